"""``eifslam render``: write the built-in scene (the paper's first experiment) as a data set.

Example::

    eifslam render --out builtin --frames 54 --noise 1.0
"""

from __future__ import annotations

import argparse
import math
import time

from ..errors import ConfigError, EifslamError

__all__ = ["add_parser", "run"]

#: most frames ``render`` writes (one loop round the table; 54 in the paper)
MAX_FRAMES = 10_000


def add_parser(sub: "argparse._SubParsersAction") -> argparse.ArgumentParser:
    """Register the ``render`` sub-command."""
    p = sub.add_parser(
        "render",
        help="render the built-in three-boxes-on-a-table scene to a data set folder",
        description="Render the built-in scene of the paper's first experiment (three boxes "
        "on an oval table, one loop of a camera round it) into the data set folder layout: "
        "images/, camera.yaml, times.txt, groundtruth.tum, boxes.json.",
    )
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--frames", type=int, default=54, help="number of images (default 54)")
    p.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                   help="Gaussian pixel noise, grey levels (default 0)")
    p.add_argument("--blur", type=float, default=0.0, metavar="SIGMA",
                   help="Gaussian blur, pixels (default 0)")
    p.add_argument("--width", type=int, default=1024, help="image width (default 1024)")
    p.add_argument("--height", type=int, default=768, help="image height (default 768)")
    p.add_argument("--hfov", type=float, default=56.0, help="horizontal field of view, degrees")
    p.add_argument("--seed", type=int, default=0, help="seed of textures, wobble and noise")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Render the scene as the arguments ask; returns the exit code."""
    from tqdm import tqdm

    from ..io.files import ensure_output_dir
    from ..io.image_header import check_image_size
    from ..sim.scene import make_scene
    from ..sim.scene.render import render_scene

    if not (math.isfinite(args.noise) and math.isfinite(args.blur) and args.noise >= 0 and args.blur >= 0):
        raise ConfigError(f"--noise and --blur must be finite and >= 0, got {args.noise} and {args.blur}")
    if not math.isfinite(args.hfov):
        raise ConfigError(f"--hfov must be finite, got {args.hfov}")
    if not 2 <= args.frames <= MAX_FRAMES:
        raise ConfigError(f"--frames must lie in [2, {MAX_FRAMES}], got {args.frames}")
    try:
        check_image_size(args.width, args.height, "--width/--height")
    except EifslamError as exc:
        raise ConfigError(str(exc)) from None
    ensure_output_dir(args.out)
    scene = make_scene(n_frames=args.frames, width=args.width, height=args.height,
                       hfov_deg=args.hfov, seed=args.seed)
    t0 = time.perf_counter()
    with tqdm(total=scene.n_frames, desc="render", unit="frame") as bar:
        out = render_scene(scene, args.out, noise_sigma=args.noise, blur_sigma=args.blur,
                           seed=args.seed, progress=lambda k: bar.update(1))
    dt = time.perf_counter() - t0
    print(f"wrote {scene.n_frames} frames of {args.width}x{args.height} to {out} "
          f"({dt / scene.n_frames:.3f} s/frame incl. textures and PNG)")
    return 0
