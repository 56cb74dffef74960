"""``eifslam batch SOURCE... --out DIR``: many sources and settings at once, on Dask.

One task per (source, mode, features), each writing ``DIR/<dataset>-<mode>-<features>/``
as ``eifslam run`` would; ``DIR/results.json`` (one row per task) and ``DIR/results.md``
are rewritten as tasks finish. Tasks whose folders are complete are skipped (``--force``
redoes them). Exit code 0 when every task succeeded, 1 when any failed (every row is
still written), 2 when Dask is not installed.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

from ..errors import ConfigError
from .run import add_common_options, announce, base_config, make_config, provenance


def add_parser(sub) -> argparse.ArgumentParser:
    """Register ``eifslam batch`` on the sub-command parsers ``sub``; returns its parser."""
    p = sub.add_parser("batch", help="run SLAM on many sequences and settings at once (Dask)",
                       description="Run eifslam on every SOURCE with every --mode and --features, one Dask task "
                                   "each (a local cluster of single-threaded processes, or --scheduler), and write "
                                   "each run's folder plus DIR/results.json and DIR/results.md. Needs Dask: "
                                   'pip install "eifslam[batch]".')
    p.add_argument("sources", nargs="+", type=Path, metavar="SOURCE",
                   help="data folders, KITTI/TUM/EuRoC/Strecha layouts or videos (with their own cameras)")
    add_common_options(p, several=True)
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None,
                       help="worker processes of the local cluster, one thread each (default: the usable CPUs)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="an existing Dask scheduler, e.g. tcp://host:8786 (its workers need eifslam and "
                            "the same paths)")
    p.set_defaults(func=main)
    return p


def configs(args: argparse.Namespace) -> list:
    """One configuration per (mode, features) of the command line, on ``--config``'s base."""
    base = base_config(args)
    modes = list(dict.fromkeys(args.mode or [None]))
    features = list(dict.fromkeys(args.features or [None]))
    return [make_config(argparse.Namespace(**{**vars(args), "mode": m, "features": f}), base)
            for m, f in itertools.product(modes, features)]


def main(args: argparse.Namespace) -> int:
    """Run the batch the parsed options describe; return the exit code (0, 1 or 2, see above).

    Raises
    ------
    EifslamError
        Bad options, a ``--config`` file or an output folder that cannot be used, a
        scheduler that cannot be reached (one line; checked before any task runs).
    """
    from ..evaluation.batch import make_tasks, write_results
    from ..io.files import ensure_output_dir
    from .cluster import DaskMissing, import_distributed, run_on_dask

    try:
        import_distributed()  # before any work
    except DaskMissing as exc:
        print(f"eifslam: error: {exc}", file=sys.stderr)
        return 2
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    settings = configs(args)
    for c in settings:
        announce(args, c)
    out = ensure_output_dir(args.out)
    tasks = make_tasks([s.resolve() for s in args.sources], settings, out.resolve(), max_frames=args.max_frames,
                       html=not args.no_html, extra=lambda c: provenance(args, c))
    rows: list = [None] * len(tasks)

    def on_row(k: int, row: dict) -> None:
        rows[k] = row
        write_results(out, [r for r in rows if r is not None])

    rows_done = run_on_dask(tasks, workers=args.workers, scheduler=args.scheduler, force=args.force,
                            progress=not args.quiet, on_row=on_row)
    failed = [r for r in rows_done if r.get("error")]
    skipped = sum(r["status"] == "skipped" for r in rows_done)
    if not args.quiet:
        print(f"eifslam: {len(rows_done)} tasks ({skipped} skipped as complete, {len(failed)} failed); "
              f"results in {out / 'results.md'}", file=sys.stderr)
    for r in failed:
        print(f"eifslam: error: {r['dataset']} {r['mode']} {r['features']}: {r['error']}", file=sys.stderr)
    return 1 if failed else 0
