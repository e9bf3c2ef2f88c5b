"""The paper's Fig. 6: region-only refinement from perturbed poses on clean synthetic frames.

The true pose is perturbed (in the object frame) by the twist 0.01·θ·(10, 10, 10, 0.5, 0.5, 0.5)
(mm, rad) and by twists of the same translation and rotation size in random directions; the
region-only refinement (`RegionRefiner`, default settings, float32) runs on one 640x480 frame of the
flat-coloured teapot and of the textured cracker box (`jaxtrack.synth`, coffee background), and the
mean mesh-point error is recorded. In the same run, scikit-image's `morphological_chan_vese`
(no shape prior, global statistics) segments the same crops from the perturbed silhouette; its
IoU against the generator's mask sits beside our final segmentation's IoU.

    python experiments/perturbation.py [--quick]
"""

from __future__ import annotations

import argparse
import pathlib
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from jaxtrack.cues.levelset import RegionRefiner
from jaxtrack.geometry import make_camera, se3_exp
from jaxtrack.render import make_mesh
from jaxtrack.synth import SynthConfig, render_sequence

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
BASE = np.array([10.0, 10.0, 10.0, 0.5, 0.5, 0.5])


def directions(rng, count):
    """The base twist and `count` random ones with the same translation and rotation norms."""
    out = [BASE]
    for _ in range(count):
        v, w = rng.normal(size=3), rng.normal(size=3)
        out.append(np.concatenate([v / np.linalg.norm(v) * np.linalg.norm(BASE[:3]), w / np.linalg.norm(w) * np.linalg.norm(BASE[3:])]))
    return out


def iou(a, b):
    return float((a & b).sum() / max((a | b).sum(), 1))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    from skimage.segmentation import morphological_chan_vese

    thetas = [0, 5, 10, 20] if args.quick else [0, 4, 8, 12, 16, 20, 25, 30]
    n_random = 1 if args.quick else 3
    objects = {
        "teapot": SynthConfig(object="teapot", appearance="flat", colour=(210, 180, 60), background="coffee", frames=1, size_mm=170, focal=700, motion="turntable"),
        "cracker_box": SynthConfig(object="cracker_box", appearance="texture", background="coffee", frames=1, size_mm=170, focal=700, motion="turntable"),
    }
    rows, curves = [], {}
    PROTOCOLS = ("cold", "carried")
    for name, cfg in objects.items():
        seq = render_sequence(cfg)
        mesh = make_mesh(seq["mesh"].vertices, seq["mesh"].faces)
        cam = make_camera(seq["K"], cfg.width, cfg.height)
        T_true = seq["T_cam_obj"][0][0]
        img = seq["images"][0][0].astype(np.float32)
        gt = seq["object_mask"][0][0]
        grey = cv2.cvtColor(seq["images"][0][0], cv2.COLOR_RGB2GRAY).astype(np.float64)
        v = np.asarray(seq["mesh"].vertices)
        err = lambda T: float(np.linalg.norm((v @ T[:3, :3].T + T[:3, 3]) - (v @ T_true[:3, :3].T + T_true[:3, 3]), axis=1).mean())  # noqa: B023
        refiner = RegionRefiner(mesh, cam)
        rng = np.random.default_rng(0)
        for theta in thetas:
            dirs = directions(rng, n_random)
            cv_ious = []
            for protocol in PROTOCOLS:
                errs, ious, times = [], [], []
                for d in dirs:
                    T0 = T_true @ np.asarray(se3_exp(jnp.asarray(0.01 * theta * d)))
                    refiner.reset()
                    if protocol == "carried":
                        # Densities as the tracker carries them from a previous frame tracked at the true
                        # pose (here learnt on this frame: the object and background do not change).
                        refiner.learn(img, T_true)
                    t = time.perf_counter()
                    res, (offsets, crop) = refiner(img, T0)
                    jax.block_until_ready(res.T_world_root)
                    times.append(time.perf_counter() - t)
                    errs.append(err(np.asarray(res.T_world_root, np.float64)))
                    (y0, x0), (h, w) = offsets[0], crop
                    seg = np.zeros_like(gt)
                    seg[y0 : y0 + h, x0 : x0 + w] = np.asarray(res.phi[0]) > 0
                    ious.append(iou(seg, gt))
                    if protocol == PROTOCOLS[0]:
                        # Chan-Vese from the perturbed model's silhouette (the same start as ours).
                        init = np.asarray(res.phi0[0]) > 0 if theta == 0 else None
                        if init is None:
                            from jaxtrack.render import Renderer

                            sil = np.asarray(Renderer(mesh, cam)(jnp.asarray(T0, jnp.float32)).face_id >= 0)
                            init = sil[y0 : y0 + h, x0 : x0 + w]
                        cv = morphological_chan_vese(grey[y0 : y0 + h, x0 : x0 + w], num_iter=60, init_level_set=init.astype(np.int8), smoothing=1)
                        cv_full = np.zeros_like(gt)
                        cv_full[y0 : y0 + h, x0 : x0 + w] = cv.astype(bool)
                        cv_ious.append(iou(cv_full, gt))
                errs = np.asarray(errs)
                rot_deg = np.degrees(np.linalg.norm(0.01 * theta * BASE[3:]))
                trans = np.linalg.norm(0.01 * theta * BASE[:3])
                rows.append((name, protocol, theta, rot_deg, trans, len(errs), np.mean(errs), np.median(errs), np.max(errs),
                             np.mean(errs < 1.0), np.mean(ious), np.mean(cv_ious), np.median(times[1:] if len(times) > 1 else times)))
                curves.setdefault((name, protocol), []).append((theta, np.mean(errs), np.mean(errs < 1.0)))
                print(rows[-1], flush=True)

    lines = [
        "# Region-only refinement from perturbed poses (Fig. 6)",
        "",
        f"Command: `python experiments/perturbation.py{' --quick' if args.quick else ''}`  ",
        (
            "Clean synthetic 640x480 frames (`jaxtrack.synth`, coffee background, object ~200 px), float32, default "
            f"`RegionConfig`/`region_params`; per θ the base twist plus {n_random} random directions of the same size. "
            "Protocols: *cold*, no densities (the first round learns them from Φ0 at the perturbed pose and every round "
            "re-estimates them); *carried*, densities learnt at the true pose (`RegionRefiner.learn`), as the tracker "
            "carries them from the previous frame (fixed during the refinement, warm-started level set). "
            "Error: mean distance of the mesh vertices from their true positions after refinement. "
            "IoU: final segmentation (ours) and scikit-image `morphological_chan_vese` (grey, 60 iterations, "
            "started from the perturbed silhouette) against the generator's mask."
        ),
        "",
        "| object | protocol | θ | rotation (°) | translation (mm) | trials | mean error (mm) | median (mm) | max (mm) | < 1 mm | IoU ours | IoU Chan-Vese | s / refinement |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.1f} | {r[4]:.1f} | {r[5]} | {r[6]:.2f} | {r[7]:.2f} | {r[8]:.2f} | {100 * r[9]:.0f}% | {r[10]:.3f} | {r[11]:.3f} | {r[12]:.2f} |")
    for (name, protocol), c in curves.items():
        ok, broken = [], []
        for t, _, frac in c:  # "up to": the largest θ before the first one below 90%
            (broken if broken or frac < 0.9 else ok).append(t)
        lines.append("")
        lines.append(f"{name} ({protocol}): ≥ 90% of trials below 1 mm up to θ = {max(ok) if ok else 'none'}; first θ below 90%: {min(broken) if broken else 'none'}.")
    text = "\n".join(lines) + "\n"
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "perturbation.md").write_text(text)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for (name, protocol), c in curves.items():
        c = np.asarray(c)
        ax.plot(c[:, 0], c[:, 1], "o-" if protocol == "carried" else "s--", label=f"{name}, {protocol} densities")
    ax.axhline(1.0, color="grey", ls="--", lw=0.8)
    ax.set_xlabel("θ (twist 0.01·θ·(10,10,10,0.5,0.5,0.5))")
    ax.set_ylabel("mean vertex error after refinement (mm)")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "perturbation.png", dpi=120)


if __name__ == "__main__":
    main()
