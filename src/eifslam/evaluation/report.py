"""HTML report of an ``eifslam run`` output folder.

Reads what the run wrote (``trajectory.tum``, ``map.ply``, ``information.npz``,
``frames.json``, ``report.json``), draws the figures of :mod:`eifslam.evaluation.plots` into
``figures/*.png`` and writes ``report.html`` beside them, referring to the pictures by
relative paths so that the folder can be moved or zipped as a whole. A missing, empty or
unreadable input leaves its figure out with a note in the page; it never stops the report.
"""

from __future__ import annotations

import functools
import json
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import jinja2
import numpy as np
import scipy.sparse as sp
from markupsafe import Markup
from numpy.typing import NDArray

from ..errors import DatasetError, EifslamError, OutputError
from ..io.files import atomic_path, atomic_write
from ..io.ply import read_ply
from ..io.trajectory import Trajectory, read_tum
from .metrics import GT_UNITS
from .report_tables import flatten as _flatten, table as _table

Array = NDArray[np.float64]

__all__ = ["FrameLog", "parse_frames", "read_frames", "write_report"]

FIGURE_DIR = "figures"
_DPI = 110


@dataclass(frozen=True)
class FrameLog:
    """Per-frame records of ``frames.json`` as arrays (one entry per frame).

    Attributes
    ----------
    frame : (N,) int64
        Frame numbers (the record's position when a record has none).
    timestamp, state_dim, map_features, nnz : (N,) float64
        Seconds; state-vector size; features in the map; non-zeros of the information
        matrix. NaN where a record lacks the value.
    state : tuple of N str
        ``"initialising"``, ``"tracking"``, ``"lost"`` (``"unknown"`` when missing).
    stage_ms : dict of str -> (N,) float64
        Milliseconds per stage (``"detect"``, ..., ``"total"``), NaN where missing.
    """

    frame: NDArray[np.int64]
    timestamp: Array
    state: tuple[str, ...]
    stage_ms: dict[str, Array] = field(repr=False)
    state_dim: Array = field(repr=False)
    map_features: Array = field(repr=False)
    nnz: Array = field(repr=False)

    def __len__(self) -> int:
        return int(self.frame.shape[0])


def _number(value: Any) -> float:
    """``value`` as a finite float, else NaN (``None``, strings, booleans, inf)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    v = float(value)
    return v if math.isfinite(v) else math.nan


def parse_frames(data: Any) -> FrameLog:
    """Build a :class:`FrameLog` from decoded ``frames.json`` content.

    Accepts ``{"frames": [...]}`` or a bare list; records that are not objects and
    missing or non-numeric values are tolerated (NaN).
    """
    records = data.get("frames", []) if isinstance(data, dict) else data
    if not isinstance(records, list):
        raise DatasetError("'frames' is not a list")
    records = [r for r in records if isinstance(r, dict)]
    stages: list[str] = []
    for r in records:
        ms = r.get("ms")
        for k in ms if isinstance(ms, dict) else ():
            if k not in stages:
                stages.append(str(k))

    def column(key: str) -> Array:
        return np.array([_number(r.get(key)) for r in records], dtype=np.float64).reshape(-1)

    frame = column("frame")
    frame = np.where(np.isfinite(frame), frame, np.arange(len(records))).astype(np.int64)
    stage_ms = {
        s: np.array([_number(r["ms"].get(s)) if isinstance(r.get("ms"), dict) else math.nan
                     for r in records], dtype=np.float64).reshape(-1)
        for s in stages
    }
    state = tuple(str(r.get("state", "unknown")) for r in records)
    return FrameLog(frame, column("timestamp"), state, stage_ms,
                    column("state_dim"), column("map_features"), column("nnz"))


def read_frames(path: str | Path) -> FrameLog:
    """Read ``frames.json`` (see :func:`parse_frames`).

    Raises
    ------
    DatasetError
        The file is missing or is not JSON.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read JSON ({exc})") from None
    try:
        return parse_frames(data)
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None


def _load(path: Path, reader: Callable[[Path], Any], notes: list[str]) -> Any:
    """``reader(path)``, or ``None`` with a note when the file is missing or unreadable."""
    if not path.is_file():
        notes.append(f"{path.name} not found.")
        return None
    try:
        return reader(path)
    except (EifslamError, OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        notes.append(f"{path.name} could not be read: {exc}")
        return None


def _read_information(path: Path) -> sp.csr_array:
    return sp.csr_array(sp.load_npz(path))


def _read_json_dict(path: Path) -> dict[str, Any]:
    data = json.loads(path.read_text())
    if not isinstance(data, dict):
        raise DatasetError(f"expected a JSON object, got {type(data).__name__}")
    return data


@dataclass
class _Section:
    """One figure of the page: a PNG (relative path) or a note saying why it is missing."""

    title: str
    image: str | None = None
    caption: str = ""
    notes: list[str] = field(default_factory=list)


def _save(fig: Any, out_dir: Path, name: str) -> str:
    """Save ``fig`` as ``out_dir/figures/name``; return the path relative to ``out_dir``."""
    rel = f"{FIGURE_DIR}/{name}"
    try:
        with atomic_path(out_dir / rel) as tmp:
            fig.savefig(tmp, dpi=_DPI)
    except (OSError, OutputError) as exc:
        raise DatasetError(f"{out_dir / rel}: cannot save figure ({exc})") from None
    finally:
        fig.clear()
    return rel


def _figure(figsize: tuple[float, float]) -> Any:
    """A figure drawn by the Agg renderer, outside pyplot.

    No pyplot figure manager is involved, so nothing has to be closed, the caller's
    backend is left alone (switching it would close the caller's open figures), and no
    display is needed.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _map_sections(out_dir: Path, traj: Trajectory | None, points: Array | None,
                  colors: NDArray[np.uint8] | None, notes: list[str]) -> list[_Section]:
    """Top view and 3-D view of trajectory and map."""
    from .plots import plot_map_3d, plot_map_top

    top = _Section("Trajectory and map, top view", notes=list(notes))
    view = _Section("Trajectory and map, 3-D view")
    C = np.zeros((0, 3)) if traj is None else traj.positions
    R = None if traj is None else traj.rotations
    P = np.zeros((0, 3)) if points is None else points
    if len(C) < 2 and len(P) == 0:
        msg = f"Nothing to draw: {len(C)} camera pose(s) and no map features."
        top.notes.append(msg)
        view.notes.append(msg)
        return [top, view]
    if len(P) == 0:
        top.notes.append("The map has no features; only the trajectory is drawn.")
    caption = f"{len(C)} camera poses, {len(P)} map features" + (
        " (a random 20,000 drawn)." if len(P) > 20_000 else ".")
    fig = _figure(figsize=(7.5, 6.5))
    plot_map_top(fig.add_subplot(), C, P, colors, R)
    top.image, top.caption = _save(fig, out_dir, "map_top.png"), caption
    fig = _figure(figsize=(7.5, 6.5))
    plot_map_3d(fig.add_subplot(projection="3d"), C, P, colors, R)
    view.image, view.caption = _save(fig, out_dir, "map_3d.png"), caption
    if len(C) < 2:
        return [top, view]
    # the map near the cameras: what they looked at, without the far features (walls,
    # distant points) that set the extent of the full view
    close = _Section("Trajectory and map, close-up (the region the cameras travelled, with a margin)")
    lo, hi = C.min(0), C.max(0)
    pad = 0.3 * max(float((hi - lo).max()), 1e-9)
    lo, hi = lo - pad, hi + pad
    inside = int(np.all((P >= lo) & (P <= hi), axis=1).sum()) if len(P) else 0
    fig = _figure(figsize=(7.5, 6.5))
    plot_map_top(fig.add_subplot(), C, P, colors, R, limits=(lo, hi))
    close.image = _save(fig, out_dir, "map_top_close.png")
    close.caption = f"{inside} of the {len(P)} map features lie in this region; camera wedges show where they looked."
    return [top, close, view]


def _read_layout(path: Path) -> NDArray[np.bool_]:
    """Per state entry, whether it belongs to a feature, from ``state_layout.json``
    (``{"kinds": "pff..."}``: one letter per state, a pose of 7 entries or a feature of 3)."""
    data = json.loads(path.read_text())
    kinds = data.get("kinds") if isinstance(data, dict) else None
    if not isinstance(kinds, str) or set(kinds) - {"p", "f"}:
        raise ValueError("'kinds' must be a string of 'p' and 'f'")
    isf = np.frombuffer(kinds.encode(), np.uint8) == ord("f")
    return np.repeat(isf, np.where(isf, 3, 7))


def _sparsity_section(out_dir: Path, info: sp.csr_array | None, notes: list[str],
                      is_feature: NDArray[np.bool_] | None = None) -> _Section:
    """Sparsity pattern of the final information matrix."""
    from .plots import plot_information_sparsity

    sec = _Section("Sparsity of the information matrix", notes=list(notes))
    if info is None:
        return sec
    if info.shape[0] == 0 or info.shape[1] == 0:
        sec.notes.append(f"The information matrix is empty ({info.shape[0]} × {info.shape[1]}).")
        return sec
    fig = _figure(figsize=(6.5, 6.5))
    if is_feature is not None and len(is_feature) != info.shape[0]:
        sec.notes.append(f"state_layout.json describes {len(is_feature)} entries, the matrix has "
                         f"{info.shape[0]}: the pose and feature blocks are not marked.")
        is_feature = None
    plot_information_sparsity(fig.add_subplot(), info, is_feature=is_feature)
    sec.image = _save(fig, out_dir, "information_sparsity.png")
    n = info.shape[0]
    nnz = int(sp.coo_array(info).count_nonzero())
    sec.caption = (f"Final information matrix, {n} × {info.shape[1]}, {nnz} non-zeros "
                   f"({100.0 * nnz / (n * info.shape[1]):.3g} % filled).")
    return sec


def _timing_section(out_dir: Path, frames: FrameLog | None, notes: list[str]) -> _Section:
    """Per-frame time by stage against frame number and against state size."""
    from .plots import plot_stage_times

    sec = _Section("Time per frame", notes=list(notes))
    if frames is None:
        return sec
    stages = {k: v for k, v in frames.stage_ms.items() if k != "total"}
    total = frames.stage_ms.get("total")
    if len(frames) == 0 or not (stages or total is not None):
        sec.notes.append("frames.json has no timed frames.")
        return sec
    has_dim = bool(np.any(np.isfinite(frames.state_dim)))
    fig = _figure(figsize=(12, 4.8) if has_dim else (7, 4.8))
    axes = fig.subplots(1, 2 if has_dim else 1, squeeze=False)[0]
    plot_stage_times(axes[0], frames.frame, stages, total, stacked=True, xlabel="frame")
    axes[0].set_title("stacked by stage, against frame")
    if has_dim:
        plot_stage_times(axes[1], frames.state_dim, stages, total, stacked=False,
                         xlabel="size of the state vector (state_dim)")
        axes[1].set_title("against map size")
    else:
        sec.notes.append("No frame records state_dim: the plot against map size is left out.")
    sec.image = _save(fig, out_dir, "timing.png")
    counts = {s: frames.state.count(s) for s in dict.fromkeys(frames.state)}
    sec.caption = f"{len(frames)} frames: " + ", ".join(f"{n} {s}" for s, n in counts.items()) + "."
    if total is not None and np.any(np.isfinite(total)):
        sec.caption += (f" Total time per frame: median {np.nanmedian(total):.3g} ms, "
                        f"max {np.nanmax(total):.3g} ms.")
    return sec


def _ground_truth_section(out_dir: Path, traj: Trajectory | None, gt: Trajectory,
                          points: Array | None, colors: NDArray[np.uint8] | None, units: str
                          ) -> tuple[_Section, dict[str, Any] | None]:
    """Sim(3)-aligned estimate and map against ground truth; also the evaluation figures."""
    from .metrics import evaluate
    from .plots import plot_aligned_map

    sec = _Section("Trajectory and map against the ground truth, top view (Sim(3)-aligned)")
    if traj is None or len(traj) == 0:
        sec.notes.append("No estimated trajectory to compare with the ground truth.")
        return sec, None
    try:
        result = evaluate(traj, gt, units=units)
    except EifslamError as exc:
        sec.notes.append(f"Evaluation impossible: {exc}")
        return sec, None
    P = np.zeros((0, 3)) if points is None else points
    fig = _figure(figsize=(7.5, 6.5))
    plot_aligned_map(fig.add_subplot(), result, P, colors)
    sec.image = _save(fig, out_dir, "ground_truth.png")
    sec.caption = (f"ATE RMSE {result.ate_rmse:.6g} {result.units} after a Sim(3) alignment (scale "
                   f"{result.sim3.scale:.6g}); the {len(P)} map features are moved by the "
                   f"same Sim(3). {result.n_matched} of {result.n_ground_truth} ground-truth "
                   f"poses matched.")
    return sec, result.to_dict()


@functools.lru_cache(maxsize=1)
def _template() -> jinja2.Template:
    """The page's template, ``templates/report.html.j2`` of this package (package data)."""
    env = jinja2.Environment(loader=jinja2.PackageLoader("eifslam.evaluation", "templates"),
                             autoescape=jinja2.select_autoescape(["html", "j2"]),
                             trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True,
                             undefined=jinja2.StrictUndefined)
    return env.get_template("report.html.j2")


def _count(value: Any) -> str | None:
    """An integer of report.json as text, or None."""
    return str(int(value)) if isinstance(value, (int, float)) and not isinstance(value, bool) \
        and math.isfinite(value) else None


def _numbers(summary: dict[str, Any] | None, evaluation: dict[str, Any] | None, units: str) -> list[dict]:
    """The five numbers of the first screen: frames tracked, ATE, fps, loops closed,
    keyframes (``label``, ``value`` as text or None, ``unit``, ``id``)."""
    s = summary or {}
    tracked, frames = _count(s.get("frames_tracked")), _count(s.get("frames"))
    fps = s.get("fps")
    loops = s.get("loop_closures")
    return [
        dict(label="frames tracked", value=tracked, unit=f"of {frames}" if frames is not None else "",
             id="frames-tracked"),
        dict(label="ATE RMSE (Sim(3)-aligned)",
             value=None if evaluation is None else f"{evaluation['ate_rmse']:.4g}",
             unit=units if evaluation is not None else "no ground truth", id="ate-rmse"),
        dict(label="speed", value=f"{fps:.3g}" if isinstance(fps, (int, float)) and not isinstance(fps, bool)
             and math.isfinite(fps) else None, unit="frames/s", id="fps"),
        dict(label="loops closed", value=str(len(loops)) if isinstance(loops, list) else None, unit="",
             id="loops-closed"),
        dict(label="keyframes", value=_count(s.get("keyframes")), unit="", id="keyframes"),
    ]


def _html(title: str, out_dir: Path, summary: dict[str, Any] | None, summary_notes: list[str],
          evaluation: dict[str, Any] | None, first: list[_Section], rest: list[_Section]) -> str:
    """Render the page from ``templates/report.html.j2``.

    Parameters
    ----------
    title : page title.
    out_dir : the run's folder, shown in the page.
    summary : report.json's content (``None`` when it could not be read).
    summary_notes : why report.json is missing or unreadable.
    evaluation : :meth:`.metrics.EvaluationResult.to_dict` against the ground truth, or ``None``.
    first : the figures of the first screen (the trajectory, against the ground truth when
        there is one, and the map), beside the five numbers.
    rest : the other figures, in page order.

    Returns
    -------
    The HTML text; every string is escaped by the template, the tables of
    :mod:`.report_tables` arrive escaped already. The evaluation is one table (the one
    computed here, else report.json's ``evaluation``); the tables come last, folded away.
    """
    units = str((evaluation or {}).get("units") or (summary or {}).get("ate_units") or GT_UNITS)
    box = (summary or {}).get("box_ratio_estimated")
    true = (summary or {}).get("box_ratio_true")
    has_box = isinstance(box, (int, float)) and not isinstance(box, bool)
    config = (summary or {}).get("config")
    if evaluation is None and isinstance((summary or {}).get("evaluation"), dict):
        shown = summary["evaluation"]
    else:
        shown = evaluation
    left_out = ("config",) if shown is None else ("config", "evaluation")
    return _template().render(
        title=title, out_dir=str(out_dir), units=units, numbers=_numbers(summary, evaluation, units),
        box_ratio=f"{box:.3f}" if has_box else None,
        box_ratio_true=f"{true:.2f}" if has_box and isinstance(true, (int, float)) else None,
        summary=summary, summary_notes=summary_notes,
        summary_table=Markup(_table(_flatten({k: v for k, v in summary.items() if k not in left_out}),
                                    "summary", units)) if summary else None,
        config_table=Markup(_table(_flatten(config), "config")) if isinstance(config, dict) else None,
        evaluation_table=None if shown is None else Markup(_table(_flatten(shown), "evaluation", units)),
        first=first, rest=rest)


def write_report(out_dir: str | Path, ground_truth: Trajectory | None = None,
                 title: str = "eifslam run", units: str = GT_UNITS) -> Path:
    """Write ``out_dir/report.html`` with its figures in ``out_dir/figures/``.

    Parameters
    ----------
    out_dir : folder written by ``eifslam run``: ``trajectory.tum``, ``map.ply``,
        ``information.npz``, ``frames.json``, ``report.json`` (each optional).
    ground_truth : camera-to-world ground-truth poses; when given, the estimate is
        aligned to it by a Sim(3) and drawn against it with its ATE, the map moved by
        the same Sim(3).
    title : page title.
    units : name of the ground truth's length unit (``"m"`` for the data sets eifslam reads).

    Returns
    -------
    Path of ``report.html``.

    Raises
    ------
    DatasetError
        ``out_dir`` is not a folder, or the report or a figure cannot be written.
        Missing or unreadable inputs do not raise: their figures are replaced by notes.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise DatasetError(f"{out}: output folder not found")
    try:
        (out / FIGURE_DIR).mkdir(exist_ok=True)
    except OSError as exc:
        raise DatasetError(f"{out / FIGURE_DIR}: cannot create folder ({exc})") from None
    map_notes: list[str] = []
    traj = _load(out / "trajectory.tum", read_tum, map_notes)
    cloud = _load(out / "map.ply", read_ply, map_notes)
    points, colors = (None, None) if cloud is None else cloud
    info_notes: list[str] = []
    info = _load(out / "information.npz", _read_information, info_notes)
    frame_notes: list[str] = []
    frames = _load(out / "frames.json", read_frames, frame_notes)
    summary_notes: list[str] = []
    summary = _load(out / "report.json", _read_json_dict, summary_notes)

    top, *maps = _map_sections(out, traj, points, colors, map_notes)  # top view, [close-up], 3-D view
    view = maps.pop()
    evaluation = None
    if ground_truth is not None:
        gt_section, evaluation = _ground_truth_section(out, traj, ground_truth, points, colors, units)
        if gt_section.image is not None:  # first screen: against the ground truth, and the map
            first, rest = [gt_section, view], [top, *maps]
        else:
            first, rest = [top, view], [gt_section, *maps]
    else:
        first, rest = [top, view], maps
    layout = _load(out / "state_layout.json", _read_layout, info_notes) if (out / "state_layout.json").exists() else None
    rest.append(_sparsity_section(out, info, info_notes, layout))
    rest.append(_timing_section(out, frames, frame_notes))

    path = out / "report.html"
    try:
        atomic_write(path, _html(title, out, summary, summary_notes, evaluation, first, rest))
    except (OSError, OutputError) as exc:
        raise DatasetError(f"{path}: cannot write report ({exc})") from None
    return path
