"""Sessions on disk: file size, save and load time, and whether a resumed run continues
as the uninterrupted one (issue 15).

Runs ``Slam`` over the first ``--frames`` images of a source, saves the session (``.npz``
plus JSON, :mod:`eifslam.system.session`) and loads it back ``--repeat`` times, compares
the size with a pickle of the same object (the format sessions had before), then tracks
``--more`` further images on the loaded session and on the uninterrupted system and
reports the largest difference of their camera centres. Prints the figures and writes
``session_io_<recovery>.json`` into ``--out``.

    python benchmarks/session_io.py --data ../shared/datasets/kitti-seq1 --frames 20 --out out/bench
"""

from __future__ import annotations

import argparse
import json
import pickle
import platform
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="any source eifslam run takes")
    ap.add_argument("--frames", type=int, default=20, help="images tracked before the save")
    ap.add_argument("--more", type=int, default=5, help="images tracked after the load")
    ap.add_argument("--repeat", type=int, default=3, help="saves and loads timed (median)")
    ap.add_argument("--recovery", choices=["incremental", "full"], default="incremental",
                    help="per-frame recovery (experimental.recovery): a loaded incremental recovery rebuilds its "
                         "window, so its later estimates differ from the uninterrupted run's where the two "
                         "windows keep different states at their last estimate; full recovery has no window")
    ap.add_argument("--out", required=True, type=Path, help="output folder for session_io.json")
    args = ap.parse_args(argv)

    import eifslam
    from eifslam import Slam, SlamConfig, open_source

    seq = open_source(args.data)
    n = min(args.frames, len(seq))
    more = min(args.more, len(seq) - n)
    images = [seq.load(k) for k in range(n + more)]
    stamps = [seq.frames[k].timestamp for k in range(n + more)]
    slam = Slam(seq.camera, SlamConfig().replace(experimental={"recovery": args.recovery}))
    for k in range(n):
        slam.track(images[k], stamps[k])
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "session_io.npz"
    save_s, load_s = [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        slam.save(path)
        save_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        back = Slam.load(path)
        load_s.append(time.perf_counter() - t0)
    pickled = len(pickle.dumps(slam, protocol=pickle.HIGHEST_PROTOCOL))
    for k in range(n, n + more):
        slam.track(images[k], stamps[k])
        back.track(images[k], stamps[k])
    pa = np.array([r.position if r.position is not None else np.full(3, np.nan) for r in slam.results])
    pb = np.array([r.position if r.position is not None else np.full(3, np.nan) for r in back.results])
    same_tracked = bool(np.array_equal(np.isnan(pa), np.isnan(pb)))
    diff = float(np.nanmax(np.abs(pa - pb))) if same_tracked else float("inf")
    extent = float(np.nanmax(np.linalg.norm(pa - pa[0], axis=1)))
    res = {
        "source": str(args.data), "recovery": args.recovery, "frames_saved": n, "frames_after": more,
        "map_features": slam.filter.layout.n_features, "state_dim": slam.filter.dim,
        "file_mb": path.stat().st_size / 1e6, "pickle_mb": pickled / 1e6,
        "save_s_median": float(np.median(save_s)), "load_s_median": float(np.median(load_s)),
        "resumed_same_frames_tracked": same_tracked, "resumed_max_position_diff": diff,
        "trajectory_extent": extent,
        "eifslam_version": eifslam.__version__, "python": sys.version.split()[0], "machine": platform.machine(),
        "command": "python benchmarks/session_io.py " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    (args.out / f"session_io_{args.recovery}.json").write_text(json.dumps(res, indent=2) + "\n")
    path.unlink()
    for k, v in res.items():
        print(f"{k:30s} {v:.4g}" if isinstance(v, float) else f"{k:30s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
