"""Every data set × mode × detector: accuracy and cost in one table.

Usage::

    python -m benchmarks.run_all --data ../shared/datasets --out out/all
    python -m benchmarks.run_all --data ../shared/datasets --out out/all --modes filter \\
        --detectors sift --only kitti-seq1,builtin --max-frames 20
    python -m benchmarks.run_all --data ../shared/datasets --out out/all --docs docs/results.md

Runs SLAM on every data set folder under ``--data`` (the sub-folders with ``images/``) and
on the built-in scene of the paper's first experiment (rendered once into
``OUT/builtin-scene``; name ``builtin``), for each mode and detector, with the system's
default configuration otherwise (or ``--config FILE``'s). Each run writes its outputs (no HTML) into
``OUT/<dataset>-<mode>-<detector>/``; a failing run is recorded with its error and the
next one starts. The runs are the tasks of ``eifslam batch`` (``eifslam.evaluation.batch``):
one after another in this process, or on Dask with ``--workers N`` (a local cluster of
single-threaded processes) or ``--scheduler ADDRESS``; ``--skip-complete`` keeps the runs
whose folders are complete instead of redoing them. Writes

* ``OUT/results.json``: a list of rows (see ``_common.build_row``), rewritten after every run;
* ``OUT/results.md``: the Markdown table (ATE, tracked %, map features, fps, median
  milliseconds per frame for each stage, COLMAP's ATE on the same images and the ratio);
* with ``--docs FILE``: the same page written to ``FILE`` as well (e.g. ``docs/results.md``).

Both pages open with :func:`benchmarks._common.markdown_header`: the date (UTC), the
machine, the commit, the library versions and the exact command.

The table is printed on stdout at the end; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

from ._common import (
    BUILTIN, backend_ms_median, build_row, command_line, discover_datasets, fmt, log, machine_info,
    markdown_header, markdown_table, prepare_builtin, short_error, split_list, write_json,
)

MODES = ("filter", "smooth", "ba")
DETECTORS = ("sift", "orb", "akaze")

#: (title, row key) of the per-stage columns: median milliseconds per frame.
STAGE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("detect ms", "ms_detect"), ("match ms", "ms_match"), ("rel. pose ms", "ms_relative_pose"),
    ("cov. ms", "ms_covariance"), ("init ms", "ms_init"), ("fuse ms", "ms_fuse"),
    ("recover ms", "ms_recover"), ("frame ms", "ms_total"),
)

HEADERS: tuple[str, ...] = (
    "data set", "mode", "detector", "tracked", "map features", "ATE", "ATE % path", "COLMAP ATE",
    "ratio to COLMAP", "box w:l", "fps", "total s", *(t for t, _ in STAGE_COLUMNS), "note",
)


def table_row(row: Mapping[str, Any]) -> list[str]:
    """The Markdown cells of one result row (same order as :data:`HEADERS`).

    Parameters
    ----------
    row : mapping
        From ``_common.build_row``.

    Returns
    -------
    list of str
    """
    if row.get("frames"):
        tracked = f"{row.get('frames_tracked')}/{row['frames']} ({row['tracked_pct']:.0f}%)"
    else:
        tracked = "–"
    box = "–"
    if row.get("box_ratio_estimated") is not None:
        box = f"{row['box_ratio_estimated']:.3f} (true {row.get('box_ratio_true', 0.8):.2f})"
    ratio = f"{row['ate_ratio_colmap']:.3g}×" if row.get("ate_ratio_colmap") is not None else "–"
    note = short_error(row.get("error")) or short_error(row.get("stopped")) or short_error(row.get("evaluation_error"))
    return [
        str(row.get("dataset")), str(row.get("mode")), str(row.get("detector")), tracked,
        fmt(row.get("map_features")), fmt(row.get("ate_rmse")), fmt(row.get("ate_percent")),
        fmt(row.get("colmap_ate")), ratio, box, fmt(row.get("fps")), fmt(row.get("total_seconds")),
        *(fmt(row.get(key)) for _, key in STAGE_COLUMNS), note,
    ]


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The results table in Markdown.

    Parameters
    ----------
    rows : sequence of mappings
        Result rows.

    Returns
    -------
    str
    """
    return markdown_table(HEADERS, [table_row(r) for r in rows])


def table_notes(max_frames: int | None) -> str:
    """What the columns mean (goes under the table in ``results.md`` and the docs page)."""
    notes = [
        "ATE: RMSE of the camera centres after a Sim(3) (Umeyama) alignment to the ground truth, "
        "over the tracked frames, in the ground truth's units (m, except middlebury-templering); "
        "read it together with the tracked fraction.",
        "COLMAP ATE: pycolmap 4.2.1 on the same images (../shared/EVALUATION.md); "
        "middlebury-templering's 0.0012 is over the 24 of 31 frames COLMAP registered. "
        "Ratio = eifslam ATE / COLMAP ATE (below 1: eifslam is more accurate).",
        "Stage columns: median milliseconds per frame over the frames where the stage ran; "
        "'frame ms' is the whole per-frame call. The final smoothing pass (mode smooth) or bundle "
        "adjustment (mode ba) is not a per-frame stage: it is counted in 'total s' and fps only.",
        "One run per configuration: timings depend on the machine's load (compare two programs by "
        "running them alternately on the same machine).",
        "box w:l: estimated width:length of the top face of the 0.80:1 box (built-in scene), "
        "from the map features after the same Sim(3).",
    ]
    if max_frames:
        notes.append(f"Runs limited to the first {max_frames} frames (--max-frames): the ATE is not "
                     "comparable with COLMAP's, which is over the whole sequence.")
    return "".join(f"- {n}\n" for n in notes)


def write_docs(path: Path, rows: Sequence[Mapping[str, Any]], command: str, max_frames: int | None,
               info: Mapping[str, Any] | None = None) -> None:
    """Write the docs page: title, provenance, the table and its notes.

    Parameters
    ----------
    path : Path
        E.g. ``docs/results.md`` (overwritten).
    rows : sequence of mappings
        Result rows.
    command : str
        The command that produced them.
    max_frames : int or None
        The ``--max-frames`` used.
    info : mapping, optional
        From ``_common.machine_info`` (default: the current machine).
    """
    text = (markdown_header("eifslam on the shared data sets", command, info)
            + format_table(rows) + "\n" + table_notes(max_frames))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/datasets"),
                   help="folder of data sets (each a sub-folder with images/)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--modes", default=",".join(MODES), help="comma-separated modes (default filter,smooth,ba)")
    p.add_argument("--detectors", default="sift,orb", help="comma-separated detectors (default sift,orb)")
    p.add_argument("--only", default=None,
                   help=f"comma-separated data set names to run (folder names, and '{BUILTIN}' for the built-in scene)")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames per run")
    p.add_argument("--docs", type=Path, default=None, help="also write the table with its provenance into this file")
    p.add_argument("--progress", action="store_true", help="show each run's per-frame progress bar")
    p.add_argument("--config", type=Path, default=None,
                   help="a configuration file (as for 'eifslam run --config') for every run; mode and "
                        "detector come from --modes and --detectors")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None,
                       help="run on a local Dask cluster of this many single-threaded processes "
                            "(default: one after another in this process)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS", help="run on this Dask scheduler")
    p.add_argument("--skip-complete", action="store_true",
                   help="skip the runs whose folders are complete (as 'eifslam batch' does; default: redo them)")
    args = p.parse_args(argv)
    args.modes = split_list(args.modes)
    args.detectors = split_list(args.detectors)
    bad = [m for m in args.modes if m not in MODES] + [d for d in args.detectors if d not in DETECTORS]
    if bad or not args.modes or not args.detectors:
        p.error(f"unknown or empty mode/detector: {bad or '(empty list)'}; modes {MODES}, detectors {DETECTORS}")
    if args.max_frames is not None and args.max_frames < 2:
        p.error("--max-frames must be at least 2")
    if args.workers is not None and args.workers < 1:
        p.error("--workers must be at least 1")
    return args


def select_datasets(data: Path, only: Sequence[str] | None) -> tuple[list[tuple[str, Path | None]], list[str]]:
    """The data sets to run, in order, and the ``--only`` names that matched nothing.

    Parameters
    ----------
    data : Path
        Folder of data sets.
    only : sequence of str or None
        Names to keep (``None`` or empty: all, plus the built-in scene).

    Returns
    -------
    (list of (name, folder or None), list of str)
        ``None`` as the folder stands for the built-in scene (rendered later).
    """
    found: list[tuple[str, Path | None]] = [(p.name, p) for p in discover_datasets(data)]
    found.append((BUILTIN, None))
    if not only:
        return found, []
    wanted = list(dict.fromkeys(only))
    names = {n for n, _ in found}
    return [(n, p) for n, p in found if n in wanted], [n for n in wanted if n not in names]


def result_row(task: Any, row: Mapping[str, Any], scene: Any = None) -> dict[str, Any]:
    """This script's row (``_common.build_row``) of a finished batch task.

    Parameters
    ----------
    task : eifslam.evaluation.batch.BatchTask
    row : mapping
        The task's row from :mod:`eifslam.evaluation.batch` (``status``, ``seconds``, ``error``).
    scene : BuiltinScene, optional
        For the built-in scene: adds the box-ratio figures (also written to ``report.json``).
    """
    rep = None
    try:
        rep = json.loads((Path(task.out_dir) / "report.json").read_text())
    except (OSError, ValueError):
        pass
    if not isinstance(rep, dict):  # the run gave no report: its error is the row's
        return build_row(task.dataset, task.mode, task.features, None, error=row.get("error") or "no report.json",
                         status=row.get("status"), seconds=row.get("seconds"))
    extra: dict[str, Any] = dict(status=row.get("status"), seconds=row.get("seconds"))
    if scene is not None and rep.get("frames_tracked", 0) >= 3 and "box_ratio_true" not in rep:
        from eifslam.evaluation.box_ratio import add_box_ratio

        add_box_ratio(rep, task.out_dir, scene)
    backend = backend_ms_median(Path(task.out_dir) / "frames.json")
    if backend is not None:
        extra["ms_backend"] = backend
    return build_row(task.dataset, task.mode, task.features, rep, **extra)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the matrix; return 0 when every run produced a report, 1 when some failed, 2 on bad input.

    The runs are the tasks of ``eifslam batch`` (:mod:`eifslam.evaluation.batch`): one after
    another in this process, or on Dask with ``--workers N`` / ``--scheduler ADDRESS``
    (:func:`eifslam.cli.cluster.run_on_dask`).

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments (default ``sys.argv[1:]``).
    """
    from eifslam.evaluation.batch import make_tasks, run_serial
    from eifslam.system.config import SlamConfig

    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    datasets, missing = select_datasets(args.data, split_list(args.only))
    for name in missing:
        log(f"--only: no data set named {name!r} under {args.data} (nor '{BUILTIN}'); skipped")
    if not datasets:
        log("nothing to run")
        return 2
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    base = SlamConfig()
    if args.config is not None:
        from eifslam.cli.config import read_config
        from eifslam.errors import ConfigError

        try:
            base = read_config(args.config)
        except ConfigError as exc:
            log(str(exc))
            return 2
    configs = [base.replace(frontend={"detector": det}, smoothing={"mode": mode})
               for mode in args.modes for det in args.detectors]
    rows: list[dict[str, Any]] = []
    scene = None
    sources, names = [], []
    for name, folder in datasets:
        if folder is None:
            try:
                folder, scene = prepare_builtin(out)
            except Exception as exc:  # rendering failed: record it for every run of the scene
                log(f"FAILED rendering the built-in scene: {type(exc).__name__}: {exc}")
                rows += [build_row(name, c.smoothing.mode, c.frontend.detector, None,
                                   error=f"rendering: {type(exc).__name__}: {exc}") for c in configs]
                continue
        sources.append(folder)
        names.append(name)
    tasks = make_tasks(sources, configs, out, max_frames=args.max_frames, html=False, names=names)
    log(f"{len(tasks)} runs: data sets {names}, modes {args.modes}, detectors {args.detectors}"
        + (f", at most {args.max_frames} frames each" if args.max_frames else ""))
    done: dict[int, dict[str, Any]] = {}

    def on_row(k: int, row: Mapping[str, Any]) -> None:
        task = tasks[k]
        done[k] = result_row(task, row, scene if task.dataset == BUILTIN else None)
        write_json(out / "results.json", rows + [done[i] for i in sorted(done)])
        log(f"[{len(done)}/{len(tasks)}] {task.name} {row['status']}: "
            + (row["error"] or f"{row['tracked']}/{row['frames']} tracked, ATE {fmt(row['ate_rmse'])}, "
                               f"{fmt(row['seconds'])} s"))

    if args.workers is None and args.scheduler is None:
        run_serial(tasks, force=not args.skip_complete, quiet=not args.progress, on_row=on_row)
    else:
        from eifslam.cli.cluster import run_on_dask

        run_on_dask(tasks, workers=args.workers, scheduler=args.scheduler, force=not args.skip_complete,
                    on_row=on_row)
    rows += [done[i] for i in sorted(done)]
    write_json(out / "results.json", rows)
    table = format_table(rows)
    command = command_line(__spec__.name, argv)
    info = machine_info()
    (out / "results.md").write_text(markdown_header("eifslam results", command, info) + table + "\n"
                                    + table_notes(args.max_frames))
    if args.docs is not None:
        write_docs(args.docs, rows, command, args.max_frames, info)
        log(f"wrote {args.docs}")
    log(f"wrote {out / 'results.json'} and {out / 'results.md'}")
    print(table)
    return 1 if any(r["error"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
