"""One data set, several configurations: filter and smooth ATE of each, from one tracking run.

Usage::

    python benchmarks/ablation.py --data ../shared/datasets/middlebury-templering \\
        --variant default '{}' --variant gate30 '{"experimental": {"zm_gate_chi2": 30}}' --out out/abl.json

Each variant is a name and a JSON dict of :class:`eifslam.system.config.SlamConfig` overrides
(``{"frontend": {...}, "experimental": {...}, ...}``), run once per ``--seeds`` value
(``frontend.seed``: OpenCV's random generator, which FLANN and RANSAC draw from). Runs
with different seeds differ by more than many configuration changes do, so compare
variants by the median over seeds. For each run, the whole sequence is
tracked (:meth:`Slam.track`), the frames without a pose get their second chance
(:meth:`Slam.finish`), the filter's trajectory is scored, then :meth:`Slam.smooth` runs and
the smoothed trajectory is scored: Sim(3)-aligned ATE RMSE against ``groundtruth.tum``
(read for scoring only). Writes a JSON list of rows and prints a Markdown table.

BLAS is pinned to one thread (set before NumPy loads) so that a run is repeatable: with
more threads the rounding of dense products changes from run to run, and on long
sequences that is enough to change later decisions (gates, references) and the result.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402


def run_variant(source: Path, overrides: dict[str, Any], max_frames: int | None = None) -> dict[str, Any]:
    """Track ``source`` with the overrides; filter and smooth ATE, frames tracked, seconds."""
    from eifslam.system.config import SlamConfig
    from eifslam.evaluation.metrics import evaluate
    from eifslam.io import Trajectory, open_source
    from eifslam.system.slam import Slam

    seq = open_source(source)
    n = len(seq) if max_frames is None else min(max_frames, len(seq))
    slam = Slam(seq.camera, SlamConfig.from_dict(overrides))
    t0 = time.perf_counter()
    for k in range(n):
        slam.track(seq.load(k), seq.frames[k].timestamp)
    added = slam.finish()
    t1 = time.perf_counter()
    gt = seq.ground_truth()

    def ate() -> tuple[float, int]:
        ts, P, Q = slam.trajectory()
        return float(evaluate(Trajectory(ts, P, Q), gt).ate_rmse), len(ts)

    filt_ate, tracked = ate()
    rep = slam.smooth()
    t2 = time.perf_counter()
    smooth_ate, _ = ate()
    return dict(frames=n, tracked=tracked, added_by_finish=added, filter_ate=filt_ate, smooth_ate=smooth_ate,
                track_s=round(t1 - t0, 1), smooth_s=round(t2 - t1, 1), smooth_passes=rep.passes,
                smooth_rejected_zm=rep.rejected_features, smooth_rejected_rel=rep.rejected_relative,
                filter_rejected_rel=len(slam.rejected_relative))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a data set folder with groundtruth.tum")
    ap.add_argument("--variant", nargs=2, action="append", metavar=("NAME", "JSON"), required=True)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--seeds", default="0", help="comma-separated frontend.seed values (default 0)")
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the rows")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    rows = []
    for name, js in args.variant:
        for seed in seeds:
            over = json.loads(js)
            over["frontend"] = dict(over.get("frontend", {}), seed=seed)
            row = dict(dataset=args.data.name, variant=name, seed=seed, overrides=over)
            row.update(run_variant(args.data, over, args.max_frames))
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.out is not None:
                args.out.parent.mkdir(parents=True, exist_ok=True)
                args.out.write_text(json.dumps(rows, indent=1))
    print(markdown(rows))
    return 0


def markdown(rows: list[dict[str, Any]]) -> str:
    """Per variant: tracked, filter and smooth ATE (median and range over seeds), seconds."""
    import numpy as np

    out = ["", "| data set | variant | runs | tracked | filter ATE median (min-max) | smooth ATE median (min-max) | track s | smooth s |",
           "|---|---|---|---|---|---|---|---|"]
    for name in dict.fromkeys(r["variant"] for r in rows):
        rs = [r for r in rows if r["variant"] == name]
        f = np.array([r["filter_ate"] for r in rs])
        s = np.array([r["smooth_ate"] for r in rs])
        out.append(f"| {rs[0]['dataset']} | {name} | {len(rs)} | {min(r['tracked'] for r in rs)}/{rs[0]['frames']} | "
                   f"{np.median(f):.4g} ({f.min():.4g}-{f.max():.4g}) | {np.median(s):.4g} ({s.min():.4g}-{s.max():.4g}) | "
                   f"{np.median([r['track_s'] for r in rs]):.1f} | {np.median([r['smooth_s'] for r in rs]):.1f} |")
    return "\n".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
