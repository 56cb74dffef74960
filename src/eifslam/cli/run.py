"""``eifslam run SOURCE --out DIR``: SLAM on a folder, a KITTI/TUM/EuRoC/Strecha layout or a video."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ConfigError, EifslamError
from ..frontend.config import DETECTORS
from ..system.config import Mode, SlamConfig

_DEFAULT = SlamConfig()


def add_common_options(p: argparse.ArgumentParser, max_features: int | None = None) -> None:
    """Options shared by ``run`` and ``demo``; every default is the configuration's
    (``SlamConfig()``) unless the command passes its own ``max_features``."""
    fe, sy = _DEFAULT.frontend, _DEFAULT.system
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--mode", choices=[m.value for m in Mode], default=None,
                   help=f"filter only, filter + relinearise + smooth, or filter + full bundle adjustment "
                        f"(default {sy.mode.value})")
    p.add_argument("--features", choices=list(DETECTORS), default=None,
                   help=f"feature detector (default {fe.detector.value})")
    p.add_argument("--map-fraction", type=float, default=None,
                   help=f"fraction of tracks kept in the map (Ωm); default {fe.map_fraction:g}, measured "
                        "(the paper kept 0.3)")
    p.add_argument("--max-features", type=int, default=None,
                   help=f"features detected per image (default {max_features or fe.max_features})")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames")
    p.add_argument("--no-html", action="store_true", help="skip report.html")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("run", help="run SLAM on an image sequence",
                       description="Run eifslam on SOURCE and write trajectory.tum, map.ply, report.json, report.html.")
    p.add_argument("source", type=Path, help="data folder (images/ + camera.yaml), KITTI/TUM/EuRoC/Strecha layout, or video")
    p.add_argument("--camera", type=Path, default=None, help="camera file (eifslam YAML, OpenCV YAML, KITTI calib.txt)")
    p.add_argument("--scale-distance", nargs=5, metavar=("KIND_A", "ID_A", "KIND_B", "ID_B", "LENGTH"), default=None,
                   help="known length between two states, e.g. 'pose 0 pose 10 2.5' or 'feature 12 feature 40 0.3'")
    p.add_argument("--save-session", type=Path, default=None, metavar="FILE",
                   help="save the session (.npz) after the last frame, to continue it with --resume")
    p.add_argument("--resume", type=Path, default=None, metavar="FILE",
                   help="continue a saved session on the frames of SOURCE after those it has "
                        "(with the session's configuration)")
    add_common_options(p)
    p.set_defaults(func=main)
    return p


def make_config(args: argparse.Namespace, base: SlamConfig | None = None) -> SlamConfig:
    """The configuration the command-line options ask for: ``base`` (default
    ``SlamConfig()``) with only the options the user passed changed."""
    fe: dict = {}
    if args.map_fraction is not None:
        if not 0.0 < args.map_fraction <= 1.0:
            raise ConfigError(f"--map-fraction must lie in (0, 1], got {args.map_fraction}")
        fe["map_fraction"] = args.map_fraction
    if args.features is not None:
        fe["detector"] = args.features
    if args.max_features is not None:
        fe["max_features"] = args.max_features
    sy = {} if args.mode is None else {"mode": args.mode}
    return (base or SlamConfig()).replace(frontend=fe, system=sy)


def parse_scale(values: list[str] | None) -> tuple | None:
    """``--scale-distance KIND_A ID_A KIND_B ID_B LENGTH`` as ``((kind, id), (kind, id), length)``."""
    if not values:
        return None
    ka, ia, kb, ib, length = values
    try:
        return (ka, int(ia)), (kb, int(ib)), float(length)
    except ValueError as exc:
        raise EifslamError(f"--scale-distance: {exc}") from exc


def main(args: argparse.Namespace) -> int:
    from ..evaluation.outputs import run_to_folder
    from ..io import open_source

    seq = open_source(args.source, camera=args.camera)
    resume = None
    if args.resume is not None:
        from ..system.slam import Slam

        resume = Slam.load(args.resume)
        given = [f"--{k.replace('_', '-')}" for k in ("mode", "features", "map_fraction", "max_features")
                 if getattr(args, k, None) is not None]
        if given:
            raise ConfigError(f"--resume continues with the session's configuration; {given[0]} cannot change it")
    config = resume.config if resume is not None else make_config(args)
    rep = run_to_folder(seq, config, args.out, max_frames=args.max_frames,
                        scale=parse_scale(args.scale_distance), html=not args.no_html,
                        slam=resume, save_session=args.save_session)
    return 0 if rep.get("frames_tracked", 0) > 0 else 1
