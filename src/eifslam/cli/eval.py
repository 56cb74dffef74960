"""``eifslam eval ESTIMATE GROUND_TRUTH``: ATE, RPE, tracked fraction of a trajectory."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import DatasetError
from ..io.trajectory import Trajectory, read_tum


def _ground_truth(path: Path) -> Trajectory:
    """A TUM file, or the ground truth of a data set folder / video."""
    if path.is_file() and path.suffix.lower() not in (".mp4", ".avi", ".mov", ".mkv"):
        return read_tum(path)
    from ..io.detect import open_source

    gt = open_source(path).ground_truth()
    if gt is None:
        raise DatasetError(f"{path}: data set has no ground truth")
    return gt


def run(args: argparse.Namespace) -> int:
    """Evaluate, print, and optionally write JSON and a plot."""
    from ..evaluation.metrics import evaluate

    est = read_tum(args.estimate)
    gt = _ground_truth(Path(args.ground_truth))
    result = evaluate(est, gt, max_diff=args.max_diff)
    print(result.summary())
    if args.json:
        Path(args.json).write_text(json.dumps(result.to_dict(arrays=args.json_arrays), indent=2) + "\n")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from ..evaluation.plots_eval import plot_evaluation

        fig, ax = plt.subplots(figsize=(7, 6))
        try:
            plot_evaluation(ax, result)
            fig.tight_layout()
            fig.savefig(args.plot, dpi=120)
        except OSError as exc:
            raise DatasetError(f"{args.plot}: cannot save plot ({exc})") from None
        finally:
            plt.close(fig)
    return 0


def add_parser(sub) -> argparse.ArgumentParser:
    """Register the ``eval`` sub-command."""
    p = sub.add_parser(
        "eval",
        help="score a trajectory against ground truth (ATE after Sim(3), RPE)",
        description=(
            "Score an estimated TUM trajectory against ground truth: ATE RMSE after a Sim(3) "
            "alignment (as 'evo_ape tum GT EST -as'), ATE as %% of path length, tracked "
            "fraction, RPE rotation and translation-direction errors in degrees."
        ),
    )
    p.add_argument("estimate", help="estimated trajectory, TUM format")
    p.add_argument("ground_truth", help="ground truth: TUM file or data set folder")
    p.add_argument("--plot", metavar="FILE", help="save a top view of the aligned trajectories")
    p.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    p.add_argument("--json-arrays", action="store_true", help="include per-pose arrays in JSON")
    p.add_argument(
        "--max-diff", type=float, default=0.01, metavar="S",
        help="timestamp association window in seconds (default 0.01, as evo)",
    )
    p.set_defaults(func=run)
    return p
