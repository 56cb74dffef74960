"""Where the filter's overconfidence comes from: its estimate or its covariance.

The same Monte Carlo runs as ``benchmarks/consistency.py`` (synthetic corridor through the
system, :class:`eifslam.sim.frontend.SyntheticFrontEnd`, every point in the map), scored
at the last frame only, with cross terms that separate the two causes:

* ``f`` / ``s``: NEES of the latest pose, filter and smoothed (estimate and covariance of
  the same mode);
* ``f_Ps`` / ``s_Pf``: the filter's error against the smoothed covariance, and the other
  way round; ``f_Pr``: the filter's error against the covariance of the information
  relinearised at the filter's own estimate (:meth:`InformationFilter.relinearise`, the
  estimate unchanged);
* ``ef2`` / ``es2``: squared position error (m^2), ``trPf`` / ``trPs`` / ``trPr``: trace of
  the position covariance (m^2);
* ``nrel`` / ``nrej``: ``ZR``/``ZT`` fused / refused by the relative gate; ``nzm``: ``Zm``
  fused.

If ``f_Ps`` stays near ``f`` while ``ef2`` is several times ``es2``, the filter's *estimate*
is off (linearisation), not its covariance. Writes ``DIR/diagnosis.json`` (per run and
the mean and median of each figure)::

    python benchmarks/consistency_diagnosis.py --out DIR --runs 8 --frames 30
    python benchmarks/consistency_diagnosis.py --out DIR --set experimental.zm_gate_chi2=none
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

from consistency import parse_sets
from eifslam.estimation.state import pose_tangent_covariance
from eifslam.geometry.rotations import quat_conjugate, quat_log, quat_multiply
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system.slam import Slam


def pose_error(filt, scene, k: int) -> np.ndarray:
    """``[p_true - p, Log(q^* q_true)]`` (6,) of pose *k*."""
    p, q = filt.pose(k)
    return np.concatenate([scene.positions[k] - p, quat_log(quat_multiply(quat_conjugate(q), scene.quats[k]))])


def nees(e: np.ndarray, P: np.ndarray) -> float:
    """``e^T P^-1 e``."""
    return float(e @ np.linalg.solve(P, e))


def diagnose(seed: int, frames: int, sections: dict) -> dict[str, float]:
    """One run: the figures of the module docstring at the last frame."""
    sc = corridor_scene(frames, np.random.default_rng(seed))
    fe = SyntheticFrontEnd(sc, seed, map_fraction=1.0)
    slam = Slam(sc.camera, fe.slam_config(**sections), frontend=fe)
    for k in range(frames):
        slam.track(k)
    k = frames - 1
    f = slam.filter
    f.complete_estimate()
    ef, Pf = pose_error(f, sc, k), f.pose_covariance(k)
    g = copy.deepcopy(f)
    g.relinearise()
    cols = g.layout.pose_columns([k])[0]
    Pr = pose_tangent_covariance(g.covariance(cols), g.x[cols[3:]])
    row = dict(nrel=float(len(f.store.relative)), nrej=float(len(slam.rejected_relative)),
               nzm=float(len(f.store.all_features())))
    slam.smooth()
    es, Ps = pose_error(slam.filter, sc, k), slam.filter.pose_covariance(k)
    row.update(f=nees(ef, Pf), s=nees(es, Ps), f_Ps=nees(ef, Ps), s_Pf=nees(es, Pf), f_Pr=nees(ef, Pr),
               ef2=float(ef[:3] @ ef[:3]), es2=float(es[:3] @ es[:3]), trPf=float(np.trace(Pf[:3, :3])),
               trPs=float(np.trace(Ps[:3, :3])), trPr=float(np.trace(Pr[:3, :3])))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--seed", type=int, default=100, help="run r uses seed SEED + r")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = ap.parse_args(argv)
    sections = parse_sets(args.set)
    rows = []
    for r in range(args.runs):
        rows.append(diagnose(args.seed + r, args.frames, sections))
        print(f"[diagnosis] run {r + 1}/{args.runs}: " + " ".join(f"{k} {v:.3g}" for k, v in rows[-1].items()),
              file=sys.stderr, flush=True)
    keys = list(rows[0])
    res = dict(runs=rows, mean={k: float(np.mean([x[k] for x in rows])) for k in keys},
               median={k: float(np.median([x[k] for x in rows])) for k in keys},
               settings=dict(sections=sections, runs=args.runs, frames=args.frames, seed=args.seed))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "diagnosis.json").write_text(json.dumps(res, indent=1))
    print("mean   " + " ".join(f"{k} {v:.3g}" for k, v in res["mean"].items()))
    print("median " + " ".join(f"{k} {v:.3g}" for k, v in res["median"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
