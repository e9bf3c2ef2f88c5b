"""Flow compile time against run time: the pyramid unrolled (every level its own compiled copy of the solver) or
its coarse levels sharing one compiled level (`FlowConfig.shared_levels_from`, issue 23).

A synthetic pair (a band-limited texture that can be sampled exactly, turned by 3° about a point off the centre
and shifted by (2.5, -1.5) px, so the true flow is known everywhere) at three settings:

- the tracker's working resolution: 96x128, η = ½ down to 4 px (6 levels), 4 warps x 1 lagged x 10 SOR sweeps;
- a chain's native crop: 240x320, down to 16 px (5 levels), the same iterations;
- `jaxtrack flow`'s Middlebury setting at 480x640 (`middlebury_config`, 3x3 median after every warp).

Per setting and k = 0 (unrolled), 1, 2: XLA compile time (`jit(...).lower(...).compile()`, no on-disk cache),
the median run time of the compiled program, the largest difference to the unrolled flow and the EPE against the
truth over the frame less a 16 px border.

    python experiments/flow_compile.py            # writes experiments/results/flow_compile.md
    python experiments/flow_compile.py --quick    # smoke run: 32x48, k = 0 and 1, no file
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from jaxtrack.bench import command_line, output_path, report_header, save_text, start_experiment

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def textured_pair(h: int, w: int, seed: int = 0):
    """(img1, img2, true flow (h, w, 2)): img2(x + flow(x)) = img1(x) for a rotation + shift of a sinusoid sum."""
    rng = np.random.default_rng(seed)
    n = 16
    freq = rng.uniform(-0.35, 0.35, size=(n, 2)) * (128.0 / max(w, 128)) ** 0.5
    phase = rng.uniform(0, 2 * np.pi, size=n)
    amp = rng.uniform(6, 16, size=n)

    def sample(x, y):
        return 128 + sum(a * np.sin(fx * x + fy * y + p) for a, (fx, fy), p in zip(amp, freq, phase, strict=True))

    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    c = np.array([0.45 * w, 0.55 * h])
    a = np.radians(3.0)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    shift = np.array([2.5, -1.5])
    p = np.stack([x - c[0], y - c[1]], -1)
    moved = np.einsum("ij,hwj->hwi", R, p) + c + shift  # where x goes
    back = np.einsum("ij,hwj->hwi", R.T, p - shift) + c  # img2(q) = img1(R⁻¹(q − c − s) + c)
    img1, img2 = sample(x, y), sample(back[..., 0], back[..., 1])
    return img1.astype(np.float32), img2.astype(np.float32), (moved - np.stack([x, y], -1)).astype(np.float32)


def measure(shape, config, params, ks, repeats: int) -> list[dict]:
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxtrack.cues.flow._solver import flow_core

    h, w = shape
    img1, img2, truth = textured_pair(h, w)
    m = min(16, h // 4)  # the scored interior: the frame less a 16 px border (less at the smoke run's size)
    border = np.zeros((h, w), bool)
    border[m:h - m, m:w - m] = True
    rows, base = [], None
    for k in ks:
        cfg = dataclasses.replace(config, shared_levels_from=k)
        fn = jax.jit(lambda a, b, cfg=cfg: flow_core(a, b, params, cfg, jnp.ones((h, w)), jnp.ones((h, w), bool), None,
                                                     1.0, jnp.float32).flow)
        t = time.perf_counter()
        compiled = fn.lower(img1, img2).compile()
        compile_s = time.perf_counter() - t
        flow = np.asarray(compiled(img1, img2))
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            compiled(img1, img2).block_until_ready()
            times.append(time.perf_counter() - t)
        base = flow if base is None else base
        epe = float(np.mean(np.linalg.norm(flow - truth, axis=-1)[border]))
        rows.append({"k": k, "compile_s": compile_s, "run_ms": 1e3 * float(np.median(times)),
                     "max_diff": float(np.abs(flow - base).max()), "epe": epe})
        print(f"[flow_compile] {h}x{w} k={k}: compile {compile_s:.1f} s, run {rows[-1]['run_ms']:.1f} ms, "
              f"max |Δ| {rows[-1]['max_diff']:.1e} px, EPE {epe:.3f} px", file=sys.stderr, flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: one 32x48 setting, k = 0 and 1, no file")
    ap.add_argument("--repeats", type=int, default=15, help="timed runs per program")
    ap.add_argument("--out", default=None, help="markdown output (default experiments/results/flow_compile.md)")
    args = ap.parse_args(argv)
    command = command_line(__file__, argv)

    from jaxtrack.cues.flow import FlowConfig, middlebury_config, middlebury_params, rigid_params
    from jaxtrack.image import pyramid_shapes

    clock = start_experiment(cache=False)  # compile times: nothing from the on-disk cache
    tracker = {"eta": 0.5, "warps": 4, "lagged": 1, "sor_iters": 10}
    if args.quick:
        settings = [("smoke", (32, 48), FlowConfig(min_size=4, **tracker), rigid_params(), (0, 1))]
        args.repeats = min(args.repeats, 2)
    else:
        settings = [
            ("tracker, working resolution", (96, 128), FlowConfig(min_size=4, **tracker), rigid_params(), (0, 1, 2)),
            ("chain, native crop", (240, 320), FlowConfig(min_size=16, **tracker), rigid_params(), (0, 1, 2)),
            ("`jaxtrack flow` (Middlebury setting)", (480, 640), middlebury_config(), middlebury_params(), (0, 2)),
        ]
    results = []
    for name, shape, config, params, ks in settings:
        levels = len(pyramid_shapes(*shape, config.eta, config.min_size, config.max_levels))
        results.append((name, shape, levels, measure(shape, config, params, ks, args.repeats)))
    lines = ["# Flow compile time: unrolled pyramid levels against shared coarse levels", ""]
    lines += report_header(command, clock.load_start, os.getloadavg(), clock.elapsed_s())
    legend = ("k = `FlowConfig.shared_levels_from` (0: every level its own compiled copy; k: the levels from k on share "
              "one, padded to level k's shape). Synthetic pair: 3° rotation + (2.5, −1.5) px shift, true flow known; EPE "
              "over the frame less a 16 px border; max |Δ| against k = 0.")
    lines += ["", legend, "",
              "| setting | shape | levels | k | compile (s) | run (ms) | max abs diff to k = 0 (px) | EPE (px) |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for name, shape, levels, rows in results:
        for r in rows:
            lines.append(f"| {name} | {shape[0]}x{shape[1]} | {levels} | {r['k']} | {r['compile_s']:.1f} | "
                         f"{r['run_ms']:.1f} | {r['max_diff']:.1e} | {r['epe']:.3f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    save_text(output_path(args.out, os.path.join(RESULTS, "flow_compile.md"), args.quick), text)
    return results


if __name__ == "__main__":
    main()
