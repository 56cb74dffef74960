"""Per-frame back-end cost of the exactly sparse EIF against a dense EKF (MonoSLAM-style).

The same synthetic corridor exploration (:func:`eifslam.sim.synthetic.corridor_scene`,
measured by :class:`eifslam.sim.frontend.SyntheticFrontEnd`, every point in the map) runs
through the system (:class:`eifslam.system.slam.Slam`, default settings) with

* the EIF with incremental recovery (paper III-G), and with the full solve, and
* :class:`eifslam.baselines.ekf.DenseEKF` (same measurements, same linearisation, dense covariance),

timing each frame's back end (the system's ``fuse`` + ``recover`` timings): EIF = fuse +
recover, EKF = linearise + covariance update.
The EKF stops after the first frame whose update exceeds ``--ekf-budget-s``.

Writes ``DIR/ekf_vs_eif.json`` (``{"eif": [{"frame", "state_dim", "ms"}...], "eif_full":
[...], "ekf": [...], "ekf_stopped_at_state_dim": n, "machine": {...}, "command": "..."}``) and ``DIR/ekf_vs_eif.png``.

    python -m benchmarks.ekf_vs_eif --out out/ekf_vs_eif
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from eifslam.baselines.ekf import DenseEKF
from eifslam.estimation.filter import InformationFilter
from eifslam.sim import synthetic
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.system.slam import Slam

from ._common import command_line, machine_info, write_json


def _track(scene, seed: int, backend: str, budget_s: float | None = None) -> list[dict]:
    """The system over the scene with one back end ("incremental", "full" or "ekf");
    per-frame rows; stops after the first frame whose back end took over ``budget_s``."""
    fe = SyntheticFrontEnd(scene, seed, map_fraction=1.0)
    config = fe.slam_config()
    filt = DenseEKF(scene.camera, config.filter) if backend == "ekf" else \
        InformationFilter(scene.camera, config.filter, recovery=backend)
    slam = Slam(scene.camera, config, frontend=fe, backend=filt)
    rows = []
    for k in range(len(scene.positions)):
        res = slam.track(k)
        ms = res.timings_ms.get("fuse", 0.0) + res.timings_ms.get("recover", 0.0)
        rows.append(dict(frame=k, state_dim=res.state_dim, ms=round(ms, 3)))
        if budget_s is not None and ms > 1e3 * budget_s:
            break
    return rows


def run(n_frames: int, seed: int, budget_s: float) -> dict:
    """Run the three back ends on one simulated corridor; return the JSON dict."""
    rng = np.random.default_rng(seed)
    scene = synthetic.corridor_scene(n_frames, rng)
    out: dict = {"n_frames": n_frames, "seed": seed, "ekf_budget_s": budget_s}
    for key, recovery in (("eif", "incremental"), ("eif_full", "full")):
        out[key] = _track(scene, seed, recovery)
    out["ekf"] = _track(scene, seed, "ekf", budget_s)
    stopped = len(out["ekf"]) < n_frames
    out["ekf_stopped_at_state_dim"] = out["ekf"][-1]["state_dim"] if stopped else None
    return out


def plot(res: dict, ax) -> None:
    """Per-frame back-end milliseconds against state dimension on ``ax``."""
    for key, label, style in (("ekf", "dense EKF (covariance update)", "o-"),
                              ("eif_full", "EIF, full recovery", "s-"),
                              ("eif", "EIF, incremental recovery", "^-")):
        rows = res[key]
        ax.plot([r["state_dim"] for r in rows], [r["ms"] for r in rows], style, ms=3, label=label)
    if res.get("ekf_stopped_at_state_dim"):
        ax.axvline(res["ekf_stopped_at_state_dim"], color="0.5", ls=":", label="EKF stopped")
    ax.set_xlabel("state dimension")
    ax.set_ylabel("back-end ms per frame (fuse + recover / update)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ekf-budget-s", type=float, default=2.0)
    args = ap.parse_args(argv)
    res = run(args.frames, args.seed, args.ekf_budget_s)
    res["machine"] = machine_info()
    res["command"] = command_line(__spec__.name, sys.argv[1:] if argv is None else argv)
    write_json(args.out / "ekf_vs_eif.json", res)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    plot(res, ax)
    fig.tight_layout()
    fig.savefig(args.out / "ekf_vs_eif.png", dpi=120)
    for key in ("eif", "eif_full", "ekf"):
        rows = res[key]
        if rows:
            print(f"{key}: {len(rows)} frames, last state_dim {rows[-1]['state_dim']}, "
                  f"median {np.median([r['ms'] for r in rows]):.1f} ms, last {rows[-1]['ms']:.1f} ms")
    print(f"EKF stopped at state dim: {res['ekf_stopped_at_state_dim']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
