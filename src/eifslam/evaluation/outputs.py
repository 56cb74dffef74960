"""Writing the results of a run: trajectory, map, per-frame figures and the summary report.

``write_outputs`` is the "save" end of load -> estimate -> save: it takes a :class:`Slam`
after a run and writes, into one folder,

* ``trajectory.tum``  every tracked frame, source timestamps, camera-to-world (TUM);
* ``map.ply``         map features with colours;
* ``frames.json``     per-frame tracking state, stage milliseconds, state size;
* ``information.npz`` the final information matrix (``scipy.sparse.save_npz``);
* ``state_layout.json`` ``{"kinds": "pff..."}``: the states in order, a pose (7 entries)
  or a feature (3), for the blocks of that matrix;
* ``report.json``     the summary figures, with ATE when ground truth is given
  (ground truth is read here, for scoring only, after the estimate is final).

``run_to_folder`` is the whole of ``eifslam run``: drive the system over a sequence
(:func:`eifslam.system.runner.run_sequence`), then write the outputs.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from .. import __version__
from ..io import Trajectory, write_ply, write_tum
from ..system.slam import Slam, TrackingState


def _median(vals: list[float]) -> float | None:
    return float(np.median(vals)) if vals else None


def frame_rows(slam: Slam) -> list[dict[str, Any]]:
    """One JSON-ready dict per processed frame."""
    rows = []
    for r in slam.results:
        rows.append(dict(frame=r.frame_id, timestamp=r.timestamp, state=r.state.value, reason=r.reason,
                         reference=r.reference, ms={k: round(v, 3) for k, v in r.timings_ms.items()},
                         state_dim=r.state_dim, map_features=r.map_features, keyframe=r.keyframe))
    return rows


def summary(slam: Slam, total_s: float, ground_truth: Trajectory | None = None,
            extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The figures of ``report.json``."""
    from .metrics import DATASET_UNITS, evaluate

    res = slam.results
    n = len(res)
    tracked = sum(r.state is not TrackingState.LOST and r.position is not None for r in res)
    I = slam.filter.information_matrix()
    stages = sorted({k for r in res for k in r.timings_ms})
    rep: dict[str, Any] = dict(
        frames=n, frames_tracked=int(tracked), frames_lost=int(n - tracked),
        keyframes=int(sum(r.keyframe and r.position is not None for r in res)),
        map_features=slam.filter.layout.n_features, state_dim=slam.filter.dim,
        information_nnz=int(I.nnz), mode=slam.config.system.mode,
        detector=slam.config.frontend.detector, map_fraction=slam.config.frontend.map_fraction,
        stage_ms_median={s: _median([r.timings_ms[s] for r in res if s in r.timings_ms]) for s in stages},
        total_seconds=round(total_s, 3), fps=round(n / total_s, 3) if total_s > 0 else None,
        eifslam_version=__version__, config=slam.config.to_dict(),
    )
    if slam.smoothing is not None:
        rep["smoothing"] = dict(passes=slam.smoothing.passes, step_norms=slam.smoothing.step_norms)
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
            rep["evaluation_error"] = str(exc)
    if extra:
        rep.update(extra)
    return rep


def write_outputs(slam: Slam, out_dir: str | Path, total_s: float, ground_truth: Trajectory | None = None,
                  extra: dict[str, Any] | None = None, html: bool = True) -> dict[str, Any]:
    """Write every output file of a run into ``out_dir``; return the summary dict."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t, P, Q = slam.trajectory()
    write_tum(out / "trajectory.tum", t, P, Q)
    _, X, cols = slam.map()
    write_ply(out / "map.ply", X, cols)
    (out / "frames.json").write_text(json.dumps({"frames": frame_rows(slam)}, indent=1))
    sp.save_npz(out / "information.npz", slam.filter.information_matrix().tocsr())
    kinds = "".join("f" if k.kind == "feature" else "p" for k in slam.filter.layout.order)
    (out / "state_layout.json").write_text(json.dumps({"kinds": kinds}))  # the blocks of information.npz
    rep = summary(slam, total_s, ground_truth, extra)
    (out / "report.json").write_text(json.dumps(rep, indent=2, default=float))
    if html:
        try:
            from .metrics import DATASET_UNITS
            from .report import write_report

            write_report(out, ground_truth=ground_truth, units=DATASET_UNITS)
        except ImportError:
            pass
    return rep


def summary_line(rep: dict[str, Any], out_dir: str | Path) -> str:
    """One line for the terminal: frames tracked, map size, speed, ATE, where the outputs are."""
    line = (f"eifslam: {rep['frames_tracked']}/{rep['frames']} frames tracked, {rep['map_features']} map features, "
            f"{rep['fps']} fps")
    if "ate_rmse" in rep:
        line += f", ATE {rep['ate_rmse']:.4g} {rep.get('ate_units', '')}".rstrip()
    return line + f"; outputs in {out_dir}"


def run_to_folder(seq, config, out_dir: str | Path, max_frames: int | None = None, scale: tuple | None = None,
                  html: bool = True, extra: dict[str, Any] | None = None, quiet: bool = False,
                  verbose: bool = True, **session: Any) -> dict[str, Any]:
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
    **session
        ``slam`` (a loaded session to continue) and ``save_session`` (a path), passed to
        :func:`~eifslam.system.runner.run_sequence`.

    Returns
    -------
    dict
        The figures written to ``report.json``.
    """
    from ..system.runner import run_sequence

    run = run_sequence(seq, config, max_frames=max_frames, scale=scale, quiet=quiet, **session)
    gt = seq.ground_truth() if getattr(seq, "has_ground_truth", False) else None
    extra = dict(extra or {})
    extra["source"] = str(getattr(seq, "root", ""))
    if run.stopped:
        extra["stopped"] = run.stopped
    rep = write_outputs(run.slam, out_dir, run.seconds, gt, extra, html=html)
    if verbose:
        print(summary_line(rep, out_dir), file=sys.stderr)
    return rep
