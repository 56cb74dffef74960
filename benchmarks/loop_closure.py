"""Loop closure: loops found, false loops, ATE with and without, fps.

Usage::

    python -m benchmarks.loop_closure --data ../shared/datasets --out out/loops \
        --sets loopworld,aliasing,all --detectors sift,orb,akaze --seeds 0,1,2 --doc docs/loop_closure.md
    python -m benchmarks.loop_closure --data ../shared/datasets --out out/loops \
        --sets loopworld --seeds 0 --resume  # runs added to the same table
    python -m benchmarks.loop_closure --data ../shared/datasets --out out/loops
    python -m benchmarks.loop_closure --data ../shared/datasets --out out/loops --only 7scenes-redkitchen-a
    python -m benchmarks.loop_closure --data out --only loopworld --features orb --out out/lw  # after eifslam render --scene loop --out out/loopworld

For each data set under ``--data`` (the sub-folders with ``images/``) SLAM runs in filter
mode twice, as ``eifslam run --mode filter`` and ``eifslam run --mode filter
--no-loop-closure`` do it (:func:`eifslam.system.runner.run_sequence`, then
:func:`eifslam.evaluation.outputs.write_outputs`, no HTML), and every reported loop is
scored against the ground truth (which nothing in the run reads).

**When a loop is true.** Frames *k* and *j* see the same place when at least a fifth of
each view, taken at the depth of the scene it shows, lies inside the other view at a like
depth: a grid of each camera's pixels is back-projected to that camera's scene depth ``D``
with its ground-truth pose, and a point counts when it projects inside the other camera's
image at a depth within a factor :data:`LIKE_DEPTH` of the other camera's ``D``
(:func:`view_overlap`; ``true`` when the smaller share is at least :data:`SAME_PLACE_SHARE`).
``D`` is the median depth of the map features the frame sees in the run's own estimate,
converted to ground-truth units by the scale of the Sim(3) alignment that ATE uses (so no
per-data-set constant enters the score).

``--sets`` names data sets under ``--data`` (``all``: every one), and ``loopworld`` and
``aliasing``, the built-in scenes, rendered into ``OUT/scenes/`` when missing (``eifslam
render --scene loop|aliasing``); every set runs with every detector of ``--detectors`` and
every seed of ``--seeds`` (``frontend.seed``). Removed loops (``report.json``'s
``loops_removed``) are scored too and counted apart: the criterion is zero false loops
*kept*.

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

from ._common import (command_line, discover_datasets, fmt, log, machine_info, markdown_header, markdown_table,
                      short_error, split_list, write_json)


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


SAME_PLACE_SHARE = 0.2
"""Share of each view that must lie in the other for two frames to see the same place."""

LIKE_DEPTH = 2.0
"""A point of one view lies in the other at a like depth when its depth there is within this
factor of the other view's scene depth."""


def view_overlap(camera, pose_k, pose_j, depth_k: float, depth_j: float | None = None, n: int = 16) -> float:
    """The smaller of the two shares of one camera's view (an ``n x n`` grid of its pixels,
    back-projected to its scene depth) that the other camera sees inside its image at a
    like depth (within :data:`LIKE_DEPTH` of its own scene depth)."""
    depth_j = depth_k if depth_j is None else depth_j

    def share(a, b, da, db):
        (pa, Ra), (pb, Rb) = a, b
        u, v = np.meshgrid(np.linspace(0, camera.width - 1, n), np.linspace(0, camera.height - 1, n))
        rays = np.stack([(u.ravel() - camera.cx) / camera.fx, (v.ravel() - camera.cy) / camera.fy, np.ones(n * n)], 1)
        X = pa + (da * rays) @ Ra.T
        z = (X - pb) @ Rb[:, 2]
        like = (z > db / LIKE_DEPTH) & (z < db * LIKE_DEPTH)
        return float(np.mean([bool(ok) and sees(camera, pb, Rb, x) for x, ok in zip(X, like)]))
    return min(share(pose_k, pose_j, depth_k, depth_j), share(pose_j, pose_k, depth_j, depth_k))


def same_place(camera, pose_k, pose_j, depth_k: float, depth_j: float | None = None) -> bool:
    """At least :data:`SAME_PLACE_SHARE` of each view in the other at a like depth."""
    return view_overlap(camera, pose_k, pose_j, depth_k, depth_j) >= SAME_PLACE_SHARE


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


def score_loops(slam, seq, gt, scale: float | None, removed: bool = False) -> list[dict[str, Any]]:
    """Every loop of the run (kept, or with ``removed`` the loops taken back) with ``true``
    (bool, or None when it cannot be scored)."""
    from eifslam.evaluation.outputs import loop_rows

    by_time = {f.timestamp: k for k, f in enumerate(seq.frames)}
    idx = {r.frame_id: by_time.get(r.timestamp, r.frame_id) for r in slam.results}
    loops = [c for c, _, _ in slam.loops.removed] if removed else slam.loop_closures
    rows = []
    for c in loops:
        row = c.to_dict()
        row["frame"], row["matched_frame"] = idx.get(c.frame, c.frame), idx.get(c.matched_frame, c.matched_frame)
        pk = gt_pose(gt, slam.results[c.frame].timestamp) if gt is not None else None
        pj = gt_pose(gt, slam.results[c.matched_frame].timestamp) if gt is not None else None
        dk, dj = median_depth(slam, c.frame), median_depth(slam, c.matched_frame)
        ok = None
        if pk is not None and pj is not None and dk is not None and dj is not None and scale:
            row["view_overlap"] = view_overlap(seq.camera, pk, pj, dk * scale, dj * scale)
            ok = row["view_overlap"] >= SAME_PLACE_SHARE
            row["gt_distance"] = float(np.linalg.norm(pk[0] - pj[0]))
            row["gt_angle_deg"] = float(np.degrees(np.arccos(np.clip(pk[1][:, 2] @ pj[1][:, 2], -1, 1))))
            row["depth_gt_units"] = dk * scale
        row["true"] = ok
        rows.append(row)
    return rows


BUILTIN = {"loopworld": "loop", "aliasing": "aliasing"}
"""Built-in scenes the benchmark renders when asked for by name (``eifslam render --scene``)."""


def resolve_sets(data: Path, names: list[str], out: Path) -> list[Path]:
    """The data set folders of ``--sets``: names under ``data`` (``all``: every one), the
    built-in scenes rendered into ``out/scenes/<name>`` when missing."""
    found = {p.name: p for p in discover_datasets(data)} if data.exists() else {}
    sets: list[Path] = []
    for name in names or ["all"]:
        if name == "all":
            sets += [p for p in found.values() if p not in sets]
        elif name in found:
            sets.append(found[name])
        elif name in BUILTIN:
            dest = out / "scenes" / name
            if not (dest / "images").exists():
                from eifslam.cli.main import main as cli_main

                log(f"rendering {name}")
                if cli_main(["render", "--scene", BUILTIN[name], "--out", str(dest)]) != 0:
                    raise RuntimeError(f"eifslam render --scene {BUILTIN[name]} failed")
            sets.append(dest)
        else:
            raise SystemExit(f"no data set {name!r} under {data}")
    return sets


def run_one(source: Path, name: str, out_dir: Path, loop: bool, detector: str | None,
            max_frames: int | None, base=None, seed: int | None = None) -> tuple[dict[str, Any], Any, Any]:
    """One filter-mode run (settings: ``base``, a ``SlamConfig``, or the defaults; the front
    end's ``seed``); returns its report, the Slam and the sequence."""
    from eifslam.evaluation.outputs import write_outputs
    from eifslam.io import open_source
    from eifslam.system.config import SlamConfig
    from eifslam.system.runner import run_sequence

    fe = {"detector": detector} if detector else {}
    if seed is not None:
        fe["seed"] = int(seed)
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
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets"), help="folder of data sets")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--sets", "--only", dest="sets", default="all",
                    help="comma-separated data set names, 'all', 'loopworld', 'aliasing' (default: all)")
    ap.add_argument("--detectors", "--features", dest="detectors", default="sift,orb,akaze",
                    help="comma-separated detectors (default: sift,orb,akaze)")
    ap.add_argument("--seeds", "--seed", dest="seeds", default="0,1,2", help="comma-separated seeds (default: 0,1,2)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--no-baseline", action="store_true", help="skip the --no-loop-closure run")
    ap.add_argument("--resume", action="store_true",
                    help="keep the rows of OUT/loop_closure.json and run only the runs it does not have "
                         "(the page then lists every command that made its rows)")
    ap.add_argument("--doc", type=Path, default=None, help="also write the table as a generated Markdown page")
    ap.add_argument("--config", type=Path, default=None,
                    help="a configuration file (as for 'eifslam run --config'); mode and loop closure are set here")
    args = ap.parse_args(argv)
    base = None
    if args.config is not None:
        from eifslam.cli.config import read_config

        base = read_config(args.config)
    args.out.mkdir(parents=True, exist_ok=True)
    sets = resolve_sets(args.data, split_list(args.sets), args.out)
    detectors, seeds = split_list(args.detectors), [int(v) for v in split_list(args.seeds)]
    command = command_line(__spec__.name, argv if argv is not None else sys.argv[1:])
    doc: dict[str, Any] = {"command": command, "commands": [command], "machine": machine_info(), "rows": []}
    if args.resume and (args.out / "loop_closure.json").exists():
        old = json.loads((args.out / "loop_closure.json").read_text())
        doc["rows"] = [r for r in old.get("rows", []) if not r.get("error")]
        doc["commands"] = [c for c in old.get("commands", [old.get("command")]) if c] + [command]
    done = {(r["dataset"], r["detector"], r["seed"]) for r in doc["rows"]}
    for src in sets:
        for det in detectors:
            for seed in seeds:
                tag = f"{src.name}-{det}-s{seed}"
                if (src.name, det, seed) in done:
                    continue
                row: dict[str, Any] = {"dataset": src.name, "detector": det, "seed": seed, "error": None}
                try:
                    log(f"{tag}: loop closure on")
                    rep, slam, (seq, gt) = run_one(src, src.name, args.out / f"{tag}-lc", True, det,
                                                   args.max_frames, base, seed)
                    scale = rep.get("evaluation", {}).get("sim3", {}).get("scale") if "evaluation" in rep else None
                    loops = score_loops(slam, seq, gt, scale)
                    removed = score_loops(slam, seq, gt, scale, removed=True)
                    row.update(frames=rep["frames"], frames_tracked=rep["frames_tracked"], fps_lc=rep["fps"],
                               ate_lc=rep.get("ate_rmse"), ate_units=rep.get("ate_units"), loops=len(loops),
                               false_loops=sum(lp["true"] is False for lp in loops),
                               unscored_loops=sum(lp["true"] is None for lp in loops), loop_list=loops,
                               removed=len(removed), removed_false=sum(lp["true"] is False for lp in removed),
                               removed_list=removed, refused=len(rep.get("loops_refused", [])),
                               loop_ms_median=rep["stage_ms_median"].get("loop"))
                    if not args.no_baseline:
                        log(f"{tag}: loop closure off")
                        rep0, _, _ = run_one(src, src.name, args.out / f"{tag}-nolc", False, det,
                                             args.max_frames, base, seed)
                        row.update(fps_nolc=rep0["fps"], ate_nolc=rep0.get("ate_rmse"),
                                   frames_tracked_nolc=rep0["frames_tracked"])
                        if row["ate_lc"] and row["ate_nolc"]:
                            row["ate_ratio"] = row["ate_lc"] / row["ate_nolc"]
                except Exception as exc:  # one run failing must not lose the others
                    row["error"] = f"{type(exc).__name__}: {exc}"
                    traceback.print_exc()
                doc["rows"].append(row)
                write_json(args.out / "loop_closure.json", doc)
    heads = ["data set", "detector", "seed", "frames", "tracked", "loops kept", "false kept", "removed",
             "false removed", "refused", "ATE lc", "ATE no lc", "ratio", "error"]
    table = markdown_table(heads, [[r["dataset"], r["detector"], str(r["seed"]), fmt(r.get("frames")),
                                    fmt(r.get("frames_tracked")), fmt(r.get("loops")), fmt(r.get("false_loops")),
                                    fmt(r.get("removed")), fmt(r.get("removed_false")), fmt(r.get("refused")),
                                    fmt(r.get("ate_lc"), 4), fmt(r.get("ate_nolc"), 4), fmt(r.get("ate_ratio")),
                                    short_error(r.get("error"))] for r in doc["rows"]])
    print(table)
    if args.doc is not None:
        page = (markdown_header("Loop closure: every loop scored against the ground truth",
                                "`, then `".join(doc["commands"]), doc["machine"])
                + "\nA loop is true when at least a fifth of each view, at the depth of the scene it shows, lies "
                "inside the other view at a like depth (`benchmarks/loop_closure.py`). \"false kept\" counts "
                "the false loops in the final map; \"removed\" the loops taken back after fusion; \"refused\" "
                "the verified loops the agreement tests refused before fusion. ATE in each set's units, "
                "filter mode.\n\n" + table + "\n")
        args.doc.write_text(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
