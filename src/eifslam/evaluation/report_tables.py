"""The tables of ``report.html``: report.json's keys as a reader names them, with units,
values to 4 significant digits (the exact value in ``data-value``) and the key beside."""

from __future__ import annotations

import html
import json
from typing import Any

from .metrics import GT_UNITS

__all__ = ["flatten", "label", "table"]


def flatten(d: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """Nested dictionaries as ``("a.b", value)`` rows."""
    rows: list[tuple[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            rows.extend(flatten(v, key + ".") if v else [(key, "{}")])
        else:
            rows.append((key, v))
    return rows


#: Labels of report.json's keys in the page's tables ("{u}": the ground truth's unit).
_LABELS = {
    "frames": "Frames", "frames_tracked": "Frames tracked", "frames_lost": "Frames lost",
    "map_features": "Map features", "state_dim": "State size (entries)",
    "information_nnz": "Non-zeros of the information matrix", "mode": "Mode", "detector": "Detector",
    "map_fraction": "Fraction of tracks in the map (Ωm)", "total_seconds": "Run time (s)",
    "fps": "Frames per second", "ate_rmse": "ATE RMSE ({u})", "ate_percent": "ATE (% of path length)",
    "ate_units": "Unit of lengths", "units": "Unit of lengths", "ate_mean": "ATE mean ({u})",
    "ate_median": "ATE median ({u})", "ate_max": "ATE max ({u})",
    "gt_path_length": "Ground-truth path length ({u})", "tracked_fraction": "Tracked fraction",
    "n_ground_truth": "Ground-truth poses", "n_estimate": "Estimated poses", "n_matched": "Poses matched",
    "box_ratio_true": "Box width:length, true", "box_ratio_estimated": "Box width:length, estimated",
    "box_ratio_points": "Map features on the box's top face", "box_ratio_error_percent": "Box ratio error (%)",
    "eifslam_version": "eifslam version", "command": "Command", "source": "Source", "stopped": "Stopped",
    "zm_gate.offered": "Zm offered to the gate", "zm_gate.refused": "Zm the gate refused",
    "sim3.scale": "Sim(3) scale", "sim3.rotation": "Sim(3) rotation", "sim3.translation": "Sim(3) translation ({u})",
}
_STATS = {"rmse": "RMSE", "mean": "mean", "median": "median", "max": "max"}


def label(key: str, units: str) -> str:
    """A reader's name for a flattened report.json key."""
    if key in _LABELS:
        return _LABELS[key].format(u=units)
    head, _, tail = key.partition(".")
    if head == "stage_ms_median":
        return f"Median time per frame, {tail} (ms)"
    if head in ("rpe_rot_deg", "rpe_dir_deg") and tail in _STATS:
        what = "rotation" if head == "rpe_rot_deg" else "translation direction"
        return f"RPE {what} {_STATS[tail]} (°)"
    return key.replace("_", " ").replace(".", ": ")


def _format(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        if len(value) <= 6 and all(isinstance(v, (int, float, str)) for v in value):
            return "[" + ", ".join(_format(v) for v in value) + "]"
        return f"[list of {len(value)}]"
    return str(value)


def table(rows: list[tuple[str, Any]], table_id: str, units: str = GT_UNITS) -> str:
    """Rows of (key, value): a readable label, the value to 4 significant digits (the full
    value in ``data-value``) and the report.json key."""
    body = "\n".join(
        f'<tr id="{table_id}-{html.escape(k, quote=True)}"><th>{html.escape(label(k, units))}</th>'
        f'<td data-value="{html.escape(json.dumps(v, default=str), quote=True)}">{html.escape(_format(v))}</td>'
        f'<td class="key">{html.escape(k)}</td></tr>'
        for k, v in rows
    )
    return f'<table id="{table_id}">\n{body}\n</table>'


