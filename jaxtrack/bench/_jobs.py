"""One bench job: a dataset item at a frame step, with or without RBOT resets, tracked and evaluated in the calling
process (a Ray worker or the driver), its results written under the bench's output folder.

    OUT/runs/<item name>/S<step>[-resets].csv            the BOP results CSV (+ .frames.jsonl), written frame by frame
    OUT/runs/<item name>/S<step>[-resets].metrics.json   the job's figures; written last, so its presence means done
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import time
import traceback

import numpy as np

from ._datasets import BenchItem

PROTOCOLS = ("rbot", "bop")
AUC_MAX_MM = 100.0  # ADD / ADD-S AUC over thresholds 0-10 cm (the YCB-Video convention, Xiang et al. 2018)
TRACKER_FIELDS = ("cues", "region", "working_shape", "pose_prior", "late_rounds", "recovery", "max_frames", "x64")


@dataclasses.dataclass(frozen=True)
class BenchSettings:
    """A bench's protocol and tracker settings (JSON-able; a resumed run must have the same tracker fields).

    Attributes:
        protocol: rbot (success at 5 cm / 5° over frame steps, with and without resets) or bop (no resets).
        frame_steps: the steps S: every S-th frame of each sequence (RBOT's frame-rate protocol).
        resets: for each job, whether a frame beyond 5 cm / 5° restarts tracking from the ground truth.
        cues, region, working_shape, pose_prior, late_rounds, recovery, max_frames: as `jaxtrack.track.track_sequence`
            (working_shape "default": the tracker's; a list [h, w]; None: native crops).
        x64: the workers compute in float64 (set from the driver's JAX config by `run_bench`).
    """

    protocol: str = "rbot"
    frame_steps: tuple = (1,)
    resets: tuple = (True, False)
    cues: tuple = ("region", "flow", "sift")
    region: str | None = None
    working_shape: object = "default"
    pose_prior: tuple | None = None
    late_rounds: tuple | None = None  # (K, f[, τ]); None: every round (the method)
    recovery: bool | None = None  # None: on for the runs without resets (`track_sequence`)
    max_frames: int | None = None
    x64: bool = False

    def __post_init__(self):
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"--protocol must be one of {', '.join(PROTOCOLS)}, got {self.protocol!r}")
        steps = tuple(int(s) for s in self.frame_steps)
        if not steps or any(s < 1 for s in steps):
            raise ValueError(f"--frame-steps must be integers ≥ 1, got {list(self.frame_steps)}")
        if not self.resets:
            raise ValueError("BenchSettings.resets: give at least one of True (RBOT resets) and False")
        if self.protocol == "bop" and any(self.resets):
            raise ValueError("--protocol bop tracks without resets (use --protocol rbot for them)")
        if self.max_frames is not None and int(self.max_frames) < 2:
            raise ValueError(f"--max-frames must be ≥ 2, got {self.max_frames}")
        if self.late_rounds is not None:
            from ..track._tracker import checked_late_rounds

            try:
                checked_late_rounds(self.late_rounds)
            except ValueError as e:
                raise ValueError(f"--late-rounds: {e}") from None

    def tracker_dict(self) -> dict:
        """The fields that change what a job computes (compared when a bench is resumed)."""
        d = dataclasses.asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items() if k in TRACKER_FIELDS}


@dataclasses.dataclass(frozen=True)
class BenchJob:
    """An item at frame step `step`, with (`reset`) or without RBOT resets."""

    item: BenchItem
    step: int
    reset: bool

    @property
    def key(self) -> str:
        return f"{self.item.name} S={self.step}{' resets' if self.reset else ''}"

    def csv(self, out: pathlib.Path) -> pathlib.Path:
        return pathlib.Path(out) / "runs" / self.item.name / f"S{self.step}{'-resets' if self.reset else ''}.csv"

    def metrics_path(self, out: pathlib.Path) -> pathlib.Path:
        csv = self.csv(out)
        return csv.with_name(csv.stem + ".metrics.json")


def jobs_for(items: list[BenchItem], settings: BenchSettings) -> list[BenchJob]:
    """Every item × frame step × reset mode (each once), an object's jobs together (a process traces the tracker's
    step once per mesh)."""
    steps = sorted({int(s) for s in settings.frame_steps})
    resets = list(dict.fromkeys(bool(r) for r in settings.resets))
    return [BenchJob(i, s, r) for i in sorted(items, key=lambda i: (i.group, i.name)) for s in steps for r in resets]


def auc(errors_mm, max_mm: float = AUC_MAX_MM, points: int = 1000) -> float:
    """Area under the accuracy-threshold curve of `errors_mm` (ADD or ADD-S) for thresholds 0..`max_mm`, in [0, 1]
    (1: every error 0; NaN errors count as failures)."""
    e = np.asarray(errors_mm, np.float64)
    if e.size == 0:
        return float("nan")
    e = np.where(np.isfinite(e), e, np.inf)
    thresholds = np.linspace(0.0, max_mm, points)
    return float(np.mean(np.mean(e[None, :] <= thresholds[:, None], axis=1)))


def job_metrics(ev) -> dict:
    """The figures of one evaluated run (`jaxtrack.track.TrackingEvaluation`): frames after the first, with truth."""
    scored = ev.has_gt & ~ev.initial
    n = int(scored.sum())
    steady = ev.time_s[2:] if len(ev.time_s) > 2 else ev.time_s[1:]
    status = {} if ev.status is None else {s: ev.status.count(s) for s in sorted(set(ev.status))}
    return {
        "frames": len(ev.im_ids), "scored": n,
        "success": float(np.mean(ev.success[scored])) if n else float("nan"),
        "add_auc": auc(ev.add_mm[scored]), "adds_auc": auc(ev.adds_mm[scored]),
        "rot_deg_mean": float(np.nanmean(ev.rot_deg[scored])) if n else float("nan"),
        "trans_mm_mean": float(np.nanmean(ev.trans_mm[scored])) if n else float("nan"),
        "resets": int(np.sum(ev.reset)) if ev.reset is not None else 0,
        "ms_median": float(np.median(steady) * 1000.0) if len(steady) else float("nan"),
        "first_s": float(ev.time_s[0]), "status": status, "diameter_mm": float(ev.diameter_mm),
    }


def _prepare_process(settings: BenchSettings, use_cache: bool) -> None:
    import cv2
    import jax

    cv2.setNumThreads(1)  # OpenCV's worker threads compete with XLA's
    # One build of the tracker's step, XLA's optimised one, unless $JAXTRACK_FUSION_EMITTERS says otherwise: a dataset's
    # figures must not depend on when a background compile finished (`jaxtrack._tiered`); over a dataset the compile is
    # paid once.
    os.environ.setdefault("JAXTRACK_FUSION_EMITTERS", "1")
    if settings.x64 and not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)
    if use_cache:
        from .._cache import enable_compilation_cache

        enable_compilation_cache()


def run_job(job: BenchJob, settings: BenchSettings, out: str | os.PathLike, use_cache: bool = True) -> dict:
    """Track and evaluate `job` in this process; writes its CSV (frame by frame) and then its metrics file.

    Returns:
        {"key", "name", ..., "error": None} with `job_metrics`' figures, or with "error" (the message and the last
        traceback lines) when the job raised: a failed sequence does not stop the others.
    """
    out = pathlib.Path(out)
    base = {"key": job.key, "name": job.item.name, "group": job.item.group, "variant": job.item.variant,
            "step": job.step, "reset": job.reset, "pid": os.getpid()}
    start = time.perf_counter()
    job.metrics_path(out).unlink(missing_ok=True)  # an older run's figures must not outlive this run
    try:
        _prepare_process(settings, use_cache)
        from ..io import frame_step_sequence
        from ..track import evaluate_tracking, track_sequence

        seq = job.item.load()
        if job.step > 1:
            seq = frame_step_sequence(seq, job.step)
        csv = job.csv(out)
        csv.parent.mkdir(parents=True, exist_ok=True)
        track_sequence(seq, obj_id=job.item.obj_id, cues=tuple(settings.cues), region=settings.region,
                       working_shape=settings.working_shape if settings.working_shape in ("default", None)
                       else tuple(settings.working_shape),
                       pose_prior=None if settings.pose_prior is None else tuple(settings.pose_prior),
                       late_rounds=None if settings.late_rounds is None else tuple(settings.late_rounds),
                       recovery=settings.recovery, reset_on_failure=job.reset, max_frames=settings.max_frames,
                       progress=False, results=csv)
        ev = evaluate_tracking(csv, seq, obj_id=job.item.obj_id)
        result = {**base, **job_metrics(ev), "wall_s": time.perf_counter() - start, "error": None,
                  "settings": settings.tracker_dict()}
    except Exception as e:  # noqa: BLE001 - a failed sequence is a value: reported, the others go on
        tail = "".join(traceback.format_exception(e)[-3:]).strip()
        return {**base, "error": f"{type(e).__name__}: {e}", "traceback": tail, "wall_s": time.perf_counter() - start}
    path = job.metrics_path(out)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(path)  # atomic: a metrics file is whole or absent
    return result


def finished_result(job: BenchJob, settings: BenchSettings, out: pathlib.Path) -> dict | None:
    """The job's metrics when it finished before with the same tracker settings (resume), else None.

    Raises:
        ValueError: its metrics were computed with other tracker settings (naming the field and the file).
    """
    from ..track import results_state

    path = job.metrics_path(out)
    if not path.is_file():
        return None
    try:
        result = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None  # unreadable: run it again
    if not isinstance(result, dict) or "key" not in result:
        return None
    if results_state(job.csv(out)).state != "complete":
        return None
    theirs, ours = result.get("settings", {}), settings.tracker_dict()
    for field in TRACKER_FIELDS:
        if theirs.get(field) != ours.get(field):
            raise ValueError(f"{path}: made with {field} = {theirs.get(field)!r}, this bench has {ours.get(field)!r}; "
                             "use another -o folder (or remove it) to bench other settings")
    return result
