"""The loop world: does drift build up over two laps, and how far apart are the laps?

Usage::

    python -m benchmarks.loop_world --data out/loopworld --out out/loop_world
    python -m benchmarks.loop_world --data out/lw --out out/lw-bench --detectors orb,sift --mode filter
    python -m benchmarks.loop_world --data out/lw --out out/lw-bench --run-args="--no-loop-closure"

Renders the loop world (``eifslam render --scene loop``, default settings) into ``--data``
when that folder holds no ``images/``, then runs ``eifslam run DATA --mode MODE --features
DET --no-html -q [RUN_ARGS]`` per detector (a subprocess: exactly the command line, with any
option the installed eifslam has, e.g. loop-closure switches) and scores the estimate
against the ground truth (scoring only, after the run):

* frames tracked, fps, ATE RMSE after the Sim(3) alignment of ``eifslam eval``;
* **drift**: the estimate aligned (Sim(3)) on the first ``--align-fraction`` of lap 1 only,
  then the position error at the end of lap 1 and at the end of lap 2 (metres and percent
  of the distance walked);
* **lap gap**: for every frame ``i`` of lap 1, the distance between the estimated positions
  of ``i`` and ``i + n/2`` (the same place on lap 2), in metres after the full Sim(3)
  alignment, against the true distance (at most about 0.3 m). Without loop closure the
  estimate's gap grows with the drift; a loop closure should bring it back to the truth.

``--places STEP`` instead checks that the world supports place recognition: every STEP-th
frame of lap 2 is matched (ORB, ratio test 0.8, fundamental-matrix RANSAC at 1 px) against
every STEP-th frame of lap 1; it reports how often the lap-1 frame with the most inliers is
within STEP frames of the same place, the inliers of the true place and those of places
more than 40 frames away (``OUT/places.json``); no SLAM is run.

Writes ``OUT/<detector>[-TAG]/`` (the run), ``OUT/loop_world[-TAG].json`` (rows, machine,
command) and ``OUT/loop_world[-TAG].png`` (top view of ground truth and estimates, lap gap against frame);
prints a table. Timings depend on the machine's load.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ._common import (
    build_row, command_line, fmt, log, machine_info, markdown_table, short_error, split_list, write_json,
)


def run_cli(data: Path, out_dir: Path, mode: str, detector: str, extra: Sequence[str] = (),
            max_frames: int | None = None) -> dict[str, Any]:
    """``eifslam run`` in a subprocess; its ``report.json`` as a result row (or the error)."""
    import json
    import subprocess

    cmd = [sys.executable, "-c", "import sys; from eifslam.cli import main; sys.exit(main())", "run",
           str(data), "--out", str(out_dir), "--mode", mode, "--features", detector, "--no-html", "-q",
           "--force", *(["--max-frames", str(max_frames)] if max_frames else []), *extra]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0 or not (out_dir / "report.json").is_file():
        err = (r.stderr.strip().splitlines() or ["exit code %d" % r.returncode])[-1]
        log(f"FAILED {detector}: {short_error(err)}")
        return build_row("loopworld", mode, detector, None, error=err)
    return build_row("loopworld", mode, detector, json.loads((out_dir / "report.json").read_text()))


def render_if_missing(data: Path, frames: int | None = None) -> None:
    """Render the default loop world into ``data`` unless it already holds images."""
    if (data / "images").is_dir() and any((data / "images").iterdir()):
        return
    from eifslam.sim.scene.loop import make_loop_scene
    from eifslam.sim.scene.render import render_scene

    scene = make_loop_scene() if frames is None else make_loop_scene(n_frames=frames)
    log(f"rendering the loop world ({scene.n_frames} frames) into {data}")
    render_scene(scene, data)


def place_figures(data: Path, step: int = 10, n_features: int = 2000) -> dict[str, Any]:
    """Lap-2 frames against lap-1 frames: is the best match the same place?

    Parameters
    ----------
    data : Path
        The rendered loop world (two laps; ``images/`` in frame order).
    step : int
        Every ``step``-th frame of each lap is used.
    n_features : int
        ORB features per image.

    Returns
    -------
    dict
        ``queries``, ``best_within_step`` (fraction), ``true_inliers_min``/``_median``,
        ``far_inliers_max``/``_p99``/``_median`` (places more than 40 frames away).
    """
    import cv2

    files = sorted((data / "images").iterdir())
    n = len(files)
    half = n // 2
    orb = cv2.ORB_create(n_features)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)

    def feat(k: int):
        return orb.detectAndCompute(cv2.imread(str(files[k]), cv2.IMREAD_GRAYSCALE), None)

    def inliers(a, b) -> int:
        (ka, da), (kb, db) = a, b
        pairs = [p for p in bf.knnMatch(da, db, k=2) if len(p) == 2]
        good = [m for m, o in pairs if m.distance < 0.8 * o.distance]
        if len(good) < 8:
            return 0
        xa = np.float32([ka[m.queryIdx].pt for m in good])
        xb = np.float32([kb[m.trainIdx].pt for m in good])
        _, mask = cv2.findFundamentalMat(xa, xb, cv2.FM_RANSAC, 1.0, 0.999)
        return 0 if mask is None else int(mask.sum())

    lap1 = np.arange(0, half, step)
    lap2 = np.arange(half, 2 * half, step)
    f1 = [feat(int(k)) for k in lap1]
    M = np.array([[inliers(feat(int(j)), a) for a in f1] for j in lap2])
    true = lap2 - half

    def ring(a: Any, b: Any) -> Any:
        return np.abs((a - b + half // 2) % half - half // 2)

    best = lap1[M.argmax(1)]
    right = M[np.arange(len(lap2)), np.argmin(ring(lap1[None, :], true[:, None]), axis=1)]
    far = M[ring(lap1[None, :], true[:, None]) > 40]
    return dict(queries=int(len(lap2)), best_within_step=float(np.mean(ring(best, true) <= step)),
                true_inliers_min=int(right.min()), true_inliers_median=float(np.median(right)),
                far_inliers_max=int(far.max()), far_inliers_p99=float(np.percentile(far, 99)),
                far_inliers_median=float(np.median(far)), step=int(step))


def drift_figures(est_tum: Path, gt_tum: Path, align_fraction: float = 0.2) -> dict[str, Any]:
    """Drift and lap-gap figures of one estimate (see the module docstring).

    Parameters
    ----------
    est_tum, gt_tum : Path
        The run's ``trajectory.tum`` and the data's ``groundtruth.tum`` (two laps).
    align_fraction : float
        Fraction of lap 1 (from its start) the drift alignment uses.

    Returns
    -------
    dict
        ``end_lap1_error_m``, ``end_lap2_error_m`` (and ``_percent`` of the distance walked),
        ``lap_gap_median_m``, ``lap_gap_max_m``, ``lap_gap_true_max_m``; arrays ``lap_gap``
        and ``lap_gap_true`` (per lap-1 frame, NaN where a frame is missing),
        ``aligned`` (N, 3) and ``gt`` (N, 3) for the figure.
    """
    from eifslam.evaluation.metrics import align_sim3, evaluate
    from eifslam.io import read_tum

    est, gt = read_tum(est_tum), read_tum(gt_tum)
    n = len(gt.timestamps)
    half = n // 2
    idx = np.searchsorted(gt.timestamps, est.timestamps)
    ok = (idx < n) & (np.abs(gt.timestamps[np.minimum(idx, n - 1)] - est.timestamps) < 1e-3)
    P = np.full((n, 3), np.nan)
    P[idx[ok]] = est.positions[ok]
    G = gt.positions
    walked = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(G, axis=0), axis=1))])
    have = np.isfinite(P[:, 0])
    first = have & (np.arange(n) < max(3, int(align_fraction * half)))
    s_first = align_sim3(P[first], G[first])
    err = np.linalg.norm(s_first.apply(np.nan_to_num(P)) - G, axis=1)
    err[~have] = np.nan
    ev = evaluate(est, gt)
    s_all = align_sim3(P[have], G[have])
    A = np.full_like(P, np.nan)
    A[have] = s_all.apply(P[have])
    gap = np.linalg.norm(A[:half] - A[half:2 * half], axis=1)
    gap_true = np.linalg.norm(G[:half] - G[half:2 * half], axis=1)
    end1, end2 = half - 1, 2 * half - 1
    return dict(
        ate_rmse=ev.ate_rmse,
        end_lap1_error_m=float(err[end1]), end_lap2_error_m=float(err[end2]),
        end_lap1_error_percent=float(100 * err[end1] / walked[end1]),
        end_lap2_error_percent=float(100 * err[end2] / walked[end2]),
        lap_gap_median_m=float(np.nanmedian(gap)), lap_gap_max_m=float(np.nanmax(gap)),
        lap_gap_true_max_m=float(gap_true.max()),
        lap_gap=gap, lap_gap_true=gap_true, aligned=A, gt=G,
    )


def plot(rows: Sequence[dict[str, Any]], curves: dict[str, dict[str, Any]], path: Path) -> None:
    """Top view (ground truth, each estimate with lap 1 and lap 2 apart) and lap gaps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.5))
    gt = next(iter(curves.values()))["gt"]
    half = len(gt) // 2
    ax.plot(gt[:, 0], gt[:, 1], "k-", lw=0.8, label="ground truth")
    for name, c in curves.items():
        A = c["aligned"]
        ax.plot(A[:half, 0], A[:half, 1], "-", lw=0.9, label=f"{name} lap 1")
        ax.plot(A[half:, 0], A[half:, 1], "--", lw=0.9, label=f"{name} lap 2")
        bx.plot(c["lap_gap"], lw=0.9, label=f"{name}")
    bx.plot(next(iter(curves.values()))["lap_gap_true"], "k-", lw=0.8, label="ground truth")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("loop world, top view (Sim(3)-aligned on all frames)")
    ax.legend(fontsize=7)
    bx.set_xlabel("lap-1 frame i")
    bx.set_ylabel("|p(i) - p(i + n/2)| (m)")
    bx.set_title("same place, lap 1 vs lap 2")
    bx.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    """Render if needed, run, score, write JSON and PNG, print a table; returns 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="out/loopworld", help="loop world folder (rendered if empty)")
    ap.add_argument("--out", default="out/loop_world", help="output folder")
    ap.add_argument("--detectors", default="orb", help="comma-separated, e.g. orb,sift")
    ap.add_argument("--mode", default="filter", choices=("filter", "smooth", "ba"))
    ap.add_argument("--frames", type=int, default=None, help="frames to render (default: the scene's)")
    ap.add_argument("--max-frames", type=int, default=None, help="process at most this many frames")
    ap.add_argument("--align-fraction", type=float, default=0.2,
                    help="fraction of lap 1 the drift alignment uses (default 0.2)")
    ap.add_argument("--run-args", default="", help="further `eifslam run` options, one string")
    ap.add_argument("--tag", default="", help="suffix of the run folders and of the JSON/PNG names")
    ap.add_argument("--places", type=int, default=None, metavar="STEP",
                    help="only the place-recognition check, every STEP-th frame (no SLAM)")
    ap.add_argument("--score-only", action="store_true",
                    help="do not run: score the runs already in OUT/<detector>[-TAG]/")
    args = ap.parse_args(argv)
    data, out = Path(args.data), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    render_if_missing(data, args.frames)
    if args.places:
        fig = place_figures(data, args.places)
        write_json(out / "places.json", dict(fig, machine=machine_info(),
                                             command=command_line(__spec__.name, sys.argv[1:] if argv is None else argv)))
        print(markdown_table(tuple(fig), [[fmt(v) for v in fig.values()]]))
        return 0
    import shlex

    extra = shlex.split(args.run_args)
    tag = f"-{args.tag}" if args.tag else ""
    rows, curves = [], {}
    for det in split_list(args.detectors):
        log(f"running {args.mode} {det} on {data} {' '.join(extra)}")
        run_dir = out / f"{det}{tag}"
        if args.score_only:
            import json

            rep_path = run_dir / "report.json"
            rep = json.loads(rep_path.read_text()) if rep_path.is_file() else None
            row = build_row("loopworld", args.mode, det, rep, error=None if rep else f"no {rep_path}")
        else:
            row = run_cli(data, run_dir, args.mode, det, extra, args.max_frames)
        row["run_args"] = args.run_args
        if row.get("error") is None:
            d = drift_figures(run_dir / "trajectory.tum", data / "groundtruth.tum", args.align_fraction)
            curves[det] = d
            row.update({k: v for k, v in d.items() if not isinstance(v, np.ndarray)})
        rows.append(row)
    if curves:
        plot(rows, curves, out / f"loop_world{tag}.png")
    write_json(out / f"loop_world{tag}.json", dict(rows=rows, machine=machine_info(),
                                            command=command_line(__spec__.name, sys.argv[1:] if argv is None else argv)))
    cols = ("detector", "tracked_pct", "fps", "ate_rmse", "end_lap1_error_m", "end_lap2_error_m",
            "lap_gap_median_m", "lap_gap_max_m", "lap_gap_true_max_m")
    print(markdown_table(cols, [[fmt(r.get(c)) for c in cols] for r in rows]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
