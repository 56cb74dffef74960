"""Consistency of the system's uncertainty: NEES of the latest pose over Monte Carlo runs.

Each run is a synthetic corridor (:func:`eifslam.sim.synthetic.corridor_scene`, its own
scene and noise seed) measured by :class:`eifslam.sim.frontend.SyntheticFrontEnd` and run
through the system (:class:`eifslam.system.slam.Slam`) at its default settings (only
``frontend.sigma_px`` and ``tracking.scale_distance`` come from the simulation, so that the
estimate is in the truth's gauge: first pose the identity, distance between the first two
poses the true one; when the map starts from another pair with the first, the truth is
scaled to the estimate's scale). After every ``--every``-th frame the normalised estimation error
squared (NEES) of the latest keyframe (the filter's latest pose), 6 DOF ``[p, dtheta]``, is taken from the filter's
estimate and covariance; at the same frames a copy of the system is smoothed
(:meth:`Slam.smooth`) and scored the same way. The latest frame between keyframes since
the previous checkpoint (its map pose and the covariance :meth:`Slam.track` reports) is
scored too; without ``--fps`` (frame indices as timestamps) every frame is due as a
keyframe, with a frame rate and a short ``--step`` some frames fall between them.

The mean NEES over ``R`` runs is consistent when it lies inside the 95% interval of
``chi2(6 R) / R``. ``--set SECTION.KEY=VALUE`` changes a setting, to see what it does
to the consistency (e.g. ``--set experimental.zm_gate_chi2=none``).

Writes ``DIR/consistency.json``::

    {"filter": {"mean_nees", "lo", "hi", "runs", "frames"}, "smooth": {...}, "between": {...},
     "per_frame": {"frame": [...], "filter": [...], "smooth": [...], "between": [...],
                   "cost_ratio": [...], "cost_ratio_max": [...]},
     "settings": {...}, "machine": {...}, "command": "..."}

(``filter``/``smooth``/``between`` at the last frame; ``per_frame`` the mean NEES at each
checkpoint, and the mean and largest over the runs of the filter's cost over the smoothed
cost: :attr:`SmoothingReport.common_costs <eifslam.estimation.smoothing.SmoothingReport>`
at the filter's estimate over its lowest value) and ``DIR/consistency.png`` (mean NEES
against frame, with the interval).

    python -m benchmarks.consistency --out out/consistency            # 50 runs x 50 frames
    python -m benchmarks.consistency --out out/c200 --frames 200 --every 50   # 50 x 200 (and 50 x 50)
    python -m benchmarks.consistency --out out/cb --step 0.1 --fps 10 # frames between keyframes
    python -m benchmarks.consistency --out out/consistency --jobs 3   # the same, 3 processes
    python -m benchmarks.consistency --out out/consistency --runs 5 --frames 20 # quick look
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import nullcontext
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from eifslam.geometry.rotations import quat_conjugate, quat_log, quat_multiply
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system.slam import Slam

from ._common import command_line, machine_info

DOF = 6


def nees(scene, k: int, p: np.ndarray, q: np.ndarray, cov: np.ndarray, scale: float = 1.0) -> float:
    """NEES of an estimate ``(p, q)`` of frame *k* (6 DOF): the error ``[s p_true - p,
    Log(q^* q_true)]`` against its 6x6 tangent covariance ``cov`` (``s = scale``, the
    estimate's scale relative to the truth)."""
    e = np.concatenate([scale * scene.positions[k] - p, quat_log(quat_multiply(quat_conjugate(q), scene.quats[k]))])
    return float(e @ np.linalg.solve(cov, e))


def pose_nees(filt, scene, k: int, scale: float = 1.0) -> float:
    """NEES of pose *k* of the filter against its covariance
    (:meth:`InformationFilter.pose_covariance`)."""
    return nees(scene, k, *filt.pose(k), filt.pose_covariance(k), scale)


def gauge_scale(filt, scene, distance: float) -> float | None:
    """The estimate's scale relative to the truth when it is in the truth's gauge up to
    scale (first pose the identity, the scale prior ``distance`` between the first pose and
    another), else None."""
    sp = filt.priors.scale
    if sp is None or int(sp[0]) != 0:
        return None
    d = float(np.linalg.norm(scene.positions[int(sp[1])] - scene.positions[0]))
    return distance / d if d > 0 else None


def interval(runs: int, dof: int = DOF, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` interval of the mean of ``runs`` chi-square(``dof``) values."""
    a = (1.0 - level) / 2.0
    lo, hi = chi2.ppf([a, 1.0 - a], runs * dof) / runs
    return float(lo), float(hi)


def parse_sets(items: list[str]) -> dict[str, dict]:
    """``["experimental.zm_gate_chi2=none", "mapping.min_feature_parallax_deg=4"]`` as config sections."""
    out: dict[str, dict] = {}
    for it in items:
        key, _, val = it.partition("=")
        sec, _, name = key.partition(".")
        if not name:
            raise SystemExit(f"--set {it!r}: expected SECTION.KEY=VALUE")
        low = val.strip().lower()
        v = None if low in ("none", "null") else True if low == "true" else False if low == "false" else val
        if isinstance(v, str):
            try:
                v = float(v) if any(c in v for c in ".e") else int(v)
            except ValueError:
                pass
        out.setdefault(sec, {})[name] = v
    return out


def one_run(seed: int, frames: int, checkpoints: list[int], sections: dict, map_fraction: float,
            step: float = 0.5, fps: float | None = None) -> dict:
    """One Monte Carlo run: NEES at each checkpoint of the latest keyframe (the filter's
    latest pose), filter and smoothed, and of the latest frame between keyframes since the
    previous checkpoint (its reported map pose and covariance; NaN when there was none)."""
    sc = corridor_scene(frames, np.random.default_rng(seed), step=step)
    fe = SyntheticFrontEnd(sc, seed, map_fraction=map_fraction)
    slam = Slam(sc.camera, fe.slam_config(**sections), frontend=fe)
    out: dict[str, list] = {"filter": [], "smooth": [], "between": [], "cost_ratio": []}
    between = np.nan
    distance = slam.config.tracking.scale_distance
    for k in range(frames):
        res = slam.track(k, None if fps is None else k / fps)
        scale = gauge_scale(slam.filter, sc, distance)
        if not res.keyframe and res.covariance is not None and res.position is not None and scale is not None:
            between = nees(sc, k, res.position, res.quat_wxyz, res.covariance, scale)
        if k not in checkpoints:
            continue
        f = slam.filter
        out["between"].append(between)
        between = np.nan
        latest = max((p for p in f.layout.pose_ids if p <= k), default=None)
        if latest is None or scale is None:
            out["filter"].append(np.nan)  # lost, or another gauge than the truth's: not scored
            out["smooth"].append(np.nan)
            out["cost_ratio"].append(np.nan)
            continue
        out["filter"].append(pose_nees(f, sc, latest, scale))
        s = copy.deepcopy(slam) if k < frames - 1 else slam
        costs = s.smooth().common_costs  # at the filter's estimate, then after each round
        out["smooth"].append(pose_nees(s.filter, sc, latest, scale))
        out["cost_ratio"].append(costs[0] / min(costs) if min(costs) > 0 else np.nan)
    out["zm_gate"] = [slam.filter.zm_gate.offered, slam.filter.zm_gate.refused]
    out["gate_chi2"] = slam.filter.config.gate_chi2
    return out


def _one_run(a: tuple) -> dict:
    """:func:`one_run` of an argument tuple (for the process pool)."""
    return one_run(*a)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--every", type=int, default=10, help="NEES after every this many frames (and the last)")
    ap.add_argument("--seed", type=int, default=100, help="run r uses seed SEED + r")
    ap.add_argument("--map-fraction", type=float, default=1.0,
                    help="share of the scene's points in the map (1: every point, as the tests)")
    ap.add_argument("--step", type=float, default=0.5,
                    help="corridor step per frame, m")
    ap.add_argument("--fps", type=float, default=None,
                    help="frame rate for the timestamps (default none: every frame is due as a keyframe); "
                         "e.g. --step 0.1 --fps 10 leaves frames between keyframes")
    ap.add_argument("--jobs", type=int, default=1, help="runs in parallel processes (same results)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = ap.parse_args(argv)
    sections = parse_sets(args.set)
    checkpoints = sorted({k for k in range(args.every - 1, args.frames, args.every)} | {args.frames - 1})
    t0 = time.perf_counter()
    rows = []
    work = [(args.seed + r, args.frames, checkpoints, sections, args.map_fraction, args.step, args.fps)
            for r in range(args.runs)]
    with ProcessPoolExecutor(args.jobs) if args.jobs > 1 else nullcontext() as pool:
        for r, row in enumerate(pool.map(_one_run, work) if pool else map(_one_run, work)):
            rows.append(row)
            print(f"[consistency] run {r + 1}/{args.runs}: filter {row['filter'][-1]:.2f} "
                  f"smooth {row['smooth'][-1]:.2f}", file=sys.stderr, flush=True)
    seconds = time.perf_counter() - t0
    res: dict = {}
    per_frame: dict[str, list] = {"frame": checkpoints}
    for mode in ("filter", "smooth", "between"):
        V = np.array([row[mode] for row in rows], float)  # (runs, checkpoints)
        ok = np.isfinite(V[:, -1])
        n = int(ok.sum())
        lo, hi = interval(n) if n else (float("nan"), float("nan"))
        res[mode] = dict(mean_nees=float(np.mean(V[ok, -1])) if n else None, lo=lo, hi=hi, runs=n,
                         frames=args.frames, median_nees=float(np.median(V[ok, -1])) if n else None,
                         consistent=bool(n and lo <= np.mean(V[ok, -1]) <= hi))
        per_frame[mode] = [float(np.nanmean(V[:, c])) if np.isfinite(V[:, c]).any() else None
                           for c in range(V.shape[1])]
    C = np.array([row["cost_ratio"] for row in rows], float)  # (runs, checkpoints)
    per_frame["cost_ratio"] = [float(np.nanmean(C[:, c])) if np.isfinite(C[:, c]).any() else None
                               for c in range(C.shape[1])]
    per_frame["cost_ratio_max"] = [float(np.nanmax(C[:, c])) if np.isfinite(C[:, c]).any() else None
                                   for c in range(C.shape[1])]
    res["per_frame"] = per_frame
    # the simulation has no wrong matches: every Zm the gate refuses is a false alarm
    offered, refused = (int(sum(row["zm_gate"][i] for row in rows)) for i in (0, 1))
    gate = rows[0]["gate_chi2"] if rows else None
    res["zm_gate"] = dict(offered=offered, refused=refused, rate=refused / offered if offered else None,
                          test_rate=None if gate is None else float(chi2.sf(gate, 2)))
    res["settings"] = dict(sections=sections, map_fraction=args.map_fraction, step=args.step, fps=args.fps, seed=args.seed,
                           jobs=args.jobs,
                           seconds=round(seconds, 1))
    res["machine"] = machine_info()
    res["command"] = command_line(__spec__.name, sys.argv[1:] if argv is None else argv)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "consistency.json").write_text(json.dumps(res, indent=1))
    for mode in ("filter", "smooth", "between"):
        m = res[mode]
        if not m["runs"]:
            continue
        print(f"{mode}: mean NEES {m['mean_nees']:.2f} (95% interval {m['lo']:.2f}-{m['hi']:.2f}, "
              f"{m['runs']} runs x {m['frames']} frames) {'consistent' if m['consistent'] else 'INCONSISTENT'}")
    digits = dict(cost_ratio=4, cost_ratio_max=4)
    print(f"per frame {checkpoints}: "
          + " ".join(f"{m} {[None if v is None else round(v, digits.get(m, 2)) for v in per_frame[m]]}"
                     for m in ("filter", "smooth", "between", "cost_ratio", "cost_ratio_max"))
          + f"  ({seconds:.0f} s)")
    g = res["zm_gate"]
    if g["rate"] is not None and g["test_rate"] is not None:
        print(f"Zm gate: refused {g['refused']} of {g['offered']} correct Zm ({100 * g['rate']:.2f}%; "
              f"the test's false-alarm rate {100 * g['test_rate']:.2f}%)")
    _plot(res, args.out / "consistency.png")
    return 0


def _plot(res: dict, path: Path) -> None:
    """Mean NEES of the latest keyframe against frame, both modes, with the 95% interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pf = res["per_frame"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(pf["frame"], pf["filter"], "o-", label="filter")
    ax.plot(pf["frame"], pf["smooth"], "s-", label="smooth")
    if any(v is not None for v in pf["between"]):
        ax.plot(pf["frame"], [np.nan if v is None else v for v in pf["between"]], "^-",
                label="frame between keyframes")
    lo, hi = interval(max(res["filter"]["runs"], 1))
    ax.axhspan(lo, hi, color="0.85", label="95% interval")
    ax.axhline(DOF, color="k", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("frame (latest keyframe at or before it)")
    ax.set_ylabel("mean NEES (6 DOF)")
    ax.set_title(f"{res['filter']['runs']} Monte Carlo runs")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
