"""A synthetic dataset in the RBOT dataset's own layout (`jaxtrack.io.read_rbot_sequence` reads it), for trying
`jaxtrack bench --protocol rbot` end to end without the dataset, and for its tests.

As in RBOT, every object follows the same trajectory (poses_first.txt) in front of the same background. The variants
are made from one rendering per object:

    a_regular        the rendering
    b_dynamiclight   the rendering under a brightness that changes frame by frame (0.55-1.45, a slow sine)
    c_noisy          the rendering with Gaussian noise (σ = `noise_sigma`)

RBOT's fourth variant, d_occlusion (a second object crossing in front), is not synthesised here.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import tempfile

import numpy as np

from ..io import prepare_output_folder, write_image
from ._sequences import SynthConfig, object_trajectory, render_sequence

SYNTH_RBOT_VARIANTS = ("a_regular", "b_dynamiclight", "c_noisy")


@dataclasses.dataclass(frozen=True)
class RbotSynthConfig:
    """What a synthetic RBOT-layout dataset holds (lengths in mm, angles in degrees).

    objects: SynthConfig objects (box, teapot, cracker_box, milk_truck or a mesh file), each written as the folder
    named by its file stem; variants: a subset of `SYNTH_RBOT_VARIANTS`; the rest as `SynthConfig`."""

    objects: tuple = ("box", "teapot")
    variants: tuple = ("a_regular", "c_noisy")
    frames: int = 30
    width: int = 320
    height: int = 240
    focal: float = 350.0
    distance: float = 600.0
    size_mm: float = 160.0
    step_px: float = 6.0
    step_deg: float = 3.0
    noise_sigma: float = 20.0
    background: str = "coffee"
    seed: int = 0

    def __post_init__(self):
        unknown = [v for v in self.variants if v not in SYNTH_RBOT_VARIANTS]
        if not self.variants or unknown:
            raise ValueError(f"RbotSynthConfig.variants must be some of {', '.join(SYNTH_RBOT_VARIANTS)}, got "
                             f"{list(self.variants)}")
        if not self.objects:
            raise ValueError("RbotSynthConfig.objects: name at least one object")
        names = [pathlib.Path(o).stem for o in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"RbotSynthConfig.objects: two objects share a folder name: {names}")
        for obj in self.objects:  # every object and field checked as SynthConfig checks them, before anything is written
            SynthConfig(**self._synth(obj))

    def _synth(self, obj: str, **extra) -> dict:
        return {"object": obj, "frames": self.frames, "width": self.width, "height": self.height, "focal": self.focal,
                "distance": self.distance, "size_mm": self.size_mm, "step_px": self.step_px, "step_deg": self.step_deg,
                "background": self.background, "seed": self.seed, "appearance": "photo", **extra}


def write_rbot_dataset(cfg: RbotSynthConfig, root: str | os.PathLike) -> pathlib.Path:
    """Render `cfg` into `root` in RBOT's layout: poses_first.txt, camera_calibration.txt and
    <object>/<object>.obj + <object>/frames/<variant>NNNN.png per object. Returns `root`."""
    root = prepare_output_folder(root, "write_rbot_dataset: root")
    rng = np.random.default_rng(cfg.seed)
    base = SynthConfig(**cfg._synth(cfg.objects[0], motion="random"))
    T_world_obj, T_cam_world = object_trajectory(base, np.random.default_rng(cfg.seed))
    T_cam_obj = np.einsum("kij,kjl->kil", T_cam_world, T_world_obj)
    gain = 1.0 + 0.45 * np.sin(np.linspace(0.0, 3.0 * np.pi, cfg.frames))
    with tempfile.TemporaryDirectory() as tmp:
        pose_file = pathlib.Path(tmp) / "poses.npy"
        np.save(pose_file, T_world_obj)
        for obj in cfg.objects:
            name = pathlib.Path(obj).stem
            rendered = render_sequence(SynthConfig(**cfg._synth(obj, motion="file", pose_file=str(pose_file))))
            folder = root / name / "frames"
            folder.mkdir(parents=True, exist_ok=True)
            tm = rendered["mesh"]
            import trimesh

            trimesh.Trimesh(np.asarray(tm.vertices), np.asarray(tm.faces), process=False).export(root / name / f"{name}.obj")
            clean = rendered["images"][0].astype(np.float32)
            for k, img in enumerate(clean):
                frames = {"a_regular": img, "b_dynamiclight": img * gain[k],
                          "c_noisy": img + rng.normal(scale=cfg.noise_sigma, size=img.shape)}
                for variant in cfg.variants:
                    out = np.clip(np.round(frames[variant]), 0, 255).astype(np.uint8)
                    write_image(folder / f"{variant}{k:04d}.png", out, "write_rbot_dataset")
    header = "r11\tr12\tr13\tr21\tr22\tr23\tr31\tr32\tr33\ttx\tty\ttz"
    rows = ["\t".join(f"{v:.9g}" for v in (*T[:3, :3].ravel(), *T[:3, 3])) for T in T_cam_obj]
    (root / "poses_first.txt").write_text("\n".join([header, *rows]) + "\n")
    K = rendered["K"]
    (root / "camera_calibration.txt").write_text(
        "fx\tfy\tcx\tcy\tk1\tk2\tp1\tp2\n" + "\t".join(f"{v:.9g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0, 0, 0, 0))
        + "\n")
    return root
