"""The sequences of a dataset on disk, as `BenchItem`s: small picklable descriptions that a worker (another process
or another machine of a Ray cluster) turns into a `jaxtrack.io.Sequence` itself.

Layouts:
    rbot   RBOT's own (poses_first.txt, camera_calibration.txt, <object>/frames/<variant>NNNN.png): an object ×
           variant per item (`jaxtrack.io.read_rbot_sequence`); d_occlusion's occluding squirrel is not tracked.
    bcot   BCOT's (models/, <scene>/K.txt, <scene>/<object>/pose.txt): a scene × object per item.
    bop    the BOP toolkit's layout (DATASET/models/, DATASET/<split>/<scene>/: `jaxtrack.io.read_bop_scene`), or this
           project's (`jaxtrack.io.read_sequence`): one sequence folder, or a folder of them; an item per scene or
           sequence and object with a first ground-truth pose (a scene with several objects gives one track per object).
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

import numpy as np

LAYOUTS = ("rbot", "bcot", "bop")


@dataclasses.dataclass(frozen=True)
class BenchItem:
    """One sequence of a dataset, tracked from its first ground-truth pose.

    Attributes:
        name: unique within the dataset, a relative path ("ape/a_regular", "scene1/cat", "seq3/obj_2").
        layout: rbot | bcot | bop; dataset: the dataset folder (every node of a cluster sees it at this path).
        parts: the reader's arguments after the dataset: (object, variant) / (scene, object) / (sequence folder,).
        obj_id: the tracked object of the sequence.
        group: what the per-object tables group by (the object's name); variant: the column (RBOT variant, BCOT
            scene, BOP sequence).
    """

    name: str
    layout: str
    dataset: str
    parts: tuple
    obj_id: int = 1
    group: str = ""
    variant: str = ""

    def load(self):
        """The item's `jaxtrack.io.Sequence`."""
        from ..io import read_bcot_sequence, read_bop_scene, read_rbot_sequence, read_sequence

        if self.layout == "rbot":
            return read_rbot_sequence(self.dataset, *self.parts)
        if self.layout == "bcot":
            return read_bcot_sequence(self.dataset, *self.parts)
        if self.layout == "bop":
            if len(self.parts) == 2:  # the BOP toolkit's DATASET/<split>/<scene>
                return read_bop_scene(self.dataset, *self.parts)
            return read_sequence(pathlib.Path(self.dataset) / self.parts[0] if self.parts[0] else self.dataset)
        raise ValueError(f"BenchItem {self.name}: unknown layout {self.layout!r} (one of {', '.join(LAYOUTS)})")


def detect_layout(dataset: str | os.PathLike) -> str:
    """rbot, bcot or bop, from the files in `dataset`.

    Raises:
        ValueError: the folder is missing or is none of the layouts (naming what each needs).
    """
    from ..io import is_bop_folder

    root = pathlib.Path(dataset)
    if not root.is_dir():
        raise ValueError(f"{root}: no such dataset folder")
    if (root / "poses_first.txt").is_file() and (root / "camera_calibration.txt").is_file():
        return "rbot"
    if (root / "models").is_dir() and any((p / "K.txt").is_file() for p in root.iterdir() if p.is_dir()):
        return "bcot"
    if is_bop_folder(root) or any(is_bop_folder(p) for p in root.iterdir() if p.is_dir()):
        return "bop"
    raise ValueError(f"{root}: not a dataset layout jaxtrack reads: RBOT needs poses_first.txt and "
                     "camera_calibration.txt, BCOT models/ and <scene>/K.txt, BOP a sequence folder (models/ beside "
                     "numbered camera folders) or a folder of them")


def _first_posed(seq) -> list[int]:
    """The objects of `seq` with a mesh and a ground-truth pose in the first frame."""
    view = seq.views[0]
    return [o for o in sorted(seq.model_paths)
            if o in view.T_cam_obj and np.all(np.isfinite(view.T_cam_obj[o][0]))]


def _bop_items(root: pathlib.Path) -> list[BenchItem]:
    from ..io import SequenceError, bop_scenes, is_bop_folder, read_bop_scene, read_sequence

    scenes = bop_scenes(root)
    if scenes:  # the BOP toolkit's layout: DATASET/models + DATASET/<split>/<scene>
        items = []
        for split, scene in scenes:
            if split.startswith("train"):  # train / train_pbr / train_synt: random views, not sequences
                continue
            label = f"{split}/{scene}"
            try:
                posed = _first_posed(read_bop_scene(root, split, scene))
            except SequenceError:  # reported as a failed run (its load raises again, with the message), not fatal
                items.append(BenchItem(f"{label}/unreadable", "bop", str(root), (split, scene), 0, "unreadable", label))
                continue
            items += [BenchItem(f"{label}/obj_{o}", "bop", str(root), (split, scene), o, f"obj_{o}", label)
                      for o in posed]
        return items
    folders = [root] if is_bop_folder(root) else sorted(p for p in root.iterdir() if p.is_dir() and is_bop_folder(p))
    items = []
    for folder in folders:
        rel = "" if folder == root else folder.name
        label = rel or folder.name
        items += [BenchItem(f"{label}/obj_{o}", "bop", str(root), (rel,), o, f"obj_{o}", label)
                  for o in _first_posed(read_sequence(folder))]
    return items


def find_items(dataset: str | os.PathLike, layout: str = "auto", *, objects: list[str] | None = None,
               variants: list[str] | None = None) -> list[BenchItem]:
    """Every sequence of `dataset` as a `BenchItem` (sorted by name), optionally only `objects` (group names) and
    `variants` (RBOT variants, BCOT scenes, BOP sequences).

    Raises:
        ValueError: an unknown layout, a folder that is not one, or a filter that keeps nothing (naming what is there).
    """
    from ..io import bcot_sequences, rbot_sequences

    root = pathlib.Path(dataset).resolve()
    if not root.is_dir():
        raise ValueError(f"{dataset}: no such dataset folder")
    if layout == "auto":
        layout = detect_layout(root)
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be auto or one of {', '.join(LAYOUTS)}, got {layout!r}")
    if layout == "rbot":
        items = [BenchItem(f"{o}/{v}", "rbot", str(root), (o, v), 1, o, v) for o, v in rbot_sequences(root)]
    elif layout == "bcot":
        items = [BenchItem(f"{s}/{o}", "bcot", str(root), (s, o), 1, o, s) for s, o in bcot_sequences(root)]
    else:
        items = _bop_items(root)
    if not items:
        raise ValueError(f"{root}: no {layout.upper()} sequence in it")
    for what, keep, field in (("objects", objects, "group"), ("variants", variants, "variant")):
        if keep:
            have = sorted({getattr(i, field) for i in items})
            unknown = [k for k in keep if k not in have]
            if unknown:
                raise ValueError(f"--{what}: {', '.join(unknown)} not in {root} (it has {', '.join(have)})")
            items = [i for i in items if getattr(i, field) in keep]
    return sorted(items, key=lambda i: i.name)
