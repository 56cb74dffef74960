"""``eifslam run SOURCE --out DIR``: SLAM on a folder, a KITTI/TUM/EuRoC/Strecha layout or a video."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..system.config import SlamConfig
from ..errors import ConfigError, EifslamError


def add_common_options(p: argparse.ArgumentParser) -> None:
    """Options shared by ``run`` and ``demo``."""
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--mode", choices=["filter", "smooth", "ba"], default="smooth",
                   help="filter only, filter + relinearise + smooth (default), or filter + full bundle adjustment")
    p.add_argument("--features", choices=["sift", "orb", "akaze", "surf"], default="sift", help="feature detector")
    p.add_argument("--map-fraction", type=float, default=None,
                   help="fraction of tracks kept in the map (Ωm); default 0.5, measured (the paper kept 0.3)")
    p.add_argument("--max-features", type=int, default=None,
                   help="features detected per image (default 2000; demo: 4000)")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames")
    p.add_argument("--no-html", action="store_true", help="skip report.html")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("run", help="run SLAM on an image sequence",
                       description="Run eifslam on SOURCE and write trajectory.tum, map.ply, report.json, report.html.")
    p.add_argument("source", type=Path, help="data folder (images/ + camera.yaml), KITTI/TUM/EuRoC/Strecha layout, or video")
    p.add_argument("--camera", type=Path, default=None, help="camera file (eifslam YAML, OpenCV YAML, KITTI calib.txt)")
    p.add_argument("--scale-distance", nargs=5, metavar=("KIND_A", "ID_A", "KIND_B", "ID_B", "LENGTH"), default=None,
                   help="known length between two states, e.g. 'pose 0 pose 10 2.5' or 'feature 12 feature 40 0.3'")
    add_common_options(p)
    p.set_defaults(func=main)
    return p


def make_config(args: argparse.Namespace, map_fraction: float = 0.5, max_features: int | None = None) -> SlamConfig:
    """The configuration the command-line options ask for (defaults given by the command)."""
    frac = map_fraction if args.map_fraction is None else args.map_fraction
    if not 0.0 < frac <= 1.0:
        raise ConfigError(f"--map-fraction must lie in (0, 1], got {frac}")
    fe: dict = {"detector": args.features, "map_fraction": frac}
    nfeat = max_features if args.max_features is None else args.max_features
    if nfeat is not None:
        fe["max_features"] = nfeat
    return SlamConfig().replace(frontend=fe, system={"mode": args.mode})


def main(args: argparse.Namespace) -> int:
    from ..io import open_source
    from ..system.runner import run_sequence

    seq = open_source(args.source, camera=args.camera)
    scale = None
    if args.scale_distance:
        ka, ia, kb, ib, length = args.scale_distance
        try:
            scale = ((ka, int(ia)), (kb, int(ib)), float(length))
        except ValueError as exc:
            raise EifslamError(f"--scale-distance: {exc}") from exc
    rep = run_sequence(seq, make_config(args), args.out, max_frames=args.max_frames, scale=scale,
                       html=not args.no_html)
    return 0 if rep.get("frames_tracked", 0) > 0 else 1
