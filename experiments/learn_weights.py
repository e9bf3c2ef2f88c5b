"""Learning the cue-weight factors by gradient (issue 12, experiment 8): gradient descent on a tracking
loss differentiated through the tracker's per-frame step, truncated over a few frames.

Parameters: θ = (log flow factor, log SIFT factor) of `TrackerParams.weights` (log-parametrised, so
the factors stay positive and steps are relative). Start: the tracker's defaults (flow 0.1, SIFT 1).

Loss of a window of K frames started at the true pose of frame s: the mean over its frames of
|T_est X − T_gt X|² / d² over the 8 corners X of the model's bounding box (camera 0, d = the box
diagonal), a smooth pose error (the rotation angle's arccos has no derivative at zero error).

Which path the derivative takes: forward mode (`jax.jvp`) through the whole `track_step` and from
frame to frame through the carried state (its float leaves: pose, segmentation Φ, local densities,
appearance model), with one tangent per parameter (vmapped). Reverse mode (`jax.grad`) stops at the
refinement loop, a `lax.while_loop` whose trip count depends on the data (rounds until the pose
settles): JAX cannot transpose it (the error is recorded in the report). Forward mode goes through
it, and through the Gauss-Newton solves by implicit differentiation (`lax.custom_root` in
`solve_pose`: the iterations are not unrolled). With two parameters forward mode is also the cheaper
direction. What has no derivative: the rasterised silhouettes and contour pixels (Φ0 and the
contour correspondences' pixels are piecewise constant in the pose), the crop offsets and SIFT
matches chosen on the host, the number of rounds; the derivative is the one of the piecewise-smooth
function between those switches. The gradient check compares it with central finite differences of
the same loss (float32, step sizes in log-factor space stated in the report).

Evaluation: tracking with RBOT resets (5 cm / 5°) on other sequences (other seeds of the same preset),
learned weights against the defaults and the paper's, through the same compiled forward-mode step
(its primal output is `track_step`'s; a second, plain program would cost another compilation).

    python experiments/learn_weights.py                   # writes experiments/results/learn_weights.{md,png,json}
    python experiments/learn_weights.py --quick --out /tmp/l.md   # smoke (occluded-box 96x72, region)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import shutil
import sys
import tempfile
import time

import numpy as np
from track_presets import preset_config, write_preset
from weight_sweep import Problem, with_factors

from jaxtrack.bench import command_line, output_path, report_header, save_text, start_experiment

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
START = (0.1, 1.0)  # the tracker's defaults: flow factor 0.1 (TRACKER_FLOW_FACTOR), SIFT factor 1
_JVP = None


def jvp_program():
    """The jitted forward-mode step: (state, its tangents (2, ...), θ) → (new state, its tangents,
    T_world_root (4, 4), dT/dθ (2, 4, 4), status). Module-level, compiled once per configuration."""
    global _JVP
    if _JVP is None:
        import equinox as eqx
        import jax
        import jax.numpy as jnp

        from jaxtrack.track import track_step

        @eqx.filter_jit
        def jvp_step(setup, state_diff, state_static, tangents, frames, matches, offsets, params, log_w, crop_shape):
            def f(diff, lw):
                state = eqx.combine(diff, state_static)
                p = with_factors(params, jnp.exp(lw[0]), jnp.exp(lw[1]))
                new, res = track_step(setup, state, frames, matches, offsets, p, crop_shape)
                new_diff, new_static = eqx.partition(new, eqx.is_inexact_array)
                return (new_diff, res.T_world_root), (new_static, res.status)

            def one(d_state, d_lw):
                (new_diff, T), (d_new, dT), (new_static, status) = jax.jvp(f, (state_diff, log_w), (d_state, d_lw), has_aux=True)
                return new_diff, T, new_static, status, d_new, dT

            eye = jnp.eye(log_w.shape[0], dtype=log_w.dtype)
            return jax.vmap(one, out_axes=(None, None, None, None, 0, 0))(tangents, eye)

        _JVP = jvp_step
    return _JVP


def box_corners(mesh) -> tuple[np.ndarray, float]:
    """(8, 3) corners of the model's bounding box (mm) and its diagonal."""
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return corners, float(np.linalg.norm(hi - lo))


def frame_loss(problem: Problem, T_world: np.ndarray, dT_world: np.ndarray | None, k: int):
    """Loss of one frame (mean squared corner error / d², camera 0) and its derivative (P,) from dT (P, 4, 4)."""
    X, d = problem.corners
    Xh = np.concatenate([X, np.ones((len(X), 1))], 1)
    A = problem.T_cam0_world @ np.asarray(T_world, np.float64)
    diff = (Xh @ A.T)[:, :3] - (Xh @ problem.gt[k].T)[:, :3]
    loss = float(np.mean(np.sum(diff**2, 1))) / d**2
    if dT_world is None:
        return loss, None
    dA = np.einsum("ij,pjk->pik", problem.T_cam0_world, np.asarray(dT_world, np.float64))
    dp = np.einsum("nk,pjk->pnj", Xh, dA)[..., :3]
    return loss, 2.0 * np.einsum("nj,pnj->p", diff, dp) / (len(X) * d**2)


def _track(problem: Problem, start: int, stop: int, log_w: np.ndarray, tangents: bool, reset: bool = False):
    """Track frames start+1 .. stop-1 from the true pose of `start` with the forward-mode step (its primal
    output is `track_step`'s), tangents of the carried state included; RBOT resets when `reset` (a reset
    restarts the tangents at zero: the true pose does not depend on θ).

    Returns:
        list per frame of (k, T_world_root (4, 4), dT/dθ (P, 4, 4), status, seconds).
    """
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from jaxtrack.cues.levelset import projected_boxes
    from jaxtrack.track import default_params, pose_errors, success_mask

    tr = problem.tracker
    program = jvp_program()
    P = len(log_w)
    lw = jnp.asarray(log_w, tr.dtype)

    def restart(k):
        state = tr.start(problem.frames(k), problem.T_world_gt[k])  # forgets the last motion (Tracker.record_motion)
        diff, static = eqx.partition(state, eqx.is_inexact_array)
        return state, diff, static, jax.tree.map(lambda a: jnp.zeros((P,) + a.shape, a.dtype), diff)

    state, diff, static, dstate = restart(start)
    out, last_crop = [], None
    for k in range(start + 1, stop):
        frames = problem.frames(k)
        before = projected_boxes(tr.mesh, tr.cameras, state.T_world_root, state.theta, tr.model)
        offsets, crop_shape = tr.crop(state.T_world_root, state.theta, before)
        if offsets is None:  # out of every image: keep the last crop (the frame fails and, with resets, restarts)
            offsets, crop_shape = last_crop
        last_crop = (offsets, crop_shape)
        matches = tr.matches(state, frames)
        params = default_params(tr.model, crop_shape, tr.dtype)
        t = time.perf_counter()
        setup = tr.setup()
        diff, T, static, status, dstate, dT = program(setup, diff, static, dstate, jnp.asarray(frames), matches,
                                                      jnp.asarray(offsets), params, lw, crop_shape)
        jax.block_until_ready(dT)
        secs = time.perf_counter() - t
        state = eqx.combine(diff, static)
        moved = projected_boxes(tr.mesh, tr.cameras, state.T_world_root, state.theta, tr.model)
        tr.record_motion(before, moved)  # the next windows follow the motion (as in Tracker.step)
        out.append((k, np.asarray(T), np.asarray(dT) if tangents else None, int(status), secs))
        if reset:
            rot, trans = pose_errors((problem.T_cam0_world @ np.asarray(T, np.float64))[None], problem.gt[k][None])
            if not bool(success_mask(np.asarray(rot), np.asarray(trans))):
                state, diff, static, dstate = restart(k)
    return out


def window_loss(problem: Problem, start: int, length: int, log_w: np.ndarray, tangents: bool = True):
    """Track frames start+1 .. start+length from the true pose of `start`, forward-mode tangents carried.

    Returns:
        (mean loss, (P,) d loss / d θ (None without tangents), statuses, seconds per step).
    """
    frames = _track(problem, start, start + length + 1, log_w, tangents)
    losses, grads = zip(*(frame_loss(problem, T, dT, k) for k, T, dT, _, _ in frames), strict=True)
    grad = np.mean(grads, 0) if tangents else None
    return float(np.mean(losses)), grad, [f[3] for f in frames], [f[4] for f in frames]


def evaluate(problem: Problem, settings: dict) -> dict:
    """RBOT tracking (5 cm / 5°, resets) of the whole sequence under each setting {name: (flow, SIFT)},
    through the same compiled forward-mode step (no second program to compile)."""
    from jaxtrack.track import pose_errors, success_mask

    out = {}
    for name, (f, s) in settings.items():
        frames = _track(problem, 0, problem.num_frames, np.log([f, s]), tangents=False, reset=True)
        T_cam = np.stack([problem.T_cam0_world @ np.asarray(T, np.float64) for _, T, _, _, _ in frames])
        rot, trans = pose_errors(T_cam, problem.gt[1:problem.num_frames])
        rot, trans = np.asarray(rot), np.asarray(trans)
        ok = np.asarray(success_mask(rot, trans))
        failed = np.nonzero(~ok)[0]
        out[name] = (f, s, {"success": float(ok.mean()), "failures": int(failed.size),
                            "first_failure": int(failed[0] + 1) if failed.size else None,
                            "rot_deg": float(rot.mean()), "trans_mm": float(trans.mean())})
    return out


def training_loss(problems, windows, length, log_w):
    """Mean window loss over the training sequences and its gradient."""
    out = [window_loss(p, s, length, log_w) for p in problems for s in windows]
    return (float(np.mean([o[0] for o in out])), np.mean([o[1] for o in out], 0),
            [x for o in out for x in o[2]], [x for o in out for x in o[3]])


def reverse_mode_probe(problem: Problem) -> str:
    """Try `jax.grad` through one step: the error JAX raises (first line), or 'works'."""
    import jax
    import jax.numpy as jnp

    from jaxtrack.track import default_params, track_step

    tr = problem.tracker
    state = tr.start(problem.frames(0), problem.T_world_gt[0])
    frames = problem.frames(1)
    offsets, crop_shape = tr.crop(np.asarray(state.T_world_root), np.asarray(state.theta))
    matches = tr.matches(state, frames)
    params = default_params(tr.model, crop_shape, tr.dtype)
    setup = tr.setup()

    def loss(lw):
        p = with_factors(params, jnp.exp(lw[0]), jnp.exp(lw[1]))
        _, res = track_step(setup, state, jnp.asarray(frames), matches, jnp.asarray(offsets), p, crop_shape)
        return jnp.sum(res.T_world_root[:3, 3])

    try:
        jax.eval_shape(jax.grad(loss), jnp.zeros(2, tr.dtype))  # tracing is enough to hit the transpose rule
    except Exception as e:  # noqa: BLE001 - the point is to report what JAX says
        msg = str(e).strip().splitlines()[0]
        return f"{type(e).__name__}: {msg[:300]}"
    return "works"


def load_problem(preset: str, scale: float, frames: int, seed: int | None, cues, folder: pathlib.Path) -> Problem:
    from jaxtrack.io import read_sequence

    cfg = preset_config(preset, scale, frames)
    if seed is not None:
        cfg = dataclasses.replace(cfg, seed=int(seed))
    sub = folder / f"seed{cfg.seed}"
    sub.mkdir(parents=True, exist_ok=True)
    return Problem(read_sequence(write_preset(preset, cfg, sub)), cues, cfg.frames)


def _fmt(x, digits=3):
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def report(args, command, history, check, probe, evals, load_start, load_end, elapsed_s, step_s, notes) -> str:
    lines = [
        "# Learning the cue weights by gradient (experiment 8)",
        "",
        *report_header(command, load_start, load_end, elapsed_s),
        "",
        (f"Training: {args.preset} seeds {args.train_seeds} at {args.width}x{args.height}, cues {args.cues}; windows of "
         f"{args.window} frames starting at the true pose of frames {args.windows}; θ = (log flow, log SIFT factor) from "
         f"(flow {START[0]:g}, SIFT {START[1]:g}); Adam, step {args.lr:g} in log-factor space. Evaluation: seeds "
         f"{args.eval_seeds}, {args.eval_frames} frames each, RBOT resets."),
        (f"Forward-mode step (2 tangents): first call incl. compile {_fmt(step_s[0], 3)} s, then median "
         f"{_fmt(float(np.median(step_s[1:])) if len(step_s) > 1 else float('nan'), 3)} s per frame."),
        "",
        "## Path of the derivative",
        "",
        "- Reverse mode (`jax.grad` through `track_step`): " + probe,
        ("- Used: forward mode (`jax.jvp`, one tangent per parameter, vmapped) through the whole step and the carried "
         "state over the window: flow and SIFT correspondences → fused weights (Section V) → prediction solve "
         "(implicit derivative, `lax.custom_root`) → the refinement `while_loop` (rounds of level-set evolution, shape "
         "matching and the fused Gauss-Newton solve, each solve differentiated implicitly) → occlusion / appearance "
         "update → next frame. Piecewise constant, so without derivative: rasterised silhouettes and Φ0, contour "
         "pixels, host crops and SIFT matches, the number of rounds."),
        "",
        "## Gradient check: forward mode against central finite differences of the same loss",
        "",
        (f"At θ = log(flow {check['at'][0]:.4g}, SIFT {check['at'][1]:.4g}), on the first training window; loss "
         f"{check['loss']:.6g}."),
        "",
        "| parameter | forward mode | " + " | ".join(f"central FD, h = {h:g}" for h in check["h"]) + " |",
        "|---|---:|" + "---:|" * len(check["h"]),
    ]
    for p, name in enumerate(("log flow factor", "log SIFT factor")):
        lines.append(f"| {name} | {check['jvp'][p]:.4g} | " + " | ".join(f"{fd[p]:.4g}" for fd in check["fd"]) + " |")
    lines += [
        "",
        "## Training",
        "",
        "| iteration | flow factor | SIFT factor | training loss | d/d log flow | d/d log SIFT | steps not OK |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for i, h in enumerate(history):
        lines.append(f"| {i} | {h['flow']:.4g} | {h['sift']:.4g} | {h['loss']:.5g} | {h['grad'][0]:.3g} | {h['grad'][1]:.3g} | "
                     f"{h['not_ok']} |")
    lines += [
        "",
        "## Evaluation on held-out sequences (RBOT resets)",
        "",
        "| sequence | weights | flow | SIFT | success | failures | first failure | mean rot ° | mean trans mm |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for seq_name, rows in evals.items():
        for name, (f, s, r) in rows.items():
            lines.append(f"| {seq_name} | {name} | {f:.3g} | {s:.3g} | {100 * r['success']:.0f} % | {r['failures']} | "
                         f"{'none' if r['first_failure'] is None else r['first_failure']} | {r['rot_deg']:.2f} | "
                         f"{r['trans_mm']:.1f} |")
    lines += ["", "Notes:", *[f"- {n}" for n in notes if n]]
    return "\n".join(lines) + "\n"


def plot(path, history, evals) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    it = np.arange(len(history))
    ax[0].plot(it, [h["loss"] for h in history], "o-")
    ax[0].set_xlabel("iteration")
    ax[0].set_ylabel("training loss")
    ax2 = ax[0].twinx()
    ax2.semilogy(it, [h["flow"] for h in history], "s--", color="C1", label="flow factor")
    ax2.semilogy(it, [h["sift"] for h in history], "^--", color="C2", label="SIFT factor")
    ax2.legend(fontsize=8)
    names = list(next(iter(evals.values()))) if evals else []
    width = 0.8 / max(len(names), 1)
    for i, name in enumerate(names):
        vals = [rows[name][2]["rot_deg"] for rows in evals.values()]
        ax[1].bar(np.arange(len(evals)) + (i - (len(names) - 1) / 2) * width, vals, width, label=name)
    ax[1].set_xticks(range(len(evals)), list(evals), fontsize=8)
    ax[1].set_ylabel("mean rotation error (°), held out")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _ints(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError as e:
        raise SystemExit(f"learn_weights: bad integer list {text!r}") from e


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: occluded-box 96x72, region, one window of 2 frames")
    ap.add_argument("--preset", default="noisy-moving-camera")
    ap.add_argument("--cues", default="region+flow+sift")
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--train-seeds", default="11,12")
    ap.add_argument("--eval-seeds", default="13,14")
    ap.add_argument("--windows", default="0,4", help="first frames of the training windows")
    ap.add_argument("--window", type=int, default=3, help="frames per window (truncation)")
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--lr", type=float, default=0.3, help="Adam step in log-factor space")
    ap.add_argument("--fd-steps", default="0.03,0.003", help="central finite-difference steps (log space)")
    ap.add_argument("--eval-frames", type=int, default=10)
    ap.add_argument("--budget-min", type=float, default=None, help="start no new iteration / evaluation after this")
    ap.add_argument("--no-probe", action="store_true", help="skip the reverse-mode probe (a trace of the step)")
    ap.add_argument("--seq-dir", default=None)
    ap.add_argument("--out", default=None, help="markdown (default experiments/results/learn_weights.md; --quick: none)")
    ap.add_argument("--plot", default=None, help="plot (default experiments/results/learn_weights.png; --quick: none)")
    ap.add_argument("--json", default=None, help="JSON (default experiments/results/learn_weights.json; --quick: none)")
    args = ap.parse_args(argv)
    if args.quick:  # the sequence and step configuration of track_presets.py --quick
        args.preset, args.cues, args.scale, args.train_seeds, args.eval_seeds = "occluded-box", "region", 0.15, "0", "0"
        args.windows, args.window, args.iterations, args.eval_frames, args.fd_steps = "0", 2, 1, 4, "0.03"
        args.no_probe = True
    cues = tuple(c for c in args.cues.split("+") if c)
    train_seeds, eval_seeds, windows = _ints(args.train_seeds), _ints(args.eval_seeds), _ints(args.windows)
    fd_steps = [float(h) for h in args.fd_steps.split(",") if h.strip()]
    frames_needed = max(windows) + args.window + 1
    command = command_line(__file__, argv)
    clock = start_experiment(cache=False)

    def log(m):
        print(f"[learn_weights] {m} ({clock.minutes():.1f} min)", file=sys.stderr, flush=True)

    seq_dir = pathlib.Path(args.seq_dir) if args.seq_dir else pathlib.Path(tempfile.mkdtemp(prefix="learn_weights_"))
    notes, step_s, history = [], [], []
    try:
        train = [load_problem(args.preset, args.scale, frames_needed, s, cues, seq_dir) for s in train_seeds]
        for p in train:
            p.corners = box_corners(p.tracker.mesh)
        cfg = preset_config(args.preset, args.scale, frames_needed)
        args.width, args.height = cfg.width, cfg.height
        probe = "not run (--no-probe)" if args.no_probe else reverse_mode_probe(train[0])
        log(f"reverse-mode probe: {probe}")
        # Gradient check at the start point, on the first training window.
        theta0 = np.log(np.array(START))
        l0, g0, _, secs = window_loss(train[0], windows[0], args.window, theta0)
        step_s += secs
        log(f"loss {l0:.5g}, forward-mode gradient {g0}")
        fds = []
        for h in fd_steps:
            fd = []
            for p in range(2):
                e = np.zeros(2)
                e[p] = h
                lp = window_loss(train[0], windows[0], args.window, theta0 + e, tangents=False)[0]
                lm = window_loss(train[0], windows[0], args.window, theta0 - e, tangents=False)[0]
                fd.append((lp - lm) / (2 * h))
            fds.append(fd)
            log(f"central FD h={h}: {fd}")
        check = {"at": START, "loss": l0, "jvp": g0.tolist(), "h": fd_steps, "fd": fds}
        # Adam on θ.
        theta, m, v = theta0.copy(), np.zeros(2), np.zeros(2)
        best = (np.inf, theta0.copy())
        for it in range(args.iterations + 1):
            if clock.over(args.budget_min):
                notes.append(f"Training stopped after {it} evaluations: the time budget (--budget-min {args.budget_min:g}) "
                             "was spent; not run (time): the remaining iterations.")
                break
            loss, grad, statuses, secs = training_loss(train, windows, args.window, theta)
            step_s += secs
            history.append({"flow": float(np.exp(theta[0])), "sift": float(np.exp(theta[1])), "loss": loss,
                            "grad": grad.tolist(), "not_ok": int(sum(s != 0 for s in statuses))})
            log(f"iteration {it}: factors {np.exp(theta).round(4)}, loss {loss:.5g}, grad {grad}")
            if loss < best[0]:
                best = (loss, theta.copy())
            if it == args.iterations:
                break
            m = 0.9 * m + 0.1 * grad
            v = 0.999 * v + 0.001 * grad**2
            mh, vh = m / (1 - 0.9 ** (it + 1)), v / (1 - 0.999 ** (it + 1))
            theta = theta - args.lr * mh / (np.sqrt(vh) + 1e-12)
        learned = np.exp(best[1])
        notes.append(f"Learned factors: the iterate with the lowest training loss: flow {learned[0]:.4g}, SIFT {learned[1]:.4g}.")
        # Held-out evaluation: paper, defaults and learned weights in one vmapped program per sequence.
        evals = {}
        settings = {"paper (1, 1)": (1.0, 1.0), "default (0.1, 1)": START, "learned": tuple(learned),
                    "learned flow, SIFT 1": (float(learned[0]), 1.0)}
        for s in eval_seeds:
            if clock.over(args.budget_min):
                notes.append(f"Not run (time): evaluation on seed {s}.")
                continue
            ev = load_problem(args.preset, args.scale, args.eval_frames, s, cues, seq_dir)
            evals[f"{args.preset} seed {s}"] = evaluate(ev, settings)
            log(f"evaluated seed {s}")
    finally:
        if not args.seq_dir:
            shutil.rmtree(seq_dir, ignore_errors=True)
    notes += [
        (f"Reduced for the 2-core budget: scale {args.scale:g} of 640x480, {len(train_seeds)} training sequence(s) x "
         f"{len(windows)} window(s) of {args.window} frames, {args.iterations} Adam steps, {len(eval_seeds)} held-out "
         f"sequence(s) of {args.eval_frames} frames; float64 gradient check not run (a second compilation of the "
         "forward-mode step)."),
        ("Finite differences cross the switches the derivative ignores (contour pixels, rounds, crops): where the "
         "loss is flat between switches and jumps at them, forward mode and FD can disagree; both are shown as measured."),
    ]
    text = report(args, command, history, check, probe, evals, clock.load_start, os.getloadavg(), clock.elapsed_s(),
                  step_s, notes)
    print(text)
    save_text(output_path(args.out, RESULTS / "learn_weights.md", args.quick), text)
    figure = output_path(args.plot, RESULTS / "learn_weights.png", args.quick)
    if figure is not None and history:
        plot(figure, history, evals)
    data = {"command": command, "history": history, "check": check, "probe": probe, "learned": learned.tolist(),
            "evals": {k: {n: {"flow": f, "sift": s, **r} for n, (f, s, r) in v.items()} for k, v in evals.items()}}
    save_text(output_path(args.json, RESULTS / "learn_weights.json", args.quick), json.dumps(data, indent=1))
    return {"history": history, "check": check, "probe": probe, "learned": learned, "evals": evals, "text": text}


if __name__ == "__main__":
    main()
