"""Writing the results of a run: trajectory, map, per-frame figures and the summary report.

``write_outputs`` is the "save" end of load -> estimate -> save: it takes a :class:`Slam`
after a run and writes, into one folder,

* ``trajectory.tum``  every tracked frame, source timestamps, camera-to-world (TUM);
* ``map.ply``         map features with colours;
* ``frames.json``     per-frame tracking state, stage milliseconds, state size;
* ``information.npz`` the final information matrix (``scipy.sparse.save_npz``);
* ``report.json``     the summary figures, with ATE when ground truth is given
  (ground truth is read here, for scoring only, after the estimate is final).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

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
                         state_dim=r.state_dim, map_features=r.map_features))
    return rows


def summary(slam: Slam, total_s: float, ground_truth: Trajectory | None = None,
            extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The figures of ``report.json``."""
    from .metrics import evaluate

    res = slam.results
    n = len(res)
    tracked = sum(r.state is not TrackingState.LOST and r.position is not None for r in res)
    I = slam.filter.information_matrix()
    stages = sorted({k for r in res for k in r.timings_ms})
    rep: dict[str, Any] = dict(
        frames=n, frames_tracked=int(tracked), frames_lost=int(n - tracked),
        map_features=slam.filter.layout.n_features, state_dim=slam.filter.dim,
        information_nnz=int(I.nnz), mode=slam.config.system.mode,
        detector=slam.config.frontend.detector, map_fraction=slam.config.frontend.map_fraction,
        stage_ms_median={s: _median([r.timings_ms[s] for r in res if s in r.timings_ms]) for s in stages},
        total_seconds=round(total_s, 3), fps=round(n / total_s, 3) if total_s > 0 else None,
    )
    if slam.smoothing is not None:
        rep["smoothing"] = dict(passes=slam.smoothing.passes, step_norms=slam.smoothing.step_norms)
    if ground_truth is not None:
        t, P, Q = slam.trajectory()
        try:
            ev = evaluate(Trajectory(t, P, Q), ground_truth)
            rep["ate_rmse"] = ev.ate_rmse
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
    rep = summary(slam, total_s, ground_truth, extra)
    (out / "report.json").write_text(json.dumps(rep, indent=2, default=float))
    if html:
        try:
            from .report import write_report

            write_report(out, ground_truth=ground_truth)
        except ImportError:
            pass
    return rep
