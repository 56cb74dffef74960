"""NEES of frames between keyframes against keyframes, with and without the map's uncertainty.

``benchmarks/consistency.py`` gives every frame a timestamp one second after the last, so
every frame is a keyframe. Here the corridor is walked slowly (``--step`` metres per frame,
``--dt`` seconds per frame), so that most frames are localised on the map between
keyframes; each frame's NEES (6 DOF, the pose and covariance reported by
:meth:`Slam.track` at that frame) is scored for ``system.map_pose_uncertainty`` off and on.
The first pair of frames with enough parallax sets the scale gauge: its true distance is
given (``--scale-pair``); runs that initialise on another pair are skipped.

    python benchmarks/consistency_keyframes.py --runs 4 --frames 40
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from eifslam.geometry.rotations import quat_conjugate, quat_log, quat_multiply
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system.slam import Slam


def run(seed: int, frames: int, step: float, dt: float, pair: int, map_uncertainty: bool,
        first: int = 5) -> dict | None:
    """Per-frame NEES of one run, split into keyframes and frames between; None when the
    map was initialised on another pair than ``(0, pair)``. Frames before ``first`` are
    not scored."""
    sc = corridor_scene(frames, np.random.default_rng(seed), step=step)
    fe = SyntheticFrontEnd(sc, seed, map_fraction=1.0)
    cfg = fe.slam_config(system={"map_pose_uncertainty": map_uncertainty, "scale_distance": fe.true_distance(0, pair)})
    slam = Slam(sc.camera, cfg, frontend=fe)
    out: dict[str, list[float]] = {"keyframes": [], "between": []}
    for k in range(frames):
        res = slam.track(k, dt * k)
        if res.position is None or res.covariance is None or k < first:
            continue
        e = np.concatenate([sc.positions[k] - res.position,
                            quat_log(quat_multiply(quat_conjugate(res.quat_wxyz), sc.quats[k]))])
        out["keyframes" if res.keyframe else "between"].append(float(e @ np.linalg.solve(res.covariance, e)))
    scale = slam.filter.priors.scale
    return out if scale is not None and tuple(scale[:2]) == (0, pair) else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="write DIR/consistency_keyframes.json")
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--step", type=float, default=0.15, help="metres per frame")
    ap.add_argument("--dt", type=float, default=0.1, help="seconds per frame")
    ap.add_argument("--scale-pair", type=int, default=2, help="the map is initialised on frames 0 and this")
    ap.add_argument("--seed", type=int, default=100)
    args = ap.parse_args(argv)
    res: dict = {}
    for mu in (False, True):
        vals: dict[str, list[float]] = {"keyframes": [], "between": []}
        used = 0
        for r in range(args.runs):
            o = run(args.seed + r, args.frames, args.step, args.dt, args.scale_pair, mu)
            if o is None:
                continue
            used += 1
            for key in vals:
                vals[key] += o[key]
        res[f"map_pose_uncertainty={mu}"] = {
            key: dict(n=len(v), mean_nees=float(np.mean(v)) if v else None,
                      median_nees=float(np.median(v)) if v else None) for key, v in vals.items()} | {"runs": used}
        print(f"map_pose_uncertainty={mu}: " + json.dumps(res[f"map_pose_uncertainty={mu}"]), flush=True)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "consistency_keyframes.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
