"""First pose from clicked points (`jaxtrack track --init-points`): accuracy of `jaxtrack.io.pose_from_points`.

Random scenes: a 640x480 camera (f = 600 px), 10 random model points in a ±80 mm box at 400-900 mm, a random
rotation (σ = 0.6 rad per axis). Cases: the first 4 points with Gaussian pixel noise σ, and all 10 with noise and
2 gross outliers (40-80 px off). Errors against the true pose; "refused" counts the poses `pose_from_points`
would refuse (RMS reprojection above 4 px). The start alone (OpenCV's EPnP or SQPnP, before jaxtrack's
Gauss-Newton refinement) is shown beside it for four points.

    python experiments/init_points.py            # writes experiments/results/init_points.md
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def scenes(trials: int, seed: int):
    from jaxtrack.geometry import make_transform, so3_exp

    rng = np.random.default_rng(seed)
    for _ in range(trials):
        T = np.asarray(make_transform(np.asarray(so3_exp(rng.normal(0, 0.6, 3))),
                                      np.array([*rng.uniform(-60, 60, 2), rng.uniform(400, 900)])))
        model = rng.uniform(-80, 80, (10, 3))
        p = model @ T[:3, :3].T + T[:3, 3]
        yield T, model, p[:, :2] / p[:, 2:] * 600 + [320, 240], rng


def opencv_only(img, model, K, flag):
    import cv2

    _, rvec, tvec = cv2.solvePnP(model, img, K, None, flags=flag)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], np.asarray(tvec).reshape(3)
    return T


def run(trials: int, noise: float, seed: int = 0) -> list[dict]:
    import cv2

    from jaxtrack.geometry import rotation_error_deg
    from jaxtrack.io import pose_from_points

    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    rows = {name: [] for name in ("4 points: EPnP alone", "4 points: SQPnP alone", "4 points: pose_from_points",
                                  "10 points, 2 outliers: pose_from_points")}
    for T, model, px, rng in scenes(trials, seed):
        four = px[:4] + rng.normal(0, noise, (4, 2))
        ten = px + rng.normal(0, noise, (10, 2))
        ten[:2] += rng.uniform(40, 80, (2, 2)) * rng.choice([-1, 1], (2, 2))
        results = {
            "4 points: EPnP alone": (opencv_only(four, model[:4], K, cv2.SOLVEPNP_EPNP), None),
            "4 points: SQPnP alone": (opencv_only(four, model[:4], K, cv2.SOLVEPNP_SQPNP), None),
            "4 points: pose_from_points": _found(pose_from_points(four, model[:4], K, max_rms_px=1e9)),
            "10 points, 2 outliers: pose_from_points": _found(pose_from_points(ten, model, K, max_rms_px=1e9)),
        }
        for name, (est, found) in results.items():
            rows[name].append({"rot": float(rotation_error_deg(est[:3, :3], T[:3, :3])),
                               "trans": float(np.linalg.norm(est[:3, 3] - T[:3, 3])),
                               "refused": bool(found is not None and found.rms_px > 4.0),
                               "outliers_found": None if found is None else sorted(np.flatnonzero(~found.inliers).tolist())})
    return rows


def _found(result):
    return result.T_cam_obj, result


def report(rows, trials: int, noise: float, command: str) -> str:
    lines = [
        "# First pose from clicked points", "",
        f"Command: `{command}`  ", f"{trials} random scenes, pixel noise σ = {noise} px; see the script's docstring.", "",
        "| case | rotation error median / max (°) | translation error median / max (mm) | refused (RMS > 4 px) | outliers found |",
        "|---|---:|---:|---:|---|",
    ]
    for name, r in rows.items():
        rot = np.array([x["rot"] for x in r])
        tr = np.array([x["trans"] for x in r])
        found = [x["outliers_found"] for x in r if x["outliers_found"] is not None]
        right = sum(f == [0, 1] for f in found) if name.startswith("10") else None
        lines.append(f"| {name} | {np.median(rot):.2f} / {rot.max():.2f} | {np.median(tr):.1f} / {tr.max():.1f} | "
                     f"{sum(x['refused'] for x in r)} | {'-' if right is None else f'both, exactly, in {right} of {len(found)}'} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--noise", type=float, default=1.0, help="pixel noise σ (px)")
    ap.add_argument("--out", default=str(RESULTS / "init_points.md"))
    args = ap.parse_args(argv)
    command = "python experiments/init_points.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = report(run(args.trials, args.noise), args.trials, args.noise, command.strip())
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text(text)
    return text


if __name__ == "__main__":
    main()
