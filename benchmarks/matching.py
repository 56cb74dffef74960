"""The matching stage alone: CPU time of ``FrontEnd.add_features`` over a sequence, replayed.

Usage::

    python benchmarks/matching.py --data ../shared/datasets/kitti-seq1 --out out/matching
    python benchmarks/matching.py --data ../shared/datasets/7scenes-redkitchen-a --detector orb \\
        --max-frames 150 --set match_window=1 --out out/matching --tag window1

The features of the first ``--max-frames`` images are detected once and cached
(``OUT/features-<set>-<detector>-<n>.pkl``, reused by later runs); then a fresh front end
adds them in order (what the tracking thread's ``match`` stage does: descriptor matching
against the match window, the epipolar RANSAC, the tracks), and the script reports the CPU
time of that replay (``time.process_time``: on a machine shared with other jobs it varies
far less than wall time), the median ``match`` milliseconds per frame (wall), and what the
tracks became: tracks seen in two frames or more, their observations, their mean length.
Run it with ``PYTHONPATH`` at another checkout to time that code on the same features
(``--set`` needs keys that checkout knows). Appends one row to ``OUT/matching.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import command_line, machine_info, split_list, write_json  # noqa: E402


def _config(detector: str, seed: int, settings: list[str]):
    from eifslam.frontend.config import FrontEndConfig

    cfg = dataclasses.replace(FrontEndConfig(), detector=detector, seed=seed)
    for kv in settings:
        key, _, value = kv.partition("=")
        cur = getattr(cfg, key)
        typed = value.lower() in ("1", "true", "yes") if isinstance(cur, bool) else type(cur)(value)
        cfg = dataclasses.replace(cfg, **{key: typed})
    return cfg


def replay(data: Path, detector: str, max_frames: int, cache_dir: Path, seed: int = 0,
           settings: list[str] | None = None) -> dict:
    """Detect (or load the cached features), then time ``add_features`` over the frames.

    Returns
    -------
    dict
        ``cpu_s, wall_s, match_ms_median, frames, features_median, tracks, observations,
        mean_track_length`` (tracks of two frames or more).
    """
    from eifslam.frontend import FrontEnd
    from eifslam.io.detect import open_source

    seq = open_source(data)
    n = min(int(max_frames), len(seq))
    cache = cache_dir / f"features-{data.name}-{detector}-{n}.pkl"
    if cache.exists():
        feats = pickle.loads(cache.read_bytes())
    else:
        fe = FrontEnd(seq.camera, _config(detector, seed, []))
        feats = [fe.detect(seq.load(k)) for k in range(n)]
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_bytes(pickle.dumps(feats))
    fe = FrontEnd(seq.camera, _config(detector, seed, settings or []))
    ms = []
    c0, w0 = time.process_time(), time.perf_counter()
    for k, f in enumerate(feats):
        ms.append(fe.add_features(f, k).timings_ms["match"])
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    lengths = np.array(list(Counter(np.concatenate([fe.frame(k).track_ids for k in range(n)]).tolist()).values()))
    multi = lengths[lengths >= 2]
    return {"frames": n, "features_median": float(np.median([len(f) for f in feats])), "cpu_s": cpu,
            "wall_s": wall, "match_ms_median": float(np.median(ms)), "tracks": int(len(multi)),
            "observations": int(multi.sum()), "mean_track_length": float(multi.mean()) if len(multi) else 0.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="one data-set folder")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--detector", default="sift")
    ap.add_argument("--max-frames", type=int, default=10**9)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], help="front-end key=value (repeatable)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    settings = [s for item in args.set for s in split_list(item)]
    row = {"set": args.data.name, "detector": args.detector, "tag": args.tag, "settings": settings,
           **replay(args.data, args.detector, args.max_frames, args.out, args.seed, settings)}
    import eifslam

    row["eifslam"] = str(Path(eifslam.__file__).resolve().parent)
    path = args.out / "matching.json"
    old = json.loads(path.read_text()) if path.exists() else {"rows": []}
    old["rows"].append(row)
    old["machine"], old["command"] = machine_info(), command_line(__file__, sys.argv[1:] if argv is None else argv)
    write_json(path, old)
    print(f"{row['set']} {row['detector']} {args.tag}: {row['frames']} frames, cpu {row['cpu_s']:.2f} s, "
          f"match median {row['match_ms_median']:.1f} ms, tracks {row['tracks']} "
          f"({row['observations']} observations, mean length {row['mean_track_length']:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
