"""The bench's tables: per job (CSV), per object × variant and overall (markdown), and one plot.

    OUT/bench.csv   one row per sequence × frame step × reset mode
    OUT/bench.md    the success rate at 5 cm / 5° per object × variant, for each frame step with and without resets;
                    the mean over objects per variant; ADD / ADD-S AUC and ms per frame; the failed sequences
    OUT/bench.png   the success rate per variant against the frame step, with (solid) and without (dashed) resets
"""

from __future__ import annotations

import csv as csv_module
import pathlib

import numpy as np

CSV_FIELDS = ("name", "group", "variant", "step", "reset", "frames", "scored", "success", "add_auc", "adds_auc",
              "rot_deg_mean", "trans_mm_mean", "resets", "ms_median", "first_s", "wall_s", "error")


def _pct(v) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{100.0 * v:.1f}"


def _num(v, digits: int = 1) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def _mean(values) -> float:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(values)) if values else float("nan")


def _mode(step: int, reset: bool) -> str:
    return f"S = {step}, {'with' if reset else 'without'} resets"


def write_csv(results: list[dict], path: pathlib.Path) -> pathlib.Path:
    with path.open("w", newline="") as f:
        w = csv_module.writer(f)
        w.writerow(CSV_FIELDS)
        for r in sorted(results, key=lambda r: (r["name"], r["step"], not r["reset"])):
            w.writerow([("" if r.get(k) is None else r.get(k, "")) if k != "error" else (r.get("error") or "")
                        for k in CSV_FIELDS])
    return path


def markdown(results: list[dict], title: str, header_lines: list[str]) -> str:
    """The bench's markdown report (see the module docstring)."""
    ok = [r for r in results if not r.get("error")]
    failed = [r for r in results if r.get("error")]
    lines = [f"# {title}", "", *header_lines, ""]
    modes = sorted({(r["step"], r["reset"]) for r in results}, key=lambda m: (m[0], not m[1]))
    variants = sorted({r["variant"] for r in results})
    groups = sorted({r["group"] for r in results})
    by = {(r["group"], r["variant"], r["step"], r["reset"]): r for r in ok}
    lines += ["## Success rate at 5 cm / 5° (%), mean over objects", "",
              "| | " + " | ".join(variants) + " | all |", "|---|" + "---:|" * (len(variants) + 1)]
    for step, reset in modes:
        cells = [_mean([by[(g, v, step, reset)]["success"] for g in groups if (g, v, step, reset) in by]) for v in variants]
        every = _mean([r["success"] for r in ok if (r["step"], r["reset"]) == (step, reset)])
        lines.append(f"| {_mode(step, reset)} | " + " | ".join(_pct(c) for c in cells) + f" | {_pct(every)} |")
    for step, reset in modes:
        lines += ["", f"## Per object, {_mode(step, reset)}: success % (ADD AUC / ADD-S AUC)", "",
                  "| object | " + " | ".join(variants) + " | mean |", "|---|" + "---:|" * (len(variants) + 1)]
        for g in groups:
            cells = []
            for v in variants:
                r = by.get((g, v, step, reset))
                cells.append("" if r is None else f"{_pct(r['success'])} ({_num(r['add_auc'], 2)} / {_num(r['adds_auc'], 2)})")
            mean = _mean([by[(g, v, step, reset)]["success"] for v in variants if (g, v, step, reset) in by])
            lines.append(f"| {g} | " + " | ".join(cells) + f" | {_pct(mean)} |")
    lines += ["", "## Per sequence", "",
              ("| sequence | mode | frames | success % | ADD AUC | ADD-S AUC | rot ° mean | resets | ms/frame (median) | "
              "first frame s |"), "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in sorted(ok, key=lambda r: (r["name"], r["step"], not r["reset"])):
        lines.append(f"| {r['name']} | {_mode(r['step'], r['reset'])} | {r['frames']} | {_pct(r['success'])} | "
                     f"{_num(r['add_auc'], 3)} | {_num(r['adds_auc'], 3)} | {_num(r['rot_deg_mean'], 2)} | {r['resets']} | "
                     f"{_num(r['ms_median'], 1)} | {_num(r['first_s'], 1)} |")
    if failed:
        lines += ["", f"## Failed ({len(failed)})", ""]
        lines += [f"- {r['key']}: {r['error']}" for r in sorted(failed, key=lambda r: r["key"])]
    return "\n".join(lines) + "\n"


def plot(results: list[dict], path: pathlib.Path) -> pathlib.Path | None:
    """The success rate per variant against the frame step (None when matplotlib is not installed)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    ok = [r for r in results if not r.get("error")]
    fig, ax = plt.subplots(figsize=(6, 4))
    for i, v in enumerate(sorted({r["variant"] for r in ok})):
        for reset in (True, False):
            rows = [r for r in ok if r["variant"] == v and r["reset"] == reset]
            steps = sorted({r["step"] for r in rows})
            if not steps:
                continue
            ys = [100.0 * _mean([r["success"] for r in rows if r["step"] == s]) for s in steps]
            ax.plot(steps, ys, marker="o", color=f"C{i}", linestyle="-" if reset else "--",
                    label=f"{v} ({'resets' if reset else 'no resets'})")
    ax.set_xlabel("frame step S")
    ax.set_ylabel("success at 5 cm / 5° (%)")
    ax.set_ylim(0, 102)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    else:  # no run finished (a bench past its timeout): say so instead of an empty legend
        ax.text(0.5, 0.5, "no finished runs", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
