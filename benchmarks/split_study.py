"""Accuracy and cost against the Ωp / Ωm split (``frontend.map_fraction``).

Usage::

    python benchmarks/split_study.py --data ../shared/datasets --out out/split
    python benchmarks/split_study.py --data ../shared/datasets --out out/split \\
        --fractions 0.1,0.3,1.0 --datasets builtin --max-frames 20
    python benchmarks/split_study.py --data ../shared/datasets --out out/split --docs docs/split_study.md

Every new feature track goes once and for ever either to ``Ωm`` (a 3-D feature in the
filter's state) or to ``Ωp`` (measurements turned into relative poses by the five-point
solver, never in the state); ``map_fraction`` is the share of new tracks put into ``Ωm``.
For each data set (folder names under ``--data``, and ``builtin`` for the built-in scene,
rendered once into ``OUT/builtin-scene``) and each fraction, this runs SLAM (``--mode``,
``--detector``, other settings the system's defaults) into ``OUT/<dataset>-f<fraction>/``
and records the ATE, the tracked fraction, the map size, the median milliseconds per
frame (whole frame, and back end = fuse + recover of the same frame) and, on the built-in
scene, the box ratio. Writes ``OUT/split_study.json``, ``OUT/split_study.png`` (ATE and
milliseconds against the fraction, one line per data set) and, with ``--docs FILE``, a
Markdown page with the table, the figure (copied next to it, same stem, ``.png``) and a
paragraph stating what the split bought in this run. Progress goes to stderr; the table
is printed on stdout at the end.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (  # noqa: E402
    BUILTIN, build_row, command_line, discover_datasets, fmt, log, machine_info, markdown_table,
    prepare_builtin, provenance_markdown, run_one, short_error, split_list, write_json,
)

DEFAULT_FRACTIONS = "0.1,0.2,0.3,0.5,0.7,1.0"
DEFAULT_DATASETS = f"kitti-seq1,middlebury-templering,{BUILTIN}"

HEADERS: tuple[str, ...] = ("data set", "map fraction", "tracked", "map features", "ATE", "ATE % path",
                            "frame ms", "back-end ms", "box w:l", "total s", "note")


def parse_fractions(text: str) -> list[float]:
    """Parse ``--fractions``: comma-separated numbers in (0, 1], returned sorted and unique.

    Parameters
    ----------
    text : str
        E.g. ``"0.1,0.3,1"``.

    Returns
    -------
    list of float

    Raises
    ------
    ValueError
        A value that is not a number or lies outside (0, 1], or an empty list.
    """
    vals = []
    for s in split_list(text):
        v = float(s)
        if not 0.0 < v <= 1.0:
            raise ValueError(f"map fraction {s} outside (0, 1]")
        vals.append(v)
    if not vals:
        raise ValueError("no fraction given")
    return sorted(set(vals))


def table_row(row: Mapping[str, Any]) -> list[str]:
    """The Markdown cells of one row (same order as :data:`HEADERS`)."""
    tracked = (f"{row.get('frames_tracked')}/{row['frames']} ({row['tracked_pct']:.0f}%)"
               if row.get("frames") else "–")
    box = fmt(row.get("box_ratio_estimated")) if row.get("box_ratio_estimated") is not None else "–"
    note = short_error(row.get("error")) or short_error(row.get("stopped")) or short_error(row.get("evaluation_error"))
    return [str(row.get("dataset")), f"{row.get('map_fraction'):g}", tracked, fmt(row.get("map_features")),
            fmt(row.get("ate_rmse")), fmt(row.get("ate_percent")), fmt(row.get("ms_total")),
            fmt(row.get("ms_backend")), box, fmt(row.get("total_seconds")), note]


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The split-study table in Markdown."""
    return markdown_table(HEADERS, [table_row(r) for r in rows])


def _ok(rows: Sequence[Mapping[str, Any]], dataset: str) -> list[Mapping[str, Any]]:
    """The rows of ``dataset`` with an ATE, by increasing fraction."""
    return sorted((r for r in rows if r["dataset"] == dataset and r.get("error") is None
                   and r.get("ate_rmse") is not None), key=lambda r: r["map_fraction"])


def summary_paragraph(rows: Sequence[Mapping[str, Any]], mode: str, detector: str,
                      max_frames: int | None = None) -> str:
    """What the split bought in this run, in numbers taken from ``rows``.

    For every data set with at least two successful fractions, compares the smallest and
    the largest fraction run (map size, median back-end and whole-frame ms, ATE, tracked
    frames) and names the fraction with the lowest ATE.

    Parameters
    ----------
    rows : sequence of mappings
        Rows with ``map_fraction``.
    mode, detector : str
        As run.
    max_frames : int, optional
        The ``--max-frames`` used.

    Returns
    -------
    str
        Markdown: an explanatory sentence and one bullet per data set.
    """
    scope = f"mode {mode}, detector {detector}" + (f", first {max_frames} frames" if max_frames else "")
    text = ("Tracks kept in the map (`Ωm`, share `map_fraction`) become 3-D features in the filter's "
            "state; the others (`Ωp`) are used only through the relative poses the five-point solver "
            "computes from them and never enter the state. A smaller fraction therefore means a smaller "
            "state and cheaper fusion and recovery per frame, at the price of fewer map features "
            "constraining the poses. In this run "
            f"({scope}):\n\n")
    bullets = []
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        ok = _ok(rows, ds)
        failed = [r for r in rows if r["dataset"] == ds and r not in ok]
        if len(ok) < 2:
            bullets.append(f"- {ds}: fewer than two fractions gave an ATE; no comparison.")
            continue
        lo, hi = ok[0], ok[-1]
        best = min(ok, key=lambda r: r["ate_rmse"])
        s = (f"- {ds}: keeping {100 * lo['map_fraction']:.0f}% of the new tracks in the map instead of "
             f"{100 * hi['map_fraction']:.0f}% "
             f"gave {fmt(lo['map_features'])} map features instead of {fmt(hi['map_features'])}, "
             f"a median back-end time of {fmt(lo['ms_backend'])} ms per frame instead of {fmt(hi['ms_backend'])} ms "
             f"({fmt(lo['ms_total'])} ms instead of {fmt(hi['ms_total'])} ms for the whole frame), "
             f"and an ATE of {fmt(lo['ate_rmse'])} instead of {fmt(hi['ate_rmse'])} "
             f"({lo['frames_tracked']}/{lo['frames']} and {hi['frames_tracked']}/{hi['frames']} frames tracked). "
             f"The lowest ATE, {fmt(best['ate_rmse'])}, was at fraction {best['map_fraction']:g}.")
        if lo.get("box_ratio_estimated") is not None and hi.get("box_ratio_estimated") is not None:
            s += (f" Box width:length {fmt(lo['box_ratio_estimated'])} and {fmt(hi['box_ratio_estimated'])} "
                  f"(true {fmt(lo.get('box_ratio_true'))}).")
        for r in failed:
            why = (f"{r['frames_tracked']}/{r['frames']} frames tracked" if r.get("frames")
                   else short_error(r.get("error") or r.get("evaluation_error")) or "no report")
            s += f" No ATE at fraction {r['map_fraction']:g} ({why})."
        bullets.append(s)
    return text + "\n".join(bullets) + "\n"


def plot(rows: Sequence[Mapping[str, Any]], path: Path, title: str = "") -> Path:
    """ATE and milliseconds per frame against the map fraction, one line per data set.

    Left: ATE (log scale; each data set in its ground truth's units). Right: median
    milliseconds per frame (log scale), whole frame (solid) and back end = fuse + recover
    (dashed). Only runs with an ATE are drawn (the ms of a lost run are not comparable).

    Parameters
    ----------
    rows : sequence of mappings
        Rows with ``map_fraction``.
    path : Path
        PNG to write.
    title : str
        Figure title.

    Returns
    -------
    Path
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.2), layout="constrained")
    ax_ate, ax_ms = fig.subplots(1, 2, sharex=True)
    colours = matplotlib.colormaps["tab10"]
    plotted = False
    for i, ds in enumerate(dict.fromkeys(r["dataset"] for r in rows)):
        c = colours(i % 10)
        rs = _ok(rows, ds)  # a lost run's ms are not comparable: successful runs only
        if not rs:
            continue
        plotted = True
        x = [r["map_fraction"] for r in rs]
        ax_ate.plot(x, [r["ate_rmse"] for r in rs], "o-", color=c, label=ds)
        for key, style, lab in (("ms_total", "o-", f"{ds} frame"), ("ms_backend", "s--", f"{ds} back end")):
            pts = [(r["map_fraction"], r[key]) for r in rs if r.get(key)]
            if pts:
                ax_ms.plot(*zip(*pts), style, color=c, label=lab)
    if plotted:
        ax_ate.set_yscale("log")
        ax_ms.set_yscale("log")
    ax_ate.set_xlabel("map fraction (share of new tracks kept in Ωm)")
    ax_ate.set_ylabel("ATE RMSE (ground-truth units, log)")
    ax_ate.set_title("accuracy (runs without an ATE left out)")
    ax_ms.set_xlabel("map fraction (share of new tracks kept in Ωm)")
    ax_ms.set_ylabel("median ms per frame (log)")
    ax_ms.set_title("cost (solid: whole frame, dashed: fuse + recover)")
    for ax in (ax_ate, ax_ms):
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def write_docs(path: Path, rows: Sequence[Mapping[str, Any]], png: Path, command: str, mode: str,
               detector: str, max_frames: int | None, info: Mapping[str, Any] | None = None) -> Path:
    """Write the docs page and copy the figure next to it.

    Parameters
    ----------
    path : Path
        E.g. ``docs/split_study.md`` (overwritten).
    rows : sequence of mappings
        Rows with ``map_fraction``.
    png : Path
        The figure; copied to ``path`` with suffix ``.png``.
    command : str
        The command that produced the rows.
    mode, detector : str
        As run.
    max_frames : int or None
        The ``--max-frames`` used.
    info : mapping, optional
        From ``_common.machine_info`` (default: the current machine).

    Returns
    -------
    Path
        The copied figure.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = path.with_suffix(".png")
    if png.resolve() != fig.resolve():
        shutil.copyfile(png, fig)
    text = ("# The Ωp / Ωm split: accuracy and cost against the map fraction\n\n"
            "Generated by `benchmarks/split_study.py`; do not edit by hand, re-run the command below.\n\n"
            + provenance_markdown(info or machine_info(), command)
            + "## What the split buys\n\n" + summary_paragraph(rows, mode, detector, max_frames)
            + "\n## Results\n\n" + format_table(rows)
            + "\n- ATE: RMSE of the camera centres after a Sim(3) alignment to the ground truth, over the "
              "tracked frames, in the ground truth's units.\n"
              "- frame ms: median over frames of the whole per-frame call; back-end ms: median over frames "
              "of fuse + recover of the same frame. The final smoothing pass or bundle adjustment is counted "
              "in total s only. One run per fraction on a shared machine: timings are noisy.\n"
            + f"\n![ATE and ms per frame against the map fraction]({fig.name})\n")
    path.write_text(text)
    return fig


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/datasets"), help="folder of data sets")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--fractions", default=DEFAULT_FRACTIONS, help=f"map fractions in (0, 1] (default {DEFAULT_FRACTIONS})")
    p.add_argument("--datasets", default=DEFAULT_DATASETS,
                   help=f"data set folder names, '{BUILTIN}' for the built-in scene (default {DEFAULT_DATASETS})")
    p.add_argument("--mode", choices=["filter", "smooth", "ba"], default="smooth", help="SLAM mode (default smooth)")
    p.add_argument("--detector", choices=["sift", "orb", "akaze"], default="sift", help="detector (default sift)")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames per run")
    p.add_argument("--docs", type=Path, default=None, help="also write a Markdown page (and the PNG next to it)")
    p.add_argument("--progress", action="store_true", help="show each run's per-frame progress bar")
    args = p.parse_args(argv)
    try:
        args.fractions = parse_fractions(args.fractions)
    except ValueError as exc:
        p.error(f"--fractions: {exc}")
    args.datasets = split_list(args.datasets)
    if not args.datasets:
        p.error("--datasets: empty list")
    if args.max_frames is not None and args.max_frames < 2:
        p.error("--max-frames must be at least 2")
    return args


def main(argv: Sequence[str] | None = None, runner: Callable[..., dict[str, Any]] | None = None) -> int:
    """Run the study; 0 when every run produced a report, 1 when some failed, 2 on bad input.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments (default ``sys.argv[1:]``).
    runner : callable, optional
        Replacement of ``run_to_folder`` (tests).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    found = {p.name: p for p in discover_datasets(args.data)}
    todo = []
    for name in args.datasets:
        if name == BUILTIN or name in found:
            todo.append(name)
        else:
            log(f"no data set named {name!r} under {args.data}; skipped")
    if not todo:
        log("nothing to run")
        return 2
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    n_runs = len(todo) * len(args.fractions)
    log(f"{n_runs} runs: data sets {todo}, fractions {args.fractions}, mode {args.mode}, detector {args.detector}"
        + (f", at most {args.max_frames} frames each" if args.max_frames else ""))
    command = command_line(__file__, argv)
    info = machine_info()
    result: dict[str, Any] = dict(command=command, machine=info, mode=args.mode, detector=args.detector,
                                  max_frames=args.max_frames, fractions=args.fractions, rows=[])
    rows: list[dict[str, Any]] = result["rows"]
    k = 0
    for name in todo:
        scene, folder = None, found.get(name)
        if name == BUILTIN:
            try:
                folder, scene = prepare_builtin(out)
            except Exception as exc:
                log(f"FAILED rendering the built-in scene: {type(exc).__name__}: {exc}")
                for f in args.fractions:
                    k += 1
                    rows.append(build_row(name, args.mode, args.detector, None,
                                          error=f"rendering: {type(exc).__name__}: {exc}", map_fraction=f))
                write_json(out / "split_study.json", result)
                continue
        for f in args.fractions:
            k += 1
            run_dir = out / f"{name}-f{f:g}"
            log(f"[{k}/{n_runs}] {name} map_fraction={f:g} -> {run_dir}")
            row = run_one(folder, name, args.mode, args.detector, run_dir, frontend={"map_fraction": f},
                          max_frames=args.max_frames, scene=scene, quiet=not args.progress, runner=runner,
                          map_fraction=f)
            rows.append(row)
            write_json(out / "split_study.json", result)
            if row["error"] is None:
                log(f"[{k}/{n_runs}] done: {row['frames_tracked']}/{row['frames']} tracked, ATE {fmt(row['ate_rmse'])}, "
                    f"{fmt(row['ms_total'])} ms/frame, back end {fmt(row['ms_backend'])} ms")
    png = plot(rows, out / "split_study.png",
               title=f"eifslam, mode {args.mode}, {args.detector}" + (f", {args.max_frames} frames" if args.max_frames else ""))
    log(f"wrote {out / 'split_study.json'} and {png}")
    if args.docs is not None:
        fig = write_docs(args.docs, rows, png, command, args.mode, args.detector, args.max_frames, info)
        log(f"wrote {args.docs} and {fig}")
    print(format_table(rows))
    return 1 if any(r["error"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
