"""Real time: frames per second end to end and per-stage milliseconds, per data set and detector.

Usage::

    python -m benchmarks.realtime --data ../shared/datasets --out out/realtime
    python -m benchmarks.realtime --data ../shared/datasets --out out/rt --only kitti-seq1 --detectors sift
    python -m benchmarks.realtime --data ../shared/datasets --out out/rt --only 7scenes-redkitchen-a \\
        --max-frames 150 --set max_features=1000 --smooth --tag feat1000

For each data set under ``--data`` (the sub-folders with ``images/``; ``builtin`` is the
rendered scene of the paper's first experiment) and each detector, SLAM runs in filter
mode as ``eifslam run --mode filter`` does it (:func:`eifslam.system.runner.run_sequence`,
then :func:`eifslam.evaluation.outputs.write_outputs`, no HTML) with the default
configuration but for the detector and the ``--set`` front-end settings. Per run it
records

* the end-to-end time (opening the source to the written outputs) and fps, against the
  camera's frame rate (from the timestamps), and the process's CPU time over the same span
  (all threads; on a machine shared with other jobs it varies less than wall time);
* for each stage (``detect, match, relative_pose, covariance, init, fuse, recover, total``
  of ``TrackResult.timings_ms``, plus ``wait``/``load``: the time the tracking thread
  waited for the prefetching worker, or decoded the image itself) the median and 95th
  percentile milliseconds over the frames where it ran;
* the median ``total`` of the first and of the last 10% of frames (a flat per-frame cost
  has a ratio near 1);
* the ATE of the filter's estimate (and of the smoothed one with ``--smooth``: the same
  run, then :meth:`Slam.smooth`, as mode ``smooth`` ends).

Writes ``OUT/<dataset>-<detector>[-<tag>]/`` (``frames.json``: one entry per frame with
``ms.total``; ``report.json``, ``trajectory.tum``, ``map.ply``), ``frames.png`` there (per-frame
milliseconds against frame index), ``OUT/realtime.json`` (the summary rows, machine and
command; rewritten after every run), ``OUT/realtime.md`` (the table under the provenance
header of :func:`benchmarks._common.markdown_header`) and prints the table on stdout. With ``detect`` in a
worker thread (the default, ``prefetch`` 2), ``total`` is the tracking thread's time per
frame without detection; ``total + wait`` is the frame's wall time.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import json
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Mapping, Sequence

from ._common import (
    BUILTIN, command_line, discover_datasets, fmt, log, machine_info, markdown_header, markdown_table, prepare_builtin,
    short_error, split_list, write_json,
)

DETECTORS = ("sift", "orb", "akaze")

#: The name of the loop world's rows (``--loop-world``).
LOOP_WORLD = "loop-world"

#: Stages summarised (median and p95 ms per frame); ``wait``/``load`` is the time the
#: tracking thread spent getting the frame; ``match_ahead`` the matching made in the
#: prefetch worker (binary descriptors), not part of ``total``.
STAGES: tuple[str, ...] = ("detect", "match", "match_ahead", "relative_pose", "covariance", "init", "fuse",
                           "recover", "total", "wait", "load")


def percentile_stats(values: Sequence[float]) -> dict[str, float | int | None]:
    """Median, 95th percentile and count of ``values`` (linear interpolation, NumPy's default).

    Parameters
    ----------
    values : sequence of float
        Milliseconds (or anything).

    Returns
    -------
    dict
        ``{"median": ..., "p95": ..., "n": ...}``; ``None`` figures when empty.
    """
    import numpy as np

    v = np.asarray([float(x) for x in values], float)
    if len(v) == 0:
        return {"median": None, "p95": None, "n": 0}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "n": int(len(v))}


def stage_stats(frames: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per-stage median/p95 over the frames of a ``frames.json`` list where the stage ran.

    Parameters
    ----------
    frames : sequence of mappings
        Each with ``ms``: ``{stage: milliseconds}``.

    Returns
    -------
    dict
        ``{stage: {"median", "p95", "n"}}`` for the stages of :data:`STAGES` that occur.
    """
    out = {}
    for s in STAGES:
        vals = [f["ms"][s] for f in frames if s in f.get("ms", {})]
        if vals:
            out[s] = percentile_stats(vals)
    return out


def flatness(frames: Sequence[Mapping[str, Any]], key: str = "total") -> dict[str, float | None]:
    """Median per-frame ``key`` ms of the first and the last 10% of frames, and their ratio.

    Parameters
    ----------
    frames : sequence of mappings
        ``frames.json`` entries in frame order.
    key : str
        The stage.

    Returns
    -------
    dict
        ``first10_ms``, ``last10_ms``, ``last_over_first`` (``None`` with fewer than 10 frames).
    """
    vals = [f["ms"][key] for f in frames if key in f.get("ms", {})]
    m = len(vals) // 10
    if m < 1:
        return {"first10_ms": None, "last10_ms": None, "last_over_first": None}
    a = percentile_stats(vals[:m])["median"]
    b = percentile_stats(vals[-m:])["median"]
    return {"first10_ms": a, "last10_ms": b, "last_over_first": (b / a) if a else None}


#: Stages of a keyframe's mapping (Algorithm 1 after the pose guess, recovery, loop closing).
MAPPING_STAGES: tuple[str, ...] = ("init", "fuse", "recover", "loop")


def mapping_stats(frames: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Keyframes and the milliseconds of their mapping (:data:`MAPPING_STAGES` summed).

    The mapping runs in the call that tracks the keyframe, so the lag between a keyframe's
    arrival and its fusion is zero frames.

    Returns
    -------
    dict
        ``keyframes``, ``keyframe_fraction``, ``mapping_ms`` (``median``, ``p95``, ``n``) and
        ``mapping_lag_frames``.
    """
    kf = [f for f in frames if f.get("keyframe") and f.get("state") != "lost"]
    ms = [sum(f.get("ms", {}).get(s, 0.0) for s in MAPPING_STAGES) for f in kf]
    return {"keyframes": len(kf), "keyframe_fraction": len(kf) / len(frames) if frames else None,
            "mapping_ms": percentile_stats(ms), "mapping_lag_frames": 0}


def reset_peak_rss() -> bool:
    """Reset this process's peak resident memory (Linux ``clear_refs``); False where unsupported.

    The memory the runs before freed is handed back to the system first (``gc.collect``,
    then glibc's ``malloc_trim`` where there is one): the peak is reset to the resident
    memory now, and the allocator keeps most of a finished run's heap, so without it the
    next run's peak would start from there."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float | None:
    """Peak resident memory of this process since start or the last :func:`reset_peak_rss`, MB."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def camera_rate_hz(timestamps: Sequence[float]) -> float | None:
    """Frames per second of the camera from the frame timestamps (``None`` when unknown)."""
    if len(timestamps) < 2:
        return None
    span = float(timestamps[-1]) - float(timestamps[0])
    return (len(timestamps) - 1) / span if span > 0 else None


def plot_frames(frames: Sequence[Mapping[str, Any]], path: Path, title: str) -> Path:
    """Per-frame milliseconds against frame index (``total``, ``total + wait``, ``detect``).

    Parameters
    ----------
    frames : sequence of mappings
        ``frames.json`` entries.
    path : Path
        The PNG to write.
    title : str

    Returns
    -------
    Path
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 4), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    k = [f["frame"] for f in frames]
    ms = [f.get("ms", {}) for f in frames]
    ax.plot(k, [m.get("total", float("nan")) for m in ms], lw=1.0, label="total (tracking thread)")
    if any("wait" in m or "load" in m for m in ms):
        ax.plot(k, [m.get("total", float("nan")) + m.get("wait", m.get("load", 0.0)) for m in ms], lw=0.8,
                alpha=0.7, label="total + wait/load (wall per frame)")
    ax.plot(k, [m.get("detect", float("nan")) for m in ms], lw=0.8, alpha=0.7, label="detect")
    ax.plot(k, [m.get("recover", float("nan")) for m in ms], lw=0.8, alpha=0.7, label="recover")
    ax.set_xlabel("frame index")
    ax.set_ylabel("milliseconds per frame")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def parse_settings(items: Sequence[str]) -> dict[str, Any]:
    """``key=value`` front-end settings; values are parsed as JSON when they can be
    (``2``, ``0.03``, ``true``), else kept as strings.

    Raises
    ------
    ValueError
        On an item without ``=``.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set expects key=value, got {item!r}")
        try:
            out[key.strip()] = json.loads(value)
        except ValueError:
            out[key.strip()] = value
    return out


def run_one(source: Path, dataset: str, detector: str, out_dir: Path, settings: Mapping[str, Any],
            max_frames: int | None, smooth: bool, prefetch: int | None) -> dict[str, Any]:
    """One timed run (filter mode) and its summary row; a failure becomes a row with ``error``."""
    row: dict[str, Any] = dict(dataset=dataset, detector=detector, settings=dict(settings), max_frames=max_frames,
                               error=None)
    try:
        from eifslam.evaluation.outputs import write_outputs
        from eifslam.io import open_source
        from eifslam.system.config import SlamConfig
        from eifslam.system.runner import run_sequence

        config = SlamConfig().replace(frontend={"detector": detector, **dict(settings)}, smoothing={"mode": "filter"})
        reset_peak_rss()
        t0, c0 = time.perf_counter(), time.process_time()
        seq = open_source(source)
        run = run_sequence(seq, config, max_frames=max_frames, quiet=True, prefetch=prefetch)
        gt = seq.ground_truth() if getattr(seq, "has_ground_truth", False) else None
        extra = {"source": str(source), **({"stopped": run.stopped} if run.stopped else {})}
        rep = write_outputs(run.slam, out_dir, run.seconds, gt, extra, html=False)
        seconds = time.perf_counter() - t0
        cpu = time.process_time() - c0
        frames = json.loads((out_dir / "frames.json").read_text())["frames"]
        n = len(frames)
        ts = [f["timestamp"] for f in frames]
        rate = camera_rate_hz(ts)
        row.update(frames=n, frames_tracked=rep.get("frames_tracked"), map_features=rep.get("map_features"),
                   seconds=seconds, fps=n / seconds if seconds > 0 else None, loop_seconds=run.seconds,
                   cpu_seconds=cpu, cpu_ms_per_frame=1e3 * cpu / n if n else None,
                   camera_hz=rate, realtime_factor=(n / seconds) / rate if rate and seconds > 0 else None,
                   prefetch=config.runtime.prefetch if prefetch is None else prefetch,
                   ate_filter=rep.get("ate_rmse"), stages=stage_stats(frames), flatness=flatness(frames),
                   stopped=run.stopped, evaluation_error=rep.get("evaluation_error"),
                   tracking_ms=percentile_stats([f["ms"]["total"] for f in frames
                                                 if not f.get("keyframe") and "total" in f.get("ms", {})]),
                   peak_rss_mb=peak_rss_mb(), loops=len(rep.get("loop_closures") or []), **mapping_stats(frames))
        if smooth and gt is not None and run.slam.filter.layout.n_poses >= 2:
            from eifslam.evaluation.metrics import evaluate
            from eifslam.io import Trajectory

            t1 = time.perf_counter()
            run.slam.smooth()
            row["smooth_seconds"] = time.perf_counter() - t1
            try:
                row["ate_smooth"] = evaluate(Trajectory(*run.slam.trajectory()), gt).ate_rmse
            except Exception as exc:  # noqa: BLE001 - recorded in the row
                row["evaluation_error"] = f"smooth: {exc}"
        plot_frames(frames, out_dir / "frames.png", f"{dataset}, {detector}: milliseconds per frame")
    except Exception as exc:  # noqa: BLE001 - one failing run must not stop the benchmark
        row["error"] = f"{type(exc).__name__}: {exc}"
        log(f"{dataset}/{detector} failed:\n{traceback.format_exc()}")
    return row


HEADERS = ("data set", "detector", "frames", "tracked", "keyframes", "loops", "s", "fps", "camera Hz", "CPU ms/frame",
           "ATE filter", "ATE smooth", "detect ms", "match ms", "tracking ms (non-keyframes)", "mapping ms/keyframe",
           "recover ms", "total ms", "wait ms", "last/first 10%", "peak MB", "note")


def table_row(row: Mapping[str, Any]) -> list[str]:
    """Markdown cells of one summary row (median / p95 for the stages)."""
    st = row.get("stages") or {}

    def stage(s: str) -> str:
        v = st.get(s) or (st.get("load") if s == "wait" else None)
        return f"{fmt(v['median'])} / {fmt(v['p95'])}" if v else "–"

    def pair(v: Mapping[str, Any] | None) -> str:
        return f"{fmt(v['median'])} / {fmt(v['p95'])}" if v and v.get("n") else "–"

    name = row.get("dataset", "") + (f" [{row['tag']}]" if row.get("tag") else "")
    return [name, str(row.get("detector")), fmt(row.get("frames")), fmt(row.get("frames_tracked")),
            fmt(row.get("keyframes")), fmt(row.get("loops")),
            fmt(row.get("seconds")), fmt(row.get("fps")), fmt(row.get("camera_hz")),
            fmt(row.get("cpu_ms_per_frame")), fmt(row.get("ate_filter")),
            fmt(row.get("ate_smooth")), stage("detect"), stage("match"), pair(row.get("tracking_ms")),
            pair(row.get("mapping_ms")), stage("recover"), stage("total"), stage("wait"),
            fmt((row.get("flatness") or {}).get("last_over_first")), fmt(row.get("peak_rss_mb")),
            short_error(row.get("error")) or short_error(row.get("stopped"))]


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The summary table in Markdown (stage cells: median / p95 ms per frame)."""
    return markdown_table(HEADERS, [table_row(r) for r in rows])


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/datasets"),
                   help="folder of data sets (each a sub-folder with images/)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--only", default=None,
                   help=f"comma-separated data set names (folder names, '{BUILTIN}' for the built-in scene)")
    p.add_argument("--detectors", default="sift,orb", help="comma-separated detectors (default sift,orb)")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames per run")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="a front-end setting (FrontEndConfig), e.g. max_features=1000; repeatable")
    p.add_argument("--prefetch", type=int, default=None,
                   help="frames detected ahead in a worker thread (default: the config's; 0: none)")
    p.add_argument("--smooth", action="store_true",
                   help="also smooth after the filter run and report the smoothed ATE (not timed in fps)")
    p.add_argument("--tag", default="", help="suffix of the run folders and label of the rows")
    p.add_argument("--builtin-frames", type=int, default=54, help="images of the built-in scene (default 54)")
    p.add_argument("--loop-world", type=Path, default=None, metavar="DIR",
                   help="also run the loop world from DIR (rendered there by 'eifslam render --scene loop' "
                        "when DIR has no images)")
    args = p.parse_args(argv)
    args.detectors = split_list(args.detectors)
    bad = [d for d in args.detectors if d not in DETECTORS]
    if bad or not args.detectors:
        p.error(f"unknown or empty detector list: {bad or '(empty)'}; known {DETECTORS}")
    if args.max_frames is not None and args.max_frames < 2:
        p.error("--max-frames must be at least 2")
    if args.prefetch is not None and args.prefetch < 0:
        p.error("--prefetch must be >= 0")
    try:
        args.settings = parse_settings(args.settings)
    except ValueError as exc:
        p.error(str(exc))
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run every data set and detector; 0 when every run worked, 1 when one failed, 2 on bad input."""
    args = parse_args(argv)
    found: list[tuple[str, Path | None]] = [(p.name, p) for p in discover_datasets(args.data)]
    found.append((BUILTIN, None))
    if args.loop_world is not None:
        if not (args.loop_world / "images").is_dir():
            from eifslam.cli.main import main as eifslam_main

            if eifslam_main(["render", "--scene", "loop", "--out", str(args.loop_world)]) != 0:
                log(f"could not render the loop world into {args.loop_world}")
                return 2
        found.append((LOOP_WORLD, args.loop_world))
    only = split_list(args.only)
    selected = [(n, p) for n, p in found if not only or n in only]
    missing = [n for n in only if n not in {n for n, _ in found}]
    if missing:
        log(f"no data set named {', '.join(missing)} under {args.data}")
    if not selected:
        log("nothing to run")
        return 2
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = dict(command=command_line(__spec__.name, sys.argv[1:] if argv is None else argv),
                                   machine=machine_info(), settings=args.settings, rows=[])
    for name, path in selected:
        if path is None:
            path, _ = prepare_builtin(out, args.builtin_frames)
        for det in args.detectors:
            folder = out / (f"{name}-{det}" + (f"-{args.tag}" if args.tag else ""))
            log(f"{name} / {det}" + (f" / {args.settings}" if args.settings else ""))
            row = run_one(path, name, det, folder, args.settings, args.max_frames, args.smooth, args.prefetch)
            row["tag"] = args.tag
            summary["rows"].append(row)
            write_json(out / "realtime.json", summary)
            if row["error"] is None:
                log(f"  {row['frames']} frames in {row['seconds']:.1f} s ({row['fps']:.2f} fps), "
                    f"ATE {fmt(row.get('ate_filter'))}")
    table = format_table(summary["rows"])
    (out / "realtime.md").write_text(markdown_header("eifslam speed per frame", summary["command"], summary["machine"])
                                     + table)
    print(table, end="")
    return 1 if any(r["error"] for r in summary["rows"]) else 0


if __name__ == "__main__":
    sys.exit(main())
