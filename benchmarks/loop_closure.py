"""Loop closure: loops found, false loops, ATE with and without, fps.

Usage::

    python -m benchmarks.loop_closure --data ../shared/datasets --out out/loops
    python -m benchmarks.loop_closure --data ../shared/datasets --out out/loops --only 7scenes-redkitchen-a
    python -m benchmarks.loop_closure --data out --only loopworld --features orb --out out/lw  # after eifslam render --scene loop --out out/loopworld

For each data set under ``--data`` (the sub-folders with ``images/``) SLAM runs in filter
mode twice, as ``eifslam run --mode filter`` and ``eifslam run --mode filter
--no-loop-closure`` do it (:func:`eifslam.system.runner.run_sequence`, then
:func:`eifslam.evaluation.outputs.write_outputs`, no HTML), and every reported loop is
scored against the ground truth (which nothing in the run reads).

**When a loop is true.** Frames *k* and *j* see the same place when, with their
ground-truth poses, the point at the scene depth ``D`` on each camera's optical axis
projects inside the other camera's image, in front of it (mutual frustum overlap at the
depth the camera looks at). ``D`` is the median depth of the map features frame *k* sees
in the run's own estimate, converted to ground-truth units by the scale of the Sim(3)
alignment that ATE uses (so no per-data-set constant enters the score). Each loop also
gets ``view_overlap``: the smaller of the two shares of one camera's view (a grid of its
pixels at depth ``D``) that the other camera sees (not part of the score; for reading
loops on the edge of it).

Writes ``OUT/<dataset>-<lc|nolc>/`` (the run's outputs), ``OUT/loop_closure.json`` (one
row per data set: loops, false loops, every loop with its score, ATE and fps with and
without; rewritten after every data set) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

from ._common import command_line, discover_datasets, fmt, log, machine_info, markdown_table, split_list, write_json


def gt_pose(gt, t: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Ground-truth centre and ``R_wc`` at the timestamp nearest ``t`` (within 20 ms), or None."""
    from eifslam.geometry.rotations import quat_to_rotmat

    ts = gt.timestamps
    i = int(np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)) if len(ts) > 1 else 0
    i = i if len(ts) < 2 or abs(ts[i] - t) < abs(ts[i - 1] - t) else i - 1
    if abs(ts[i] - t) > 0.02:
        return None
    return gt.positions[i], quat_to_rotmat(gt.quats_wxyz[i])


def sees(camera, p: np.ndarray, R_wc: np.ndarray, X: np.ndarray) -> bool:
    """Whether world point ``X`` is in front of the camera and inside its image."""
    x = R_wc.T @ (X - p)
    if x[2] <= 0:
        return False
    u, v = camera.fx * x[0] / x[2] + camera.cx, camera.fy * x[1] / x[2] + camera.cy
    return bool(0 <= u <= camera.width - 1 and 0 <= v <= camera.height - 1)


def same_place(camera, pose_k, pose_j, depth: float) -> bool:
    """Mutual frustum overlap at ``depth`` (see the module docstring)."""
    (pk, Rk), (pj, Rj) = pose_k, pose_j
    return sees(camera, pj, Rj, pk + depth * Rk[:, 2]) and sees(camera, pk, Rk, pj + depth * Rj[:, 2])


def view_overlap(camera, pose_k, pose_j, depth: float, n: int = 16) -> float:
    """The smaller of the two shares of one camera's view (an ``n x n`` grid of its pixels,
    back-projected to ``depth``) that the other camera sees: how much of the place the two
    frames share, reported beside ``same_place`` (which asks only for each view's centre)."""
    def share(a, b):
        (pa, Ra), (pb, Rb) = a, b
        u, v = np.meshgrid(np.linspace(0, camera.width - 1, n), np.linspace(0, camera.height - 1, n))
        rays = np.stack([(u.ravel() - camera.cx) / camera.fx, (v.ravel() - camera.cy) / camera.fy, np.ones(n * n)], 1)
        return float(np.mean([sees(camera, pb, Rb, pa + Ra @ (depth * r)) for r in rays]))
    return min(share(pose_k, pose_j), share(pose_j, pose_k))


def median_depth(slam, frame_id: int) -> float | None:
    """Median depth of the estimated map features frame ``frame_id`` sees in its image."""
    ids, X, _ = slam.map()
    T = slam.T_wc(frame_id)
    x = (X - T[:3, 3]) @ T[:3, :3]
    c = slam.camera
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = c.fx * x[:, 0] / x[:, 2] + c.cx, c.fy * x[:, 1] / x[:, 2] + c.cy
    ok = (x[:, 2] > 0) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
    return float(np.median(x[ok, 2])) if ok.any() else None


def score_loops(slam, seq, gt, scale: float | None) -> list[dict[str, Any]]:
    """Every loop of the run with ``true`` (bool, or None when it cannot be scored)."""
    from eifslam.evaluation.outputs import loop_rows

    by_time = {f.timestamp: k for k, f in enumerate(seq.frames)}
    idx = {r.frame_id: by_time.get(r.timestamp, r.frame_id) for r in slam.results}
    rows = []
    for c, row in zip(slam.loop_closures, loop_rows(slam, idx)):
        pk = gt_pose(gt, slam.results[c.frame].timestamp) if gt is not None else None
        pj = gt_pose(gt, slam.results[c.matched_frame].timestamp) if gt is not None else None
        d = median_depth(slam, c.frame)
        ok = None
        if pk is not None and pj is not None and d is not None and scale:
            ok = same_place(seq.camera, pk, pj, d * scale)
            row["gt_distance"] = float(np.linalg.norm(pk[0] - pj[0]))
            row["gt_angle_deg"] = float(np.degrees(np.arccos(np.clip(pk[1][:, 2] @ pj[1][:, 2], -1, 1))))
            row["depth_gt_units"] = d * scale
            row["view_overlap"] = view_overlap(seq.camera, pk, pj, d * scale)
        row["true"] = ok
        rows.append(row)
    return rows


def run_one(source: Path, name: str, out_dir: Path, loop: bool, detector: str | None,
            max_frames: int | None, base=None) -> tuple[dict[str, Any], Any, Any]:
    """One filter-mode run (settings: ``base``, a ``SlamConfig``, or the defaults); returns
    its report, the Slam and the sequence."""
    from eifslam.evaluation.outputs import write_outputs
    from eifslam.io import open_source
    from eifslam.system.config import SlamConfig
    from eifslam.system.runner import run_sequence

    fe = {"detector": detector} if detector else {}
    config = (base or SlamConfig()).replace(frontend=fe, smoothing={"mode": "filter"}, loops={"enabled": loop})
    t0 = time.perf_counter()
    seq = open_source(source)
    run = run_sequence(seq, config, max_frames=max_frames, quiet=True)
    gt = seq.ground_truth() if getattr(seq, "has_ground_truth", False) else None
    rep = write_outputs(run.slam, out_dir, run.seconds, gt, {"source": str(source)}, html=False)
    rep["wall_seconds"] = time.perf_counter() - t0
    return rep, run.slam, (seq, gt)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, type=Path, help="folder of data sets")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--only", default=None, help="comma-separated data set names")
    ap.add_argument("--features", default=None, help="detector (default: the configuration's)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--no-baseline", action="store_true", help="skip the --no-loop-closure run")
    ap.add_argument("--config", type=Path, default=None,
                    help="a configuration file (as for 'eifslam run --config'); mode and loop closure are set here")
    args = ap.parse_args(argv)
    base = None
    if args.config is not None:
        from eifslam.cli.config import read_config

        base = read_config(args.config)
    only = set(split_list(args.only))
    sets = [p for p in discover_datasets(args.data) if not only or p.name in only]
    args.out.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {"command": command_line(__spec__.name, argv if argv is not None else sys.argv[1:]),
                           "machine": machine_info(), "rows": []}
    for src in sets:
        row: dict[str, Any] = {"dataset": src.name, "error": None}
        try:
            log(f"{src.name}: loop closure on")
            rep, slam, (seq, gt) = run_one(src, src.name, args.out / f"{src.name}-lc", True, args.features,
                                           args.max_frames, base)
            scale = rep.get("evaluation", {}).get("sim3", {}).get("scale") if "evaluation" in rep else None
            loops = score_loops(slam, seq, gt, scale)
            row.update(frames=rep["frames"], frames_tracked=rep["frames_tracked"], fps_lc=rep["fps"],
                       ate_lc=rep.get("ate_rmse"), ate_units=rep.get("ate_units"), loops=len(loops),
                       false_loops=sum(lp["true"] is False for lp in loops),
                       unscored_loops=sum(lp["true"] is None for lp in loops), loop_list=loops,
                       loop_ms_median=rep["stage_ms_median"].get("loop"))
            if not args.no_baseline:
                log(f"{src.name}: loop closure off")
                rep0, _, _ = run_one(src, src.name, args.out / f"{src.name}-nolc", False, args.features,
                                     args.max_frames, base)
                row.update(fps_nolc=rep0["fps"], ate_nolc=rep0.get("ate_rmse"),
                           frames_tracked_nolc=rep0["frames_tracked"])
                if row["ate_lc"] and row["ate_nolc"]:
                    row["ate_ratio"] = row["ate_lc"] / row["ate_nolc"]
        except Exception as exc:  # one data set failing must not lose the others
            row["error"] = f"{type(exc).__name__}: {exc}"
            traceback.print_exc()
        doc["rows"].append(row)
        write_json(args.out / "loop_closure.json", doc)
    heads = ["data set", "frames", "tracked", "loops", "false", "ATE lc", "ATE no lc", "ratio", "fps lc", "fps no lc"]
    print(markdown_table(heads, [[r["dataset"], fmt(r.get("frames")), fmt(r.get("frames_tracked")), fmt(r.get("loops")),
                                  fmt(r.get("false_loops")), fmt(r.get("ate_lc"), 4), fmt(r.get("ate_nolc"), 4),
                                  fmt(r.get("ate_ratio")), fmt(r.get("fps_lc")), fmt(r.get("fps_nolc"))]
                                 for r in doc["rows"]]))
    print(json.dumps([{k: v for k, v in r.items() if k != "loop_list"} for r in doc["rows"]], indent=1,
                     default=float), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
