"""Front-end speed and relative-pose accuracy on a data-set folder.

Usage::

    python -m benchmarks.frontend --data ../shared/datasets/kitti-seq1 --out out/frontend

writes ``OUT/frontend.json``::

    {"detectors": {"sift": {"ms_median", "ms_p95", "stages_ms_median": {"detect", "match",
                            "relative_pose", "covariance"}, "pairs", "usable_pairs",
                            "zr_error_deg_median", "zt_error_deg_median", ...}, "orb": {...}},
     "machine": {...}, "command": "..."}

and prints one table row per detector.

``ms_*`` is the whole front end per frame: ``add_frame`` plus ``relative_pose`` with the
frame ``k - step`` (``--step``, default 1). The errors (when the folder has ``groundtruth.tum``) are over the
pairs (k - step, k) whose relative pose is usable: the rotation error of ``ZR`` and the angle between
``ZT``'s direction and the true one, the truth being ``R_ij = R_wi.T R_wj`` and
``t_ij ∝ R_wi.T (p_j - p_i)`` from the camera-to-world ground truth (scoring only).
A detector missing from the installed OpenCV gets ``{"error": "..."}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

from eifslam.geometry.camera import PinholeCamera
from eifslam.errors import ConfigError
from eifslam.frontend import FrontEnd, FrontEndConfig
from eifslam.geometry.rotations import quat_to_rotmat, quat_xyzw_to_wxyz

from ._common import command_line, fmt, machine_info, markdown_table, write_json


def load_folder(d: Path, limit: int | None):
    """Camera, sorted image paths and (optional) ground truth ``(N, 8)`` of a folder."""
    c = yaml.safe_load((d / "camera.yaml").read_text())
    cam = PinholeCamera(float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"]),
                        int(c["width"]), int(c["height"]), tuple(c.get("distortion") or ()))
    files = sorted(p for p in (d / "images").iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    gt_path = d / "groundtruth.tum"
    gt = np.loadtxt(gt_path, comments="#") if gt_path.exists() else None
    if limit:
        files = files[:limit]
    return cam, files, gt


def true_relative(gt: np.ndarray, i: int, j: int):
    Ri = quat_to_rotmat(quat_xyzw_to_wxyz(gt[i, 4:]))
    Rj = quat_to_rotmat(quat_xyzw_to_wxyz(gt[j, 4:]))
    return Ri.T @ Rj, Ri.T @ (gt[j, 1:4] - gt[i, 1:4])


def run(detector: str, cam, images, gt, overrides: dict, step: int = 1) -> dict:
    try:
        fe = FrontEnd(cam, FrontEndConfig.from_dict({"detector": detector, **overrides}))
    except ConfigError as exc:
        return {"error": str(exc)}
    total, stages = [], {k: [] for k in ("detect", "match", "relative_pose", "covariance")}
    rot_err, dir_err, reasons, inliers, parallax = [], [], {}, [], []
    for k, img in enumerate(images):
        t0 = time.perf_counter()
        res = fe.add_frame(img, k)
        rp = fe.relative_pose(k - step, k) if k >= step else None
        total.append((time.perf_counter() - t0) * 1e3)
        for key in ("detect", "match"):
            stages[key].append(res.timings_ms[key])
        if rp is None:
            continue
        for key in ("relative_pose", "covariance"):
            stages[key].append(rp.timings_ms.get(key, 0.0))
        reasons[rp.reason or "ok"] = reasons.get(rp.reason or "ok", 0) + 1
        if not rp.ok:
            continue
        inliers.append(rp.n_inliers)
        parallax.append(rp.parallax_deg)
        if gt is not None:
            R, t = true_relative(gt, k - step, k)
            m = rp.measurement
            dR = quat_to_rotmat(m.q_ij).T @ R
            rot_err.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
            if np.linalg.norm(t) > 0:
                dir_err.append(np.degrees(np.arccos(np.clip(m.t_ij @ t / np.linalg.norm(t), -1, 1))))
    out = {
        "ms_median": float(np.median(total[1:])),
        "ms_p95": float(np.percentile(total[1:], 95)),
        "stages_ms_median": {k: float(np.median(v)) for k, v in stages.items()},
        "pairs": len(images) - step,
        "step": step,
        "usable_pairs": len(inliers),
        "reasons": reasons,
        "inliers_median": float(np.median(inliers)) if inliers else 0.0,
        "parallax_deg_median": float(np.median(parallax)) if parallax else 0.0,
    }
    if gt is not None and rot_err:
        out["zr_error_deg_median"] = float(np.median(rot_err))
        out["zt_error_deg_median"] = float(np.median(dir_err))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="data-set folder (images/, camera.yaml)")
    ap.add_argument("--out", required=True, type=Path, help="output folder for frontend.json")
    ap.add_argument("--detectors", default="sift,orb", help="comma-separated detectors")
    ap.add_argument("--limit", type=int, default=None, help="use the first N images only")
    ap.add_argument("--step", type=int, default=1,
                    help="relative pose of frame k with frame k - step (default: consecutive)")
    ap.add_argument("--threads", type=int, default=2, help="cv2.setNumThreads")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="FrontEndConfig overrides, e.g. max_features=1000")
    args = ap.parse_args(argv)
    cv2.setNumThreads(args.threads)
    overrides = {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        overrides[k] = yaml.safe_load(v)
    cam, files, gt = load_folder(args.data, args.limit)
    images = [cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files]  # read outside the timing
    results = {}
    for det in args.detectors.split(","):
        results[det] = run(det, cam, images, gt, overrides, args.step)
        print(det, json.dumps(results[det]), file=sys.stderr)
    write_json(args.out / "frontend.json",
               dict(detectors=results, machine=machine_info(),
                    command=command_line(__spec__.name, sys.argv[1:] if argv is None else argv)))
    print(format_table(results), end="")
    return 0


HEADERS = ("detector", "ms median", "ms p95", "detect", "match", "relative_pose", "covariance", "usable pairs",
           "ZR error deg", "ZT error deg")


def format_table(results: dict) -> str:
    """The per-detector figures of :func:`run` as a Markdown table (errors in the first column)."""
    rows = []
    for det, r in results.items():
        if "error" in r:
            rows.append([f"{det}: {r['error']}"] + ["–"] * (len(HEADERS) - 1))
            continue
        st = r["stages_ms_median"]
        rows.append([det, fmt(r["ms_median"]), fmt(r["ms_p95"]), *(fmt(st.get(k)) for k in HEADERS[3:7]),
                     f"{r['usable_pairs']}/{r['pairs']}", fmt(r.get("zr_error_deg_median")),
                     fmt(r.get("zt_error_deg_median"))])
    return markdown_table(HEADERS, rows)


if __name__ == "__main__":
    raise SystemExit(main())
