"""Per-frame incremental recovery on a real sequence: record once, replay the back end.

Usage::

    # run SLAM on a sequence, record every filter operation, print timings and ATE
    python benchmarks/recovery_replay.py record ../shared/datasets/7scenes-redkitchen-a \
        --log out/redkitchen_ops.pkl [--frames 500]
    # replay only the back end (layout growth, fusions, recover_active) from the log
    python benchmarks/recovery_replay.py replay out/redkitchen_ops.pkl [--check-every 25]

``record`` wraps the filter of a :class:`eifslam.system.slam.Slam` so that every ``add_pose`` /
``add_features`` (layout growth), every fusion ``info.add(idx, Lam, eta)`` and every
``recover_active()`` is appended to a log, in order. It prints the per-frame ``recover``
timings (median, p95, sum), the tracking wall time, the recovery statistics and the ATE
RMSE against the ground truth.

``replay`` feeds the same operations to a fresh layout, :class:`TrackedInformationStore`
and :class:`IncrementalRecovery`, and times each ``step`` (the per-frame recovery without
the front end, on identical input, so that two versions of the recovery can be compared
on a busy machine). Every ``--check-every`` steps (outside the timings) it checks that the
active window equals the full sparse solve, and at the end that the back-substituted full
solution equals it. It also describes every fallback: how many touched states were
marginalised, and how many steps ago they were last measured.

BLAS runs single-threaded (``OPENBLAS_NUM_THREADS=1``).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402


def _summary(ms: list[float]) -> str:
    a = np.asarray(ms, float)
    if not len(a):
        return "n=0"
    return f"n={len(a)} median={np.median(a):.2f} ms p95={np.percentile(a, 95):.2f} ms " \
           f"max={a.max():.1f} ms sum={a.sum() / 1e3:.2f} s"


def record(args: argparse.Namespace) -> None:
    """Run SLAM on a sequence and record the filter operations."""
    from eifslam.evaluation.metrics import evaluate
    from eifslam.io import Trajectory, open_source
    from eifslam.system.slam import Slam

    seq = open_source(args.sequence)
    slam = Slam(seq.camera)
    filt = slam.filter
    log: list[tuple] = []
    add_pose, add_features, recover_active = filt.add_pose, filt.add_features, filt.recover_active
    info_add = filt.info.add

    def rec_add_pose(frame_id, p, q):
        log.append(("pose", int(frame_id)))
        return add_pose(frame_id, p, q)

    def rec_add_features(track_ids, X):
        log.append(("features", [int(t) for t in track_ids]))
        return add_features(track_ids, X)

    def rec_info_add(idx, Lam, eta):
        log.append(("add", np.array(idx, np.int64), np.array(Lam, float), np.array(eta, float)))
        return info_add(idx, Lam, eta)

    def rec_recover():
        log.append(("recover",))
        return recover_active()

    filt.add_pose, filt.add_features, filt.recover_active = rec_add_pose, rec_add_features, rec_recover
    filt.info.add = rec_info_add
    n = len(seq) if args.frames is None else min(args.frames, len(seq))
    rec_ms, tot = [], []
    t0 = time.perf_counter()
    for k in range(n):
        r = slam.track(seq.load(k), seq.frames[k].timestamp)
        if "recover" in r.timings_ms:
            rec_ms.append(r.timings_ms["recover"])
        tot.append(r.timings_ms.get("total", 0.0))
        if args.progress and k % 50 == 0:
            print(f"[record] frame {k} stats={filt.incremental.stats}", file=sys.stderr, flush=True)
    t_track = time.perf_counter() - t0
    print(f"tracking loop: {t_track:.1f} s for {n} frames")
    print(f"recover per frame: {_summary(rec_ms)}")
    print(f"total per frame:   {_summary(tot)}")
    print(f"stats: {filt.incremental.stats}")
    gt = seq.ground_truth()
    if gt is not None:
        ate = evaluate(Trajectory(*slam.trajectory()), gt).ate_rmse
        print(f"ATE RMSE: {ate:.5f} ({sum(r.position is not None for r in slam.results)} frames with a pose)")
    if args.log:
        Path(args.log).parent.mkdir(parents=True, exist_ok=True)
        with open(args.log, "wb") as fh:
            pickle.dump({"sequence": args.sequence, "frames": n, "ops": log}, fh, protocol=pickle.HIGHEST_PROTOCOL)
        print(f"wrote {args.log} ({len(log)} operations)")


def replay(args: argparse.Namespace) -> None:
    """Replay a recorded log through the incremental recovery and time each step."""
    from eifslam.errors import EstimatorError
    from eifslam.estimation.incremental import IncrementalRecovery, TrackedInformationStore
    from eifslam.estimation.state import StateLayout
    from eifslam.estimation.recovery import factorize

    with open(args.log, "rb") as fh:
        blob = pickle.load(fh)
    layout = StateLayout()
    info = TrackedInformationStore()
    inc = IncrementalRecovery(args.window, args.window)
    info.listeners.append(inc)
    x = np.zeros(0)
    step_ms: list[float] = []
    worst = 0.0
    fall_info: list[tuple[int, int, int, int, int]] = []  # step, touched marginalised poses, features, min/max age
    errors = 0
    pending_touched: list[np.ndarray] = []

    def full_solve() -> np.ndarray:
        isf = np.zeros(layout.dim, bool)
        for kind, _, off, size in layout.blocks():
            isf[off: off + size] = kind == "feature"
        return factorize(info.matrix(), np.flatnonzero(~isf), np.flatnonzero(isf)).solve(info.vector)

    for op in blob["ops"]:
        if op[0] == "pose":
            layout.add_pose(op[1])
            info.grow(layout.dim)
        elif op[0] == "features":
            for t in op[1]:
                layout.add_feature(t)
            info.grow(layout.dim)
        elif op[0] == "add":
            info.add(op[1], op[2], op[3])
            pending_touched.append(op[1].ravel())
        else:
            if len(x) < layout.dim:
                x = np.concatenate([x, np.zeros(layout.dim - len(x))])
            touched = np.concatenate(pending_touched) if pending_touched else np.zeros(0, np.int64)
            pending_touched = []
            if inc.valid and len(touched):  # describe a fallback before the step (not timed)
                pos = inc._pos  # noqa: SLF001
                known = touched[touched < len(pos)]
                marg = np.unique(inc._map.start[known[pos[known] < 0]])  # noqa: SLF001
                if len(marg):
                    age = inc.stats.steps + 1 - inc._last[marg]  # noqa: SLF001
                    nf = int(inc._map.is_feature[marg].sum())  # noqa: SLF001
                    fall_info.append((inc.stats.steps + 1, len(marg) - nf, nf, int(age.min()), int(age.max())))
            t0 = time.perf_counter()
            try:  # as InformationFilter.recover_active
                inc.step(layout, info, x)
            except EstimatorError:
                inc.on_invalidate()
                inc.stats.fallbacks += 1
                x[:] = full_solve()
                errors += 1
            step_ms.append(1e3 * (time.perf_counter() - t0))
            s = inc.stats.steps
            if args.check_every and s % args.check_every == 0:
                a = inc.pidx  # poses: the features of this data are too ill-conditioned to compare
                xf = full_solve()
                d = float(np.max(np.abs(x[a] - xf[a]))) if len(a) else 0.0
                worst = max(worst, d)
                if args.progress:
                    print(f"[replay] step {s} dim {layout.dim} window {inc.stats.window_poses}p/"
                          f"{inc.stats.window_features}f diff {d:.2e} {_summary(step_ms[-args.check_every:])}",
                          file=sys.stderr, flush=True)
    print(f"replay steps: {_summary(step_ms)}")
    print(f"stats: {inc.stats}")
    xf = full_solve()
    x_all = inc.full_solution(x.copy())
    pose = np.zeros(layout.dim, bool)
    for kind, _, off, size in layout.blocks():
        pose[off: off + size] = kind == "pose"
    d_all = float(np.max(np.abs(x_all[pose] - xf[pose])))
    print(f"active poses vs full sparse solve: worst abs diff {worst:.2e} (checked every {args.check_every} "
          f"steps); full_solution vs full sparse solve at the end, all poses: {d_all:.2e}; "
          f"solves that raised (full solve used): {errors}")
    if fall_info:
        fi = np.array(fall_info)
        print(f"steps with measurements of marginalised states: {len(fi)}; touched marginalised poses per step: "
              f"median {np.median(fi[:, 1]):.0f} max {fi[:, 1].max()} (in {np.sum(fi[:, 1] > 0)} steps); features: "
              f"median {np.median(fi[:, 2]):.0f} max {fi[:, 2].max()} (in {np.sum(fi[:, 2] > 0)} steps); "
              f"age (steps since last measured) min {fi[:, 3].min()} median-of-max {np.median(fi[:, 4]):.0f} "
              f"max {fi[:, 4].max()}")
    if args.json:
        import json
        Path(args.json).write_text(json.dumps(dict(step_ms=step_ms, fallbacks=fall_info,
                                                   stats=inc.stats.__dict__, worst=worst, final=d_all)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("sequence")
    r.add_argument("--log", default=None)
    r.add_argument("--frames", type=int, default=None)
    r.add_argument("--progress", action="store_true")
    p = sub.add_parser("replay")
    p.add_argument("log")
    p.add_argument("--window", type=int, default=5, help="IncrementalRecovery windows (Slam default: 5)")
    p.add_argument("--check-every", type=int, default=25)
    p.add_argument("--json", default=None)
    p.add_argument("--progress", action="store_true")
    args = ap.parse_args(argv)
    (record if args.cmd == "record" else replay)(args)


if __name__ == "__main__":
    main()
