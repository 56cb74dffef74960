"""``eifslam run SOURCE --out DIR``: SLAM on a folder, a KITTI/TUM/EuRoC/Strecha layout, a video or a
ROS bag."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..errors import ConfigError, DatasetError, EifslamError
from ..frontend.config import DETECTORS
from ..system.config import Mode, SlamConfig

_DEFAULT = SlamConfig()

#: the kinds of state ``--scale-distance`` can name
SCALE_KINDS = ("pose", "feature")


def add_common_options(p: argparse.ArgumentParser, max_features: int | None = None, several: bool = False) -> None:
    """Options shared by ``run``, ``demo`` and ``batch``; every default is the configuration's
    (``SlamConfig()``) unless the command passes its own ``max_features``. With ``several``
    (``batch``), ``--mode`` and ``--features`` take one or more values (a list)."""
    fe = _DEFAULT.frontend
    nargs = "+" if several else None
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--mode", choices=[m.value for m in Mode], default=None, nargs=nargs,
                   help=f"filter only, filter + relinearise + smooth, or filter + full bundle adjustment "
                        f"(smoothing.mode; default {_DEFAULT.smoothing.mode.value})")
    p.add_argument("--features", choices=list(DETECTORS), default=None, nargs=nargs,
                   help=f"feature detector (frontend.detector; default {fe.detector.value})")
    p.add_argument("--map-fraction", type=float, default=None,
                   help=f"fraction of tracks kept in the map (Ωm; frontend.map_fraction); default "
                        f"{fe.map_fraction:g}")
    p.add_argument("--max-features", type=int, default=None,
                   help=f"features detected per image (frontend.max_features; default "
                        f"{max_features or fe.max_features})")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames")
    p.add_argument("--no-html", action="store_true", help="skip report.html")
    loops = p.add_mutually_exclusive_group()
    loops.add_argument("--loop-closure", action="store_true",
                       help="place recognition and loop closure (loops.enabled true; "
                            f"default {'on' if _DEFAULT.loops.enabled else 'off'})")
    loops.add_argument("--no-loop-closure", action="store_true",
                       help="no place recognition or loop closure (loops.enabled false)")
    p.add_argument("--config", type=Path, default=None, metavar="FILE.yaml",
                   help="settings from a YAML file (any of 'eifslam config' prints); the options above "
                        "override it")
    p.add_argument("--seed", type=int, default=None,
                   help=f"seed of the front end's random draws (frontend.seed, default {fe.seed})")
    p.add_argument("--force", action="store_true",
                   help="redo the tasks whose output folders are complete (else they are skipped)" if several
                   else "write into an output folder that already holds eifslam outputs (they are replaced)")
    talk = p.add_mutually_exclusive_group()
    talk.add_argument("-q", "--quiet", action="store_true", help="no progress bar and no summary line")
    talk.add_argument("-v", "--verbose", action="store_true",
                      help="also print the effective configuration (YAML) before the run")


#: Files an eifslam run writes into its output folder (the overwrite guard looks for them).
OUTPUT_FILES = ("report.json", "trajectory.tum", "map.ply", "frames.json", "information.npz", "state_layout.json",
                "report.html")


def guard_outputs(out: Path, force: bool) -> None:
    """Refuse to write into a folder that holds an earlier run's outputs, unless ``force``.

    Raises
    ------
    EifslamError
        One line naming the folder and the first output file found in it.
    """
    if force or not out.is_dir():
        return
    found = [f for f in OUTPUT_FILES if (out / f).is_file()]  # a folder of that name is no output
    if found:
        raise EifslamError(f"{out} already holds eifslam outputs ({found[0]}); use --force to replace them, "
                           "or choose another --out")


def base_config(args: argparse.Namespace, default: SlamConfig | None = None) -> SlamConfig:
    """The configuration before the command-line options: ``--config FILE``'s, else ``default``
    (``SlamConfig()``)."""
    if getattr(args, "config", None) is not None:
        from .config import read_config

        return read_config(args.config)
    return default or SlamConfig()


def provenance(args: argparse.Namespace, config: SlamConfig) -> dict:
    """What ``report.json`` records to reproduce the run: the version, the full effective
    configuration and the command."""
    import shlex

    from .. import __version__

    argv = getattr(args, "argv", None)
    return {"eifslam_version": __version__, "config": config.to_dict(),
            "command": shlex.join(["eifslam", *argv]) if argv is not None else None}


def announce(args: argparse.Namespace, config: SlamConfig) -> None:
    """With ``-v``: the effective configuration on stderr."""
    if getattr(args, "verbose", False):
        import sys

        from .config import config_yaml

        print("eifslam: effective configuration:\n" + config_yaml(config), file=sys.stderr, end="")


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("run", help="run SLAM on an image sequence",
                       description="Run eifslam on SOURCE and write trajectory.tum, map.ply, report.json, report.html.")
    p.add_argument("source", type=Path, help="data folder (images/ + camera.yaml), KITTI/TUM/EuRoC/Strecha layout, "
                                              "video, ROS 1 .bag file or ROS 2 bag folder")
    p.add_argument("--camera", type=Path, default=None,
                   help="camera file (eifslam YAML, OpenCV YAML, KITTI calib.txt); for a ROS bag, instead of its "
                        "CameraInfo")
    p.add_argument("--topic", default=None, metavar="TOPIC",
                   help="image topic of a ROS bag (sensor_msgs/Image or CompressedImage), e.g. /cam0/image_raw; "
                        "default: the bag's only image topic")
    p.add_argument("--scale-distance", nargs=5, metavar=("KIND_A", "ID_A", "KIND_B", "ID_B", "LENGTH"), default=None,
                   help="known length between two states, e.g. 'pose 0 pose 10 2.5' or 'feature 12 feature 40 0.3'")
    p.add_argument("--save-session", type=Path, default=None, metavar="FILE",
                   help="save the session (.npz) after the last frame, to continue it with --resume")
    p.add_argument("--resume", type=Path, default=None, metavar="FILE",
                   help="continue a saved session on the frames of SOURCE after those it has "
                        "(with the session's configuration)")
    p.add_argument("--viewer", action="store_true",
                   help="open the rerun viewer and stream the run to it (needs the viewer extra: "
                        "pip install 'eifslam[viewer]')")
    p.add_argument("--rerun-save", type=Path, default=None, metavar="FILE.rrd",
                   help="record the viewer's stream into a rerun file, to open later with 'rerun FILE.rrd'")
    add_common_options(p)
    p.set_defaults(func=main)
    return p


def make_config(args: argparse.Namespace, base: SlamConfig | None = None) -> SlamConfig:
    """The configuration the command-line options ask for: ``base`` (default
    ``SlamConfig()``) with only the options the user passed changed."""
    fe: dict = {}
    max_frames = getattr(args, "max_frames", None)  # not a configuration value: checked here, early
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames must be >= 1, got {max_frames}")
    if args.map_fraction is not None:
        if not 0.0 < args.map_fraction <= 1.0:
            raise ConfigError(f"--map-fraction must lie in (0, 1], got {args.map_fraction}")
        fe["map_fraction"] = args.map_fraction
    if args.features is not None:
        fe["detector"] = args.features
    if args.max_features is not None:
        fe["max_features"] = args.max_features
    if getattr(args, "seed", None) is not None:
        fe["seed"] = args.seed
    smoothing = {} if args.mode is None else {"mode": args.mode}
    loops = {}
    if getattr(args, "no_loop_closure", False):
        loops["enabled"] = False
    elif getattr(args, "loop_closure", False):
        loops["enabled"] = True
    return (base or SlamConfig()).replace(frontend=fe, smoothing=smoothing, loops=loops)


def parse_scale(values: list[str] | None) -> tuple | None:
    """``--scale-distance KIND_A ID_A KIND_B ID_B LENGTH`` as ``((kind, id), (kind, id), length)``.

    Checked before any work: kinds ``pose``/``feature``, ids non-negative integers, the
    length (map units) positive and finite. Whether the two states exist is known only at
    the end of the run (a missing one gives a warning and unscaled outputs).

    Raises
    ------
    ConfigError
        One line naming the option and the bad value.
    """
    if not values:
        return None
    ka, ia, kb, ib, length = values
    keys = []
    for kind, ident in ((ka, ia), (kb, ib)):
        if kind not in SCALE_KINDS:
            raise ConfigError(f"--scale-distance: unknown state kind {kind!r} (use 'pose' or 'feature')")
        try:
            k = int(ident)
        except ValueError:
            raise ConfigError(f"--scale-distance: state id must be an integer, got {ident!r}") from None
        if k < 0:
            raise ConfigError(f"--scale-distance: state id must be >= 0, got {k}")
        keys.append((kind, k))
    try:
        d = float(length)
    except ValueError:
        raise ConfigError(f"--scale-distance: length must be a number, got {length!r}") from None
    if not (math.isfinite(d) and d > 0):
        raise ConfigError(f"--scale-distance: length must be positive and finite, got {length!r}")
    if keys[0] == keys[1]:
        raise ConfigError(f"--scale-distance: the two states are the same ({ka} {keys[0][1]})")
    return keys[0], keys[1], d


def main(args: argparse.Namespace) -> int:
    from ..evaluation.outputs import run_to_folder
    from ..io import open_source
    from ..io.files import ensure_output_dir

    # everything that can be checked before any work: options, output folder, then source
    scale = parse_scale(args.scale_distance)
    viewing = getattr(args, "viewer", False) or getattr(args, "rerun_save", None) is not None
    if viewing:
        from ..viz.viewer import import_rerun

        import_rerun(spawn=args.viewer)  # one line saying how to install it, or that there is no display
        save = getattr(args, "rerun_save", None)
        if save is not None and not save.parent.is_dir():
            raise ConfigError(f"--rerun-save: {save.parent} is not a folder")
    guard_outputs(args.out, args.force)
    resume = None
    if args.resume is not None:
        from ..system.slam import Slam

        resume = Slam.load(args.resume)
        given = [f"--{k.replace('_', '-')}" for k in ("mode", "features", "map_fraction", "max_features",
                                                      "seed", "config")
                 if getattr(args, k, None) is not None]
        if given:
            raise ConfigError(f"--resume continues with the session's configuration; {given[0]} cannot change it")
        config = resume.config
    else:
        config = make_config(args, base_config(args))
    ensure_output_dir(args.out)
    seq = open_source(args.source, camera=args.camera, topic=args.topic)
    announce(args, config)
    viewer, on_frame, slam = None, None, resume
    if viewing:
        from ..evaluation.outputs import scoring_ground_truth
        from ..system.slam import Slam
        from ..viz.viewer import RerunViewer

        gt, _ = scoring_ground_truth(seq)  # drawn, never given to the estimator
        viewer = RerunViewer(seq.camera, spawn=args.viewer, save=args.rerun_save, ground_truth=gt,
                             color_order=config.frontend.color_order)
        slam = resume if resume is not None else Slam(seq.camera, config)
        seq, on_frame = viewer.watch(seq), viewer.on_frame(slam)
    try:
        rep = run_to_folder(seq, config, args.out, max_frames=args.max_frames, scale=scale, html=not args.no_html,
                            extra=provenance(args, config), quiet=args.quiet, verbose=not args.quiet,
                            on_frame=on_frame, slam=slam, save_session=args.save_session)
    finally:
        if viewer is not None:
            viewer.finish(slam)
    if rep.get("frames_tracked", 0) == 0:
        raise DatasetError(f"{args.source}: no frame could be tracked ({rep.get('frames', 0)} read; "
                           f"the empty outputs are in {args.out})")
    return 0
