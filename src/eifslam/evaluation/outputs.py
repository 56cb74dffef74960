"""Writing the results of a run: trajectory, map, per-frame figures and the summary report.

``write_outputs`` is the "save" end of load -> estimate -> save: it takes a :class:`Slam`
after a run and writes, into one folder,

* ``trajectory.tum``  every tracked frame, source timestamps, camera-to-world (TUM);
* ``map.ply``         map features with colours;
* ``frames.json``     per-frame tracking state, stage milliseconds, state size, what became of
  the frame's keypoints (detected, matched, ``Ωp``/``Ωm``, in the map, fused);
* ``information.npz`` the final information matrix (read with ``scipy.sparse.load_npz``; written a
  block of columns at a time, :func:`~eifslam.io.sparse.write_csc_npz`);
* ``state_layout.json`` ``{"kinds": "pff..."}``: the states in order, a pose (7 entries)
  or a feature (3), for the blocks of that matrix;
* ``report.json``     the summary figures, with ATE when ground truth is given
  (ground truth is read here, for scoring only, after the estimate is final; a ground
  truth that cannot be read or used leaves ``evaluation_skipped`` with the reason, and
  every estimate is still written).

Every file is written atomically (a temporary file in the folder, then
:func:`os.replace`), so a run killed while saving leaves no half-written file.

``run_to_folder`` is the whole of ``eifslam run``: check the output folder, drive the
system over a sequence (:func:`eifslam.system.runner.run_sequence`) while appending each
tracked pose to ``trajectory.partial.tum`` (flushed per frame: a run killed by SIGKILL or
a crash keeps it), then write the outputs and remove the partial file.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .. import __version__
from ..errors import EifslamError, OutputError
from ..io import Trajectory, write_ply, write_tum
from ..io.files import atomic_write, ensure_output_dir
from ..io.sparse import write_csc_npz
from ..io.trajectory import TumAppender
from ..system.slam import Slam, TrackingState, TrackResult

#: the trajectory as tracked, written frame by frame during a run (removed at its end)
PARTIAL_TRAJECTORY = "trajectory.partial.tum"


def _median(vals: list[float]) -> float | None:
    return float(np.median(vals)) if vals else None


def feature_counts(slam: Slam) -> dict[int, dict[str, int]]:
    """Per stored frame, what became of its keypoints at the end of the run (the
    ``features`` entry of a ``frames.json`` record): ``detected`` keypoints; ``matched``,
    those whose track was seen in an earlier frame; ``omega_p`` and ``omega_m``, those of
    ``Ωp`` and ``Ωm`` tracks; ``in_map``, the ``Ωm`` ones whose feature is in the state;
    ``zm_fused``, the frame's ``Zm`` among the stored measurements (a keyframe's
    ``in_map - zm_fused`` were gated or rejected; a frame between keyframes fuses none);
    ``relative``, the stored ``ZR``/``ZT`` that end at the frame."""
    fe, filt = slam.frontend, slam.filter
    zm = filt.store.all_features()
    fused = np.bincount(zm.pose[zm.pose >= 0]) if len(zm.pose) else np.zeros(0, np.int64)
    rel: dict[int, int] = {}
    for m in filt.store.relative:
        rel[int(m.j)] = rel.get(int(m.j), 0) + 1
    seen = np.zeros(0, bool)
    out: dict[int, dict[str, int]] = {}
    for k in sorted(fe.frame_ids):
        f = fe.frame(k)
        ids = f.track_ids
        if len(ids) and ids.max() >= len(seen):
            seen = np.concatenate([seen, np.zeros(int(ids.max()) + 1 - len(seen), bool)])
        in_state = filt.layout.has_features(ids[f.in_map]) if f.in_map.any() else np.zeros(0, bool)
        out[k] = dict(detected=int(len(ids)), matched=int(seen[ids].sum()) if len(ids) else 0,
                      omega_p=int((~f.in_map).sum()), omega_m=int(f.in_map.sum()),
                      in_map=int(np.sum(in_state)), zm_fused=int(fused[k]) if k < len(fused) else 0,
                      relative=rel.get(int(k), 0))
        seen[ids] = True
    return out


def frame_rows(slam: Slam) -> list[dict[str, Any]]:
    """One JSON-ready dict per processed frame (with :func:`feature_counts` as
    ``features`` for the frames the front end stores)."""
    counts = feature_counts(slam)
    rows = []
    for r in slam.results:
        row = dict(frame=r.frame_id, timestamp=r.timestamp, state=r.state.value, reason=r.reason,
                   reference=r.reference, ms={k: round(v, 3) for k, v in r.timings_ms.items()},
                   state_dim=r.state_dim, map_features=r.map_features, keyframe=r.keyframe)
        if r.frame_id in counts:
            row["features"] = counts[r.frame_id]
        rows.append(row)
    return rows


def loop_rows(slam: Slam, input_index: dict[int, int] | None = None) -> list[dict[str, Any]]:
    """``report.json``'s ``loop_closures``: one dict per loop (:class:`~eifslam.system.loops.LoopClosure`),
    ``frame`` and ``matched_frame`` mapped through ``input_index`` (the system's frame id
    to the input frame's index, which differ when unreadable images were skipped)."""
    rows = []
    for c in slam.loop_closures:
        d = c.to_dict()
        if input_index is not None:
            d["frame"] = input_index.get(c.frame, c.frame)
            d["matched_frame"] = input_index.get(c.matched_frame, c.matched_frame)
        rows.append(d)
    return rows


def refused_loop_rows(slam: Slam) -> list[dict[str, Any]]:
    """``report.json``'s ``loops_refused``: the loops that passed the geometric verification
    and were refused because the estimate or the path travelled contradicts them, one dict
    each: ``frame``,
    ``old_frame``, ``reason`` (those held for confirmation by the next keyframes are not
    listed)."""
    return [dict(frame=int(k), old_frame=int(j), reason=why) for k, j, why in slam.loops.rejected
            if why.startswith(("rotation disagrees with the estimate", "position disagrees with the path"))]


def removed_loop_rows(slam: Slam) -> list[dict[str, Any]]:
    """``report.json``'s ``loops_removed``: the loops fused and then taken back (the estimate
    with the keyframes after them contradicted them, or the caller removed them), one dict
    each: the loop's fields (:class:`~eifslam.system.loops.LoopClosure`), ``removed_at``
    (the frame at which it was taken back) and ``reason``. They are not in ``loop_closures``."""
    return [dict(c.to_dict(), removed_at=int(at), reason=why) for c, at, why in slam.loops.removed]


def summary(slam: Slam, total_s: float, ground_truth: Trajectory | None = None,
            extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The figures of ``report.json``."""
    from .metrics import DATASET_UNITS, evaluate

    res = slam.results
    n = len(res)
    tracked = sum(r.state is not TrackingState.LOST and r.position is not None for r in res)
    stages = sorted({k for r in res for k in r.timings_ms})
    rep: dict[str, Any] = dict(
        frames=n, frames_tracked=int(tracked), frames_lost=int(n - tracked),
        keyframes=int(sum(r.keyframe and r.position is not None for r in res)),
        map_features=slam.filter.layout.n_features, state_dim=slam.filter.dim,
        information_nnz=slam.filter.information_nnz(), mode=slam.config.smoothing.mode,
        detector=slam.config.frontend.detector, map_fraction=slam.config.frontend.map_fraction,
        stage_ms_median={s: _median([r.timings_ms[s] for r in res if s in r.timings_ms]) for s in stages},
        total_seconds=round(total_s, 3), fps=round(n / total_s, 3) if total_s > 0 else None,
        eifslam_version=__version__, config=slam.config.to_dict(), loop_closures=loop_rows(slam),
        loops_refused=refused_loop_rows(slam), loops_removed=removed_loop_rows(slam),
        zm_gate=dict(offered=slam.filter.zm_gate.offered, refused=slam.filter.zm_gate.refused),
    )
    if slam.smoothing is not None:
        sm = slam.smoothing
        rep["smoothing"] = dict(passes=sm.passes, step_norms=sm.step_norms, dampings=sm.dampings,
                                common_costs=sm.common_costs,
                                kept=sm.kept, reason=sm.reason, rejected_features=sm.rejected_features,
                                rejected_relative=sm.rejected_relative, noise_scale=sm.noise_scale,
                                noise_groups=[g.to_dict() for g in sm.noise_groups],
                                focal=None if sm.focal is None else sm.focal.as_dict())
    if slam.bundle_adjustment is not None:
        rep["ba"] = slam.bundle_adjustment.summary()
    if ground_truth is not None:
        t, P, Q = slam.trajectory()
        try:
            ev = evaluate(Trajectory(t, P, Q), ground_truth, units=DATASET_UNITS)
            rep["ate_rmse"] = ev.ate_rmse
            rep["ate_units"] = ev.units
            rep["ate_percent"] = ev.ate_percent
            rep["evaluation"] = ev.to_dict()
        except Exception as exc:  # evaluation must never lose the run's outputs
            rep["evaluation_error"] = rep["evaluation_skipped"] = f"evaluation failed ({exc})"
    if extra:
        rep.update(extra)
    return rep


def write_outputs(slam: Slam, out_dir: str | Path, total_s: float, ground_truth: Trajectory | None = None,
                  extra: dict[str, Any] | None = None, html: bool = True) -> dict[str, Any]:
    """Write every output file of a run into ``out_dir``; return the summary dict.

    Each file is written atomically and independently: one that cannot be written (a
    full disk, a folder of the same name) does not stop the others; ``report.json`` lists
    it under ``write_errors`` and :class:`OutputError` is raised once all were tried.
    """
    out = ensure_output_dir(out_dir)
    errors: list[str] = []

    def save(write, *args) -> None:
        try:
            write(*args)
        except EifslamError as exc:
            errors.append(str(exc))
            print(f"eifslam: warning: {exc}", file=sys.stderr)

    def save_npz(path: Path) -> None:  # uncompressed (zlib: 0.2 s of a 51-frame run), CSC as the filter keeps it
        n = slam.filter.dim
        write_csc_npz(path, (n, n), slam.filter.information_blocks())  # a block at a time: no second copy of I

    t, P, Q = slam.trajectory()  # the estimate first: it is what a user cannot recompute
    save(write_tum, out / "trajectory.tum", t, P, Q)
    _, X, cols = slam.map()
    save(write_ply, out / "map.ply", X, cols)
    save(atomic_write, out / "frames.json", json.dumps({"frames": frame_rows(slam)}, indent=1))
    save(save_npz, out / "information.npz")
    kinds = "".join("f" if k.kind == "feature" else "p" for k in slam.filter.layout.order)
    save(atomic_write, out / "state_layout.json", json.dumps({"kinds": kinds}))  # the blocks of information.npz
    rep = summary(slam, total_s, ground_truth, extra)
    if errors:
        rep["write_errors"] = list(errors)
    save(atomic_write, out / "report.json", json.dumps(rep, indent=2, default=float))
    if errors:
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        raise OutputError(errors[0] + more)
    if html:
        try:
            from .metrics import DATASET_UNITS
            from .report import write_report

            write_report(out, ground_truth=None if "evaluation_skipped" in rep else ground_truth,
                         units=DATASET_UNITS)
        except ImportError:
            pass
        except EifslamError as exc:  # the figures are a view; everything else is written
            print(f"eifslam: warning: report.html not written: {exc}", file=sys.stderr)
    return rep


def scoring_ground_truth(seq) -> tuple[Trajectory | None, str | None]:
    """The sequence's ground truth for scoring, or why there is none to use.

    Ground truth is for scoring only, so a malformed or unusable file must not fail the
    run: it gives ``(None, reason)`` and the caller warns and writes every estimate.

    Returns
    -------
    (Trajectory or None, str or None)
        ``(gt, None)``; ``(None, None)`` when the sequence has no ground truth; ``(None,
        reason)`` when it has one that cannot be used.
    """
    if not getattr(seq, "has_ground_truth", False):
        return None, None
    try:
        gt = seq.ground_truth()
    except EifslamError as exc:
        return None, f"ground truth not usable: {exc}"
    except Exception as exc:  # noqa: BLE001 - scoring must never cost the run's outputs
        return None, f"ground truth not usable: {type(exc).__name__}: {exc}"
    if gt is not None and len(gt) == 0:
        return None, "ground truth has no pose at the frame times"
    return gt, None


def summary_line(rep: dict[str, Any], out_dir: str | Path) -> str:
    """One line for the terminal: frames tracked, map size, speed, ATE, where the outputs are."""
    line = (f"eifslam: {rep['frames_tracked']}/{rep['frames']} frames tracked, {rep['map_features']} map features, "
            f"{rep['fps']} fps")
    if "ate_rmse" in rep:
        line += f", ATE {rep['ate_rmse']:.4g} {rep.get('ate_units', '')}".rstrip()
    return line + f"; outputs in {out_dir}"


def run_to_folder(seq, config, out_dir: str | Path, max_frames: int | None = None, scale: tuple | None = None,
                  html: bool = True, extra: dict[str, Any] | None = None, quiet: bool = False,
                  verbose: bool = True, on_frame: Callable[[TrackResult], None] | None = None,
                  **session: Any) -> dict[str, Any]:
    """Run SLAM over a sequence and write every output into ``out_dir``.

    Parameters
    ----------
    seq : sequence
        From :func:`eifslam.io.open_source`; its ground truth, when it has one, scores the run.
    config : SlamConfig
    out_dir : path
    max_frames, scale, quiet
        As for :func:`~eifslam.system.runner.run_sequence`.
    html : bool
        Also write ``report.html``.
    extra : dict, optional
        Copied into ``report.json``.
    verbose : bool
        Print :func:`summary_line` to stderr.
    on_frame : callable, optional
        Also called with each frame's :class:`TrackResult` as it is tracked (e.g. a live
        viewer, :class:`eifslam.viz.viewer.RerunViewer`).
    **session
        ``slam`` (a loaded session to continue) and ``save_session`` (a path), passed to
        :func:`~eifslam.system.runner.run_sequence`.

    Returns
    -------
    dict
        The figures written to ``report.json``.

    Raises
    ------
    OutputError
        ``out_dir`` cannot take the outputs (checked before the run starts).
    """
    from ..system.runner import stop_requests

    with stop_requests():  # SIGTERM while saving: the saving goes on (the CLI's handler)
        return _run_and_write(seq, config, out_dir, max_frames, scale, html, extra, quiet, verbose, on_frame,
                              session)


def _run_and_write(seq, config, out_dir: str | Path, max_frames: int | None, scale: tuple | None, html: bool,
                   extra: dict[str, Any] | None, quiet: bool, verbose: bool,
                   also: Callable[[TrackResult], None] | None, session: dict[str, Any]) -> dict[str, Any]:
    """:func:`run_to_folder` inside its stop-request block (same parameters)."""
    from ..system.runner import run_sequence

    out = ensure_output_dir(out_dir)  # before any work
    partial = TumAppender(out / PARTIAL_TRAJECTORY)

    def on_frame(res) -> None:
        if res.position is not None and res.quat_wxyz is not None:
            partial.append(res.timestamp, res.position, res.quat_wxyz)
        if also is not None:
            also(res)

    try:
        run = run_sequence(seq, config, max_frames=max_frames, scale=scale, quiet=quiet, on_frame=on_frame,
                           **session)
    finally:
        partial.close()
    gt, skipped = scoring_ground_truth(seq)
    extra = dict(extra or {})
    extra["source"] = str(getattr(seq, "root", ""))
    by_time = {f.timestamp: k for k, f in enumerate(getattr(seq, "frames", []))}
    extra["loop_closures"] = loop_rows(run.slam, {r.frame_id: by_time.get(r.timestamp, r.frame_id)
                                                  for r in run.slam.results})
    if run.stopped:
        extra["stopped"] = run.stopped
    if run.scale_error:
        extra["scale_skipped"] = run.scale_error
    if skipped:
        print(f"eifslam: warning: {skipped}; evaluation skipped", file=sys.stderr)
        extra["evaluation_skipped"] = extra["evaluation_error"] = skipped
    rep = write_outputs(run.slam, out, run.seconds, gt, extra, html=html)
    partial.path.unlink(missing_ok=True)  # trajectory.tum, complete, replaces it
    if verbose:
        print(summary_line(rep, out_dir), file=sys.stderr)
    return rep
