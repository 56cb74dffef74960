"""Shared helpers of the benchmarks.

Pure parts (no OpenCV, no SLAM): data set discovery, the COLMAP reference figures,
turning a ``report.json`` dict into a flat result row, Markdown tables, and the
provenance of a result (date, machine, commit, command): :func:`machine_info`,
:func:`command_line` and :func:`markdown_header`, which every benchmark that writes a
Markdown page puts at its top. The SLAM-running parts (:func:`run_one`,
:func:`prepare_builtin`) import eifslam lazily.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import traceback
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

#: Name of the built-in rendered scene in ``--only`` / ``--datasets`` lists and in results.
BUILTIN = "builtin"

#: COLMAP ATE RMSE on the shared data (``../shared/EVALUATION.md``), in the ground
#: truth's units. middlebury-templering: on the 24 of 31 frames COLMAP registered.
COLMAP_ATE: dict[str, float] = {
    "kitti-seq1": 0.024,
    "strecha-fountain-p11": 0.0034,
    "middlebury-templering": 0.0012,
    "7scenes-redkitchen-a": 0.038,
    "strecha-herzjesu-p25": 0.0059,  # COLMAP at 768 px (../shared/EVALUATION.md)
    "strecha-castle-p30": 0.169,
}

#: Frame stages timed by :class:`eifslam.system.slam.Slam` (``report.json`` ``stage_ms_median``).
STAGES: tuple[str, ...] = ("detect", "match", "relative_pose", "covariance", "init", "fuse", "recover", "total")

#: Stages of the back end (the EIF): fusion and recovery.
BACKEND_STAGES: tuple[str, ...] = ("fuse", "recover")


def log(msg: str) -> None:
    """Print a progress message to stderr (stdout is kept for the final table).

    Parameters
    ----------
    msg : str
        The message, printed with a ``[bench]`` prefix.
    """
    print(f"[bench] {msg}", file=sys.stderr, flush=True)


def split_list(text: str | None) -> list[str]:
    """Split a comma-separated option value, dropping blanks.

    Parameters
    ----------
    text : str or None
        E.g. ``"filter, smooth,ba"``.

    Returns
    -------
    list of str
        ``["filter", "smooth", "ba"]``; ``[]`` for ``None`` or an empty string.
    """
    if not text:
        return []
    return [s.strip() for s in text.split(",") if s.strip()]


def discover_datasets(data: str | Path) -> list[Path]:
    """Data set folders directly under ``data``: the sub-folders holding an ``images/`` folder.

    Parameters
    ----------
    data : str or Path
        Folder of data sets (e.g. ``../shared/datasets``). A missing folder gives ``[]``.

    Returns
    -------
    list of Path
        Sorted by name. Hidden folders are skipped.
    """
    root = Path(data)
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir()
                  if p.is_dir() and not p.name.startswith(".") and (p / "images").is_dir())


def _num(v: Any) -> float | None:
    """``v`` as a finite float, else ``None``."""
    if v is None or isinstance(v, bool):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def build_row(dataset: str, mode: str, detector: str, report: Mapping[str, Any] | None = None,
              error: str | None = None, **extra: Any) -> dict[str, Any]:
    """One flat result row from a run's ``report.json`` dict (or from a failure).

    Parameters
    ----------
    dataset, mode, detector : str
        What was run.
    report : mapping, optional
        The dict :func:`eifslam.evaluation.outputs.run_to_folder` returns (possibly updated
        with the box-ratio figures). ``None`` when the run failed before writing one.
    error : str, optional
        Why the run failed (``"ExcType: message"``).
    **extra
        Further keys copied into the row (e.g. ``map_fraction``).

    Returns
    -------
    dict
        Keys: ``dataset, mode, detector, frames, frames_tracked, tracked_pct, map_features,
        ate_rmse, ate_percent, colmap_ate, ate_ratio_colmap, fps, total_seconds,
        ms_<stage>`` for every stage of :data:`STAGES`, ``ms_backend`` (median per-frame
        fuse + recover; here the sum of the two medians unless ``extra`` gives it), ``box_ratio_true, box_ratio_estimated, box_ratio_points,
        box_ratio_error_percent`` (``None`` when absent), ``ba`` (the report's ``ba``
        section or ``None``), ``stopped`` (the runner's note when the loop stopped early or
        a final pass failed), ``evaluation_error`` and ``error``. Missing figures are ``None``.
    """
    rep: Mapping[str, Any] = report or {}
    frames = rep.get("frames")
    tracked = rep.get("frames_tracked")
    tracked_pct = (100.0 * tracked / frames) if frames and tracked is not None else None
    ate = _num(rep.get("ate_rmse"))
    colmap = COLMAP_ATE.get(dataset)
    stages = rep.get("stage_ms_median") or {}
    row: dict[str, Any] = dict(
        dataset=dataset, mode=mode, detector=detector,
        frames=frames, frames_tracked=tracked, tracked_pct=tracked_pct,
        map_features=rep.get("map_features"),
        ate_rmse=ate, ate_percent=_num(rep.get("ate_percent")),
        colmap_ate=colmap,
        ate_ratio_colmap=(ate / colmap) if ate is not None and colmap else None,
        fps=_num(rep.get("fps")), total_seconds=_num(rep.get("total_seconds")),
    )
    for s in STAGES:
        row[f"ms_{s}"] = _num(stages.get(s))
    backend = [row[f"ms_{s}"] for s in BACKEND_STAGES if row[f"ms_{s}"] is not None]
    row["ms_backend"] = sum(backend) if backend else None
    for key in ("box_ratio_true", "box_ratio_estimated", "box_ratio_points", "box_ratio_error_percent"):
        row[key] = rep.get(key)
    row["ba"] = rep.get("ba")
    row["stopped"] = rep.get("stopped")
    row["evaluation_error"] = rep.get("evaluation_error")
    row["error"] = error
    row.update(extra)
    return row


def fmt(v: Any, digits: int = 3) -> str:
    """Format a table cell: ``–`` for missing, ``digits`` significant digits for floats.

    Parameters
    ----------
    v : any
        The value.
    digits : int
        Significant digits of a float.

    Returns
    -------
    str
    """
    if v is None:
        return "–"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):
        return str(v)
    f = _num(v)
    if f is None:
        return str(v).replace("|", "\\|").replace("\n", " ")
    if f == 0:
        return "0"
    if abs(f) >= 10 ** digits:
        return f"{f:.0f}"
    return f"{f:.{digits}g}"


def markdown_table(headers: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A GitHub Markdown table.

    Parameters
    ----------
    headers : sequence of str
        Column titles.
    rows : iterable of sequences of str
        Cells, already formatted; ``|`` and newlines are escaped.

    Returns
    -------
    str
        The table, one line per row, ending with a newline.
    """
    def clean(c: str) -> str:
        return str(c).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(clean(h) for h in headers) + " |",
             "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(clean(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def short_error(msg: str | None, limit: int = 80) -> str:
    """The first line of an error message, cut to ``limit`` characters (``""`` for none)."""
    if not msg:
        return ""
    first = str(msg).strip().splitlines()[0] if str(msg).strip() else ""
    return first if len(first) <= limit else first[: limit - 1] + "…"


def git_describe(repo: Path | None = None) -> str | None:
    """Short commit id of the checkout holding ``repo`` (``+dirty`` when files changed), or ``None``."""
    cwd = str(repo or Path(__file__).resolve().parent)
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=cwd, capture_output=True,
                             text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd,
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return rev + ("+dirty" if dirty else "") if rev else None


def machine_info() -> dict[str, Any]:
    """Where and with what a benchmark ran.

    Returns
    -------
    dict
        ``date_utc`` (ISO 8601), ``platform`` (:func:`platform.platform`), ``cpu_count``,
        ``cpus_usable`` (the process's CPU affinity when known), ``python``, ``numpy``,
        ``scipy``, ``opencv``, ``eifslam_commit``.
    """
    import numpy
    import scipy

    try:
        import cv2

        opencv = cv2.__version__
    except ImportError:  # pragma: no cover - opencv is a dependency
        opencv = None
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = None
    return dict(date_utc=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                platform=platform.platform(), cpu_count=os.cpu_count(), cpus_usable=usable,
                python=platform.python_version(), numpy=numpy.__version__, scipy=scipy.__version__,
                opencv=opencv, eifslam_commit=git_describe())


def command_line(module: str, argv: Sequence[str]) -> str:
    """The shell command that reproduces a run: ``python -m <module> <argv>``.

    Parameters
    ----------
    module : str
        The benchmark's module name (``__spec__.name``, e.g. ``"benchmarks.run_all"``),
        run from the repository's root.
    argv : sequence of str
        Its arguments.

    Returns
    -------
    str
        The command, quoted for a POSIX shell.

    Examples
    --------
    >>> command_line("benchmarks.run_all", ["--out", "a b"])
    "python -m benchmarks.run_all --out 'a b'"
    """
    return shlex.join(["python", "-m", module, *map(str, argv)])


def provenance_markdown(info: Mapping[str, Any], command: str) -> str:
    """The provenance lines of a generated Markdown page: date, machine, commit, versions, command.

    Parameters
    ----------
    info : mapping
        From :func:`machine_info`.
    command : str
        From :func:`command_line`.

    Returns
    -------
    str
        Markdown bullet list followed by a blank line.
    """
    cpus = f"{info.get('cpu_count')} CPUs"
    if info.get("cpus_usable") not in (None, info.get("cpu_count")):
        cpus += f" ({info.get('cpus_usable')} usable)"
    lines = [
        f"- Date: {info.get('date_utc')}",
        f"- Machine: {info.get('platform')}, {cpus}",
        f"- Commit: {info.get('eifslam_commit') or 'unknown'}",
        f"- Python {info.get('python')}, OpenCV {info.get('opencv')}, NumPy {info.get('numpy')}, "
        f"SciPy {info.get('scipy')}",
        f"- Command: `{command}`",
    ]
    return "\n".join(lines) + "\n\n"


def markdown_header(title: str, command: str, info: Mapping[str, Any] | None = None) -> str:
    """The top of every Markdown page a benchmark generates: title, then its provenance.

    Parameters
    ----------
    title : str
        The page's title (a level-1 heading).
    command : str
        From :func:`command_line`.
    info : mapping, optional
        From :func:`machine_info` (default: the current machine, now).

    Returns
    -------
    str
        ``# title``, a line saying the page is generated, and :func:`provenance_markdown`.
    """
    return (f"# {title}\n\n"
            "Generated by the command below; re-run it rather than edit this page.\n\n"
            + provenance_markdown(info or machine_info(), command))


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON (atomically: a temporary file then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=float))
    tmp.replace(path)


def backend_ms_median(frames_json: Path) -> float | None:
    """Median over frames of the per-frame back-end time (fuse + recover), in ms.

    Parameters
    ----------
    frames_json : Path
        A run's ``frames.json`` (``{"frames": [{"ms": {stage: ms}}, ...]}``).

    Returns
    -------
    float or None
        Over the frames that have a fuse or recover time; ``None`` when there are none
        or the file cannot be read.
    """
    try:
        frames = json.loads(Path(frames_json).read_text())["frames"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    vals = [sum(float(f["ms"].get(s, 0.0)) for s in BACKEND_STAGES)
            for f in frames if any(s in f.get("ms", {}) for s in BACKEND_STAGES)]
    if not vals:
        return None
    vals.sort()
    n = len(vals)
    return vals[n // 2] if n % 2 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])


# -- running ------------------------------------------------------------------------------
def prepare_builtin(out: Path, n_frames: int = 54) -> tuple[Path, Any]:
    """Render the built-in scene (the paper's first experiment) once into ``out/builtin-scene``.

    Parameters
    ----------
    out : Path
        The benchmark's output folder.
    n_frames : int
        Number of images of the scene (paper: 54).

    Returns
    -------
    (Path, BuiltinScene)
        The data folder and the scene (needed for the box-ratio figures).
    """
    from eifslam.sim.scene import make_scene, render_scene

    scene = make_scene(n_frames=n_frames)
    data = out / "builtin-scene"
    log(f"rendering the built-in scene ({n_frames} images of {scene.camera.width}x{scene.camera.height}) into {data}")
    render_scene(scene, data)
    return data, scene


def run_one(source: Path, dataset: str, mode: str, detector: str, out_dir: Path,
            frontend: Mapping[str, Any] | None = None, max_frames: int | None = None,
            scene: Any = None, quiet: bool = True,
            runner: Callable[..., dict[str, Any]] | None = None, **row_extra: Any) -> dict[str, Any]:
    """Run SLAM once and return its result row; a failure becomes a row with ``error``.

    Parameters
    ----------
    source : Path
        Data folder (anything :func:`eifslam.io.open_source` reads).
    dataset, mode, detector : str
        Names for the row; ``mode`` and ``detector`` configure the run.
    out_dir : Path
        Where the run writes ``trajectory.tum``, ``map.ply``, ``report.json`` (no HTML).
    frontend : mapping, optional
        Further front-end settings (e.g. ``{"map_fraction": 0.5}``).
    max_frames : int, optional
        Process at most this many frames.
    scene : BuiltinScene, optional
        For the built-in scene: adds the box-ratio figures (also written to ``report.json``).
    quiet : bool
        Hide the per-frame progress bar.
    runner : callable, optional
        Replacement of :func:`eifslam.evaluation.outputs.run_to_folder` (tests).
    **row_extra
        Copied into the row.

    Returns
    -------
    dict
        From :func:`build_row`.
    """
    try:
        from eifslam.evaluation.outputs import run_to_folder
        from eifslam.system.config import SlamConfig
        from eifslam.io import open_source

        config = SlamConfig().replace(frontend={"detector": detector, **dict(frontend or {})},
                                      smoothing={"mode": mode})
        seq = open_source(source)
        rep = (runner or run_to_folder)(seq, config, out_dir, max_frames=max_frames, html=False, quiet=quiet)
        if scene is not None and rep.get("frames_tracked", 0) >= 3:
            from eifslam.evaluation.box_ratio import add_box_ratio

            add_box_ratio(rep, out_dir, scene)
        backend = backend_ms_median(out_dir / "frames.json")
        if backend is not None:
            row_extra = {"ms_backend": backend, **row_extra}
        return build_row(dataset, mode, detector, rep, **row_extra)
    except Exception as exc:  # one failing run must not stop the benchmark
        traceback.print_exc(file=sys.stderr)
        log(f"FAILED {dataset} {mode} {detector}: {type(exc).__name__}: {exc}")
        return build_row(dataset, mode, detector, None, error=f"{type(exc).__name__}: {exc}", **row_extra)
