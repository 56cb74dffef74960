"""Many runs at once: the part of ``eifslam batch`` that does not depend on an engine.

A batch is a list of :class:`BatchTask`, one per (source, setting); each task runs SLAM
over one source with one configuration into its own folder, exactly as ``eifslam run``
would (:func:`~eifslam.evaluation.outputs.run_to_folder`), and gives back one flat result
row. What runs the tasks (in this process one after another, :func:`run_serial`, or on a
Dask cluster, :mod:`eifslam.cli.cluster`) is the caller's choice; this module owns

* the task list (:func:`make_tasks`): folder names unique per (data set, mode, features);
* the task function (:func:`run_task`): never raises, a failure is a row with ``error``;
* the completeness check (:func:`is_complete`): ``report.json``, written last and
  atomically, is present and parseable, and the run was not interrupted;
* the rows of tasks that could not run (:func:`failed_row`, :func:`skipped_row`) and the
  results files (:func:`write_results`: ``results.json`` and ``results.md``).

Ground truth is only for scoring: the loaders find it, :func:`run_to_folder` scores the
finished estimate with it, and the row copies the ATE from ``report.json``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from ..errors import EifslamError
from ..io.files import atomic_write
from ..system.config import SlamConfig

__all__ = ["BatchTask", "make_tasks", "dataset_names", "is_complete", "run_task", "run_serial", "failed_row",
           "skipped_row", "write_results", "results_markdown", "one_line", "ROW_KEYS"]

#: the keys of every result row, in the order ``results.md`` shows them
ROW_KEYS = ("dataset", "mode", "features", "status", "frames", "tracked", "map_features", "ate_rmse",
            "ate_units", "seconds", "cpu_seconds", "error", "out", "source")


@dataclass(frozen=True)
class BatchTask:
    """One run of a batch: a source, a configuration and the folder of its outputs.

    Plain data (strings and a configuration mapping), so that it pickles to another
    process or machine unchanged.

    Attributes
    ----------
    source : str
        Anything :func:`eifslam.io.open_source` reads (a data folder, a layout, a video).
    dataset : str
        The source's name in the rows (unique within the batch).
    config : dict
        :meth:`SlamConfig.to_dict` of the run's configuration.
    out_dir : str
        The run's output folder (``OUT/<dataset>-<mode>-<features>``).
    max_frames : int or None
        Process at most this many frames.
    html : bool
        Also write ``report.html``.
    extra : dict
        Copied into ``report.json`` (the command's provenance).
    """

    source: str
    dataset: str
    config: dict
    out_dir: str
    max_frames: int | None = None
    html: bool = True
    extra: dict = field(default_factory=dict)

    @property
    def mode(self) -> str:
        """The system's mode (``filter``, ``smooth`` or ``ba``)."""
        return str(self.config["smoothing"]["mode"])

    @property
    def features(self) -> str:
        """The feature detector."""
        return str(self.config["frontend"]["detector"])

    @property
    def name(self) -> str:
        """The output folder's name: ``<dataset>-<mode>-<features>``."""
        return f"{self.dataset}-{self.mode}-{self.features}"


def dataset_names(sources: Sequence[str | Path]) -> list[str]:
    """A name per source, unique within the list: the folder's name (a video file's stem),
    with ``-2``, ``-3``, ... after a name already taken.

    Examples
    --------
    >>> dataset_names(["a/kitti", "b/kitti", "clip.mp4"])
    ['kitti', 'kitti-2', 'clip']
    """
    names: list[str] = []
    for s in sources:
        p = Path(s)
        base = (p.stem if p.suffix and not p.is_dir() else p.name) or p.resolve().name or "source"
        name, k = base, 1
        while name in names:
            k += 1
            name = f"{base}-{k}"
        names.append(name)
    return names


def make_tasks(sources: Sequence[str | Path], configs: Sequence[SlamConfig], out: str | Path,
               max_frames: int | None = None, html: bool = True,
               extra: Callable[[SlamConfig], dict] | None = None,
               names: Sequence[str] | None = None) -> list[BatchTask]:
    """One task per (source, configuration), sources first.

    Parameters
    ----------
    sources : sequence of paths
        What to run on.
    configs : sequence of SlamConfig
        The settings; two with the same mode and detector would share a folder and are
        refused.
    out : path
        The batch's folder; each task writes into ``out/<dataset>-<mode>-<features>``.
    max_frames, html
        As :class:`BatchTask`.
    extra : callable, optional
        ``config -> dict`` copied into each task's ``report.json``.
    names : sequence of str, optional
        The sources' names (default :func:`dataset_names`); must be unique.

    Returns
    -------
    list of BatchTask

    Raises
    ------
    EifslamError
        Two configurations share a mode and a detector, or two sources a name.
    """
    names = list(names) if names is not None else dataset_names(sources)
    if len(set(names)) != len(names) or len(names) != len(sources):
        raise EifslamError(f"the batch's sources need one name each, all different (got {names})")
    seen: set[tuple[str, str]] = set()
    for c in configs:
        key = (str(c.smoothing.mode), str(c.frontend.detector))
        if key in seen:
            raise EifslamError(f"two settings of the batch have mode {key[0]} and features {key[1]}: "
                               "their outputs would share a folder")
        seen.add(key)
    tasks = []
    for src, name in zip(sources, names):
        for c in configs:
            d = c.to_dict()
            folder = f"{name}-{d['smoothing']['mode']}-{d['frontend']['detector']}"
            tasks.append(BatchTask(source=str(src), dataset=name, config=d, out_dir=str(Path(out) / folder),
                                   max_frames=max_frames, html=html, extra=dict(extra(c)) if extra else {}))
    return tasks


def _report(out_dir: str | Path) -> dict[str, Any] | None:
    """The folder's ``report.json`` as a dict, or ``None`` when absent or unreadable."""
    try:
        rep = json.loads((Path(out_dir) / "report.json").read_text())
    except (OSError, ValueError):
        return None
    return rep if isinstance(rep, dict) else None


def is_complete(out_dir: str | Path) -> bool:
    """Whether a task's folder holds a finished run: ``report.json`` (written last, and
    atomically) is there and parses, and the run was not interrupted before its last frame."""
    rep = _report(out_dir)
    return rep is not None and not str(rep.get("stopped") or "").startswith("interrupted")


def one_line(exc: BaseException) -> str:
    """An exception as one line: an eifslam error's own message, else ``Type: message``."""
    text = str(exc) if isinstance(exc, EifslamError) else f"{type(exc).__name__}: {exc}".rstrip(": ")
    return " ".join(text.split()) or type(exc).__name__


def _row(task: BatchTask, status: str, rep: Mapping[str, Any] | None, seconds: float | None,
         error: str | None, cpu_seconds: float | None = None) -> dict[str, Any]:
    rep = rep or {}
    frames, tracked = rep.get("frames"), rep.get("frames_tracked")
    if error is None and rep.get("stopped"):
        error = f"stopped early: {rep['stopped']}"
    if error is None and frames is not None and not tracked:
        error = f"no frame could be tracked ({frames} read)"
    return dict(dataset=task.dataset, mode=task.mode, features=task.features, status=status, frames=frames,
                tracked=tracked, map_features=rep.get("map_features"), ate_rmse=rep.get("ate_rmse"),
                ate_units=rep.get("ate_units"), seconds=None if seconds is None else round(seconds, 3),
                cpu_seconds=None if cpu_seconds is None else round(cpu_seconds, 3),
                error=None if error is None else " ".join(str(error).split()), out=task.out_dir, source=task.source)


def failed_row(task: BatchTask, error: str, seconds: float | None = None) -> dict[str, Any]:
    """The row of a task that gave no report (its worker died, it was cancelled, ...)."""
    return _row(task, "failed", _report(task.out_dir) if is_complete(task.out_dir) else None, seconds, error)


def skipped_row(task: BatchTask) -> dict[str, Any]:
    """The row of a task whose folder is already complete, from its ``report.json``
    (``seconds`` is that run's ``total_seconds``)."""
    rep = _report(task.out_dir) or {}
    return _row(task, "skipped", rep, rep.get("total_seconds"), None)


def run_task(task: BatchTask, quiet: bool = True) -> dict[str, Any]:
    """Run one task into its folder, as ``eifslam run`` would; never raises.

    A ``report.json`` left by an earlier run is removed first, so the folder counts as
    complete again only once this run has written its own.

    Parameters
    ----------
    task : BatchTask
    quiet : bool
        No per-frame progress bar and no summary line.

    Returns
    -------
    dict
        The row: ``dataset, mode, features, status`` (``done`` or ``failed``), ``frames,
        tracked`` (frames with a pose), ``map_features, ate_rmse, ate_units`` (``None``
        without ground truth), ``seconds`` (wall time of the task), ``cpu_seconds`` (CPU
        time of the process during the task, all its threads), ``error`` (one line or
        ``None``), ``out``, ``source``.
    """
    from ..io import open_source
    from .outputs import run_to_folder

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        (Path(task.out_dir) / "report.json").unlink(missing_ok=True)
        config = SlamConfig.from_dict(task.config)
        seq = open_source(task.source)
        rep = run_to_folder(seq, config, task.out_dir, max_frames=task.max_frames, html=task.html,
                            extra=dict(task.extra), quiet=quiet, verbose=not quiet)
    except Exception as exc:  # noqa: BLE001 - one failing task must not stop the others
        return _row(task, "failed", None, time.perf_counter() - t0, one_line(exc), time.process_time() - c0)
    row = _row(task, "done", rep, time.perf_counter() - t0, None, time.process_time() - c0)
    if row["error"]:
        row["status"] = "failed"
    return row


def run_serial(tasks: Sequence[BatchTask], force: bool = False, quiet: bool = True,
               on_row: Callable[[int, dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Run the tasks one after another in this process (the engine without Dask).

    Parameters
    ----------
    tasks : sequence of BatchTask
    force : bool
        Redo the tasks whose folders are complete (else they are skipped).
    quiet : bool
        As :func:`run_task`.
    on_row : callable, optional
        ``(index, row)`` after each task (e.g. to rewrite ``results.json``).

    Returns
    -------
    list of dict
        The rows, in the order of ``tasks``.
    """
    rows = []
    for k, task in enumerate(tasks):
        row = skipped_row(task) if not force and is_complete(task.out_dir) else run_task(task, quiet=quiet)
        rows.append(row)
        if on_row is not None:
            on_row(k, row)
    return rows


def _cell(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v).replace("|", "\\|")


def results_markdown(rows: Iterable[Mapping[str, Any]]) -> str:
    """The rows as a Markdown table (one line per task)."""
    heads = ("data set", "mode", "features", "status", "tracked", "map features", "ATE", "seconds", "error")
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for r in rows:
        tracked = f"{r['tracked']}/{r['frames']}" if r.get("frames") is not None else None
        ate = None if r.get("ate_rmse") is None else f"{r['ate_rmse']:.4g} {r.get('ate_units') or ''}".rstrip()
        cells = (r.get("dataset"), r.get("mode"), r.get("features"), r.get("status"), tracked,
                 r.get("map_features"), ate, r.get("seconds"), r.get("error"))
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def write_results(out: str | Path, rows: Sequence[Mapping[str, Any]], title: str = "eifslam batch") -> None:
    """Write ``out/results.json`` (the rows) and ``out/results.md`` (their table), atomically.

    Raises
    ------
    OutputError
        A file cannot be written (names it).
    """
    out = Path(out)
    atomic_write(out / "results.json", json.dumps(list(rows), indent=2, default=float) + "\n")
    failed = sum(bool(r.get("error")) for r in rows)
    atomic_write(out / "results.md", f"# {title}\n\n{len(rows)} tasks, {failed} failed.\n\n"
                 + results_markdown(rows))
