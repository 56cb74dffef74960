"""Scoring the built-in scene (``eifslam demo``): the width:length ratio of the 0.80:1 box.

Ground truth is used for scoring only, after the estimate is final.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["box_ratio_figures"]


def box_ratio_figures(out_dir: str | Path, scene) -> dict[str, Any]:
    """Box ratio from the mapped features on the 0.80:1 box's top face.

    Parameters
    ----------
    out_dir : path
        A run's output folder (``trajectory.tum``, ``map.ply``).
    scene : BuiltinScene
        The rendered scene (:func:`eifslam.sim.scene.make_scene`).

    Returns
    -------
    dict
        ``box_ratio_true``, ``box_ratio_estimated`` (None when no ratio could be
        measured), ``box_ratio_points`` and ``box_ratio_error_percent``, after the same
        Sim(3) alignment as the ATE.
    """
    from ..io import read_ply, read_tum
    from ..io.trajectory import Trajectory
    from ..sim.scene import estimate_box_ratio
    from .metrics import evaluate

    out_dir = Path(out_dir)
    est = read_tum(out_dir / "trajectory.tum")
    gt = Trajectory(scene.timestamps, scene.positions, scene.quats_wxyz)
    ev = evaluate(est, gt)
    pts, _ = read_ply(out_dir / "map.ply")
    aligned = ev.sim3.apply(pts)
    ratio, n = estimate_box_ratio(aligned, scene)
    return dict(box_ratio_true=scene.box_ratio_true, box_ratio_estimated=None if ratio != ratio else ratio,
                box_ratio_points=n, box_ratio_error_percent=None if ratio != ratio else
                100.0 * abs(ratio - scene.box_ratio_true) / scene.box_ratio_true)


def add_box_ratio(rep: dict[str, Any], out_dir: str | Path, scene) -> dict[str, Any]:
    """Add the box-ratio figures of a built-in-scene run to its report and rewrite
    ``report.json``; a scoring failure becomes ``box_ratio_error`` (the run is kept).

    Parameters
    ----------
    rep : dict
        The run's report (from :func:`eifslam.evaluation.outputs.write_outputs`); updated.
    out_dir : path
        The run's output folder.
    scene : BuiltinScene

    Returns
    -------
    dict
        ``rep``.
    """
    import json

    from ..io.files import atomic_write

    try:
        rep.update(box_ratio_figures(out_dir, scene))
    except Exception as exc:  # scoring must not lose the run
        rep["box_ratio_error"] = f"{type(exc).__name__}: {exc}"
    atomic_write(Path(out_dir) / "report.json", json.dumps(rep, indent=2, default=float))
    return rep
