"""Drive a :class:`~eifslam.slam.Slam` over a sequence with a progress bar; lose nothing.

Ctrl-C or a failing frame stops the loop, and what was estimated so far is written.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from .config import SlamConfig
from ..errors import EifslamError, ImageError
from ..evaluation.outputs import write_outputs
from .slam import Slam


def run_sequence(seq, config: SlamConfig, out_dir: Path, max_frames: int | None = None,
                 scale: tuple | None = None, html: bool = True, extra: dict[str, Any] | None = None,
                 quiet: bool = False) -> dict[str, Any]:
    """Run SLAM over ``seq`` (an :mod:`eifslam.io` sequence) and write the outputs."""
    slam = Slam(seq.camera, config)
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    t0 = time.perf_counter()
    stopped = None
    bar = tqdm(range(n), desc="eifslam", unit="frame", disable=quiet, file=sys.stderr)
    try:
        for k in bar:
            try:
                image = seq.load(k)
            except ImageError as exc:  # a missing/corrupt image: report it, keep going
                tqdm.write(f"eifslam: skipping frame {k}: {exc}", file=sys.stderr)
                continue
            res = slam.track(image, seq.frames[k].timestamp)
            bar.set_postfix(state=res.state.value, map=res.map_features)
    except KeyboardInterrupt:
        stopped = "interrupted"
    except EifslamError as exc:
        stopped = f"stopped at a failing frame: {exc}"
    finally:
        bar.close()
    if stopped:
        print(f"eifslam: {stopped}; writing what was estimated so far", file=sys.stderr)
    if stopped is None or stopped.startswith("stopped"):
        try:  # one more chance for every frame without a pose, against the final map
            slam.finish()
        except EifslamError as exc:
            print(f"eifslam: retrying lost frames failed ({exc})", file=sys.stderr)
    if config.system.mode == "smooth" and slam.filter.layout.n_poses >= 2:
        try:
            slam.smooth()
        except EifslamError as exc:  # keep the filter's estimate rather than lose the run
            stopped = (stopped + "; " if stopped else "") + f"smoothing failed: {exc}"
            print(f"eifslam: smoothing failed ({exc}); writing the filter's estimate", file=sys.stderr)
    if config.system.mode == "ba" and slam.filter.layout.n_poses >= 2:
        from ..baselines.bundle_adjustment import bundle_adjust_slam

        try:
            extra = dict(extra or {}, ba=bundle_adjust_slam(slam).summary())
        except EifslamError as exc:  # keep the filter's estimate rather than lose the run
            stopped = (stopped + "; " if stopped else "") + f"bundle adjustment failed: {exc}"
            print(f"eifslam: bundle adjustment failed ({exc}); writing the filter's estimate", file=sys.stderr)
    if scale is not None and slam.filter.layout.n_poses >= 2:
        a, b, length = scale
        slam.set_scale(a, b, length)
    total = time.perf_counter() - t0
    gt = seq.ground_truth() if getattr(seq, "has_ground_truth", False) else None
    extra = dict(extra or {})
    extra["source"] = str(getattr(seq, "root", ""))
    if stopped:
        extra["stopped"] = stopped
    rep = write_outputs(slam, out_dir, total, gt, extra, html=html)
    line = f"eifslam: {rep['frames_tracked']}/{rep['frames']} frames tracked, {rep['map_features']} map features, {rep['fps']} fps"
    if "ate_rmse" in rep:
        line += f", ATE {rep['ate_rmse']:.4g}"
    print(line + f"; outputs in {out_dir}", file=sys.stderr)
    return rep
