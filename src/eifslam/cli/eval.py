"""``eifslam eval GROUNDTRUTH ESTIMATE``: ATE, RPE, tracked fraction of a trajectory.

The arguments are in evo's order (``evo_ape tum GROUNDTRUTH ESTIMATE -as``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

from ..errors import ConfigError, DatasetError, EifslamError, OutputError
from ..io.files import atomic_path, atomic_write
from ..io.trajectory import Trajectory, read_tum


def _ground_truth(path: Path) -> tuple[Trajectory, str | None]:
    """A TUM file, or the ground truth of a data set folder / video (in metres), and its
    unit when known."""
    if path.is_file() and path.suffix.lower() not in (".mp4", ".avi", ".mov", ".mkv"):
        return read_tum(path), None
    from ..evaluation.metrics import DATASET_UNITS
    from ..io.detect import open_source

    gt = open_source(path).ground_truth()
    if gt is None:
        raise DatasetError(f"{path}: data set has no ground truth")
    return gt, DATASET_UNITS


def _check_output_file(path: str, option: str) -> None:
    """Refuse, before any work, an output file that cannot be written: a folder, a
    missing or non-writable parent folder."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{p}: {option} names a folder; give a file name")
    parent = p.parent
    if not parent.is_dir():
        raise OutputError(f"{p}: {option}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise OutputError(f"{p}: {option}: folder {parent} is not writable")


def _plot_formats() -> set[str]:
    """File name endings matplotlib can save (``png``, ``pdf``, ``svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase

    return set(FigureCanvasBase.get_supported_filetypes())


def check_args(args: argparse.Namespace) -> None:
    """Every check that needs no file read: output files and ``--max-diff``.

    Raises
    ------
    EifslamError
        One line naming the file or option.
    """
    if not (math.isfinite(args.max_diff) and args.max_diff > 0):
        raise ConfigError(f"--max-diff must be positive and finite, got {args.max_diff}")
    if args.json:
        _check_output_file(args.json, "--json")
    if args.plot:
        _check_output_file(args.plot, "--plot")
        ext = Path(args.plot).suffix.lower().lstrip(".")
        formats = _plot_formats()
        if ext not in formats:
            raise OutputError(f"{args.plot}: --plot: unknown image format {ext or '(no extension)'!r} "
                              f"(use one of {', '.join(sorted(formats))})")


def run(args: argparse.Namespace) -> int:
    """Evaluate, print, and optionally write JSON and a plot."""
    from ..evaluation.metrics import evaluate

    from ..evaluation.metrics import GT_UNITS

    check_args(args)
    gt, known = _ground_truth(Path(args.ground_truth))
    est = read_tum(args.estimate)
    try:
        result = evaluate(est, gt, max_diff=args.max_diff, units=args.units or known or GT_UNITS)
    except EifslamError as exc:  # name the files the problem is about
        raise type(exc)(f"{args.estimate} against {args.ground_truth}: {exc}") from None
    print(result.summary())
    if args.json:
        atomic_write(args.json, json.dumps(result.to_dict(arrays=args.json_arrays), indent=2) + "\n")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from ..evaluation.plots_eval import plot_evaluation

        fig, ax = plt.subplots(figsize=(7, 6))
        try:
            plot_evaluation(ax, result)
            fig.tight_layout()
            with atomic_path(args.plot) as tmp:
                fig.savefig(tmp, dpi=120)
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
            "Score an estimated TUM trajectory against ground truth, in evo's order: ATE RMSE "
            "after a Sim(3) alignment (as 'evo_ape tum GROUNDTRUTH ESTIMATE -as'), ATE as % of "
            "path length, tracked fraction, RPE rotation and translation-direction errors in "
            "degrees. Lengths are in the ground truth's unit: metres for a data set folder, "
            "'ground-truth units' for a TUM file unless --units names it."
        ),
    )
    p.add_argument("ground_truth", metavar="GROUNDTRUTH", help="ground truth: TUM file or data set folder")
    p.add_argument("estimate", metavar="ESTIMATE", help="estimated trajectory, TUM format (e.g. DIR/trajectory.tum)")
    p.add_argument("--units", metavar="UNIT", default=None,
                   help="name of the ground truth's length unit, e.g. m (default: m for a data set "
                        "folder, 'ground-truth units' for a TUM file)")
    p.add_argument("--plot", metavar="FILE", help="save a top view of the aligned trajectories")
    p.add_argument("--json", metavar="FILE", help="write the figures as JSON (ate_rmse, units, RPE, Sim(3), ...)")
    p.add_argument("--json-arrays", action="store_true", help="include per-pose arrays in JSON")
    p.add_argument(
        "--max-diff", type=float, default=0.01, metavar="S",
        help="timestamp association window in seconds (default 0.01, as evo)",
    )
    p.set_defaults(func=run)
    return p
