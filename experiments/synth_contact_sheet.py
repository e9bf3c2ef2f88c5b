"""Contact sheet of every synthetic preset: frames 0, ⅓, ⅔ and last of camera 0, with the ground-truth
silhouette outlined by the tracker's own JAX renderer (a visual cross-check of the two renderers).

    python experiments/synth_contact_sheet.py   # writes experiments/results/synth_contact_sheet.png
"""

from __future__ import annotations

import dataclasses
import pathlib

import cv2
import jax.numpy as jnp
import numpy as np

import jaxtrack as jt
from jaxtrack.render import Renderer, make_mesh
from jaxtrack.synth import PRESETS, render_sequence

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def main():
    rows = []
    for name, cfg in PRESETS.items():
        cfg = dataclasses.replace(cfg, frames=min(cfg.frames, 24))
        seq = render_sequence(cfg)
        tm = seq["mesh"]
        renderer = Renderer(make_mesh(tm.vertices, tm.faces), jt.make_camera(seq["K"], cfg.width, cfg.height))
        tiles = []
        n = len(seq["images"][0])
        for k in (0, n // 3, 2 * n // 3, n - 1):
            img = cv2.cvtColor(seq["images"][0][k], cv2.COLOR_RGB2BGR)
            sil = np.asarray(renderer(jnp.asarray(seq["T_cam_obj"][0][k], jnp.float32)).silhouette).astype(np.uint8)
            contours, _ = cv2.findContours(sil, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, contours, -1, (0, 255, 0), 1)
            tiles.append(cv2.resize(img, (320, 240)))
        row = np.concatenate(tiles, 1)
        cv2.putText(row, name, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
        rows.append(row)
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "synth_contact_sheet.png"
    cv2.imwrite(str(out), np.concatenate(rows, 0))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
