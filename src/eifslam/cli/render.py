"""``eifslam render``: write a built-in scene as a data set.

``--scene boxes`` (default) is the paper's first experiment, ``--scene loop`` the loop
world (two laps round a block of textured walls, for loop closure), ``--scene aliasing``
one lap round a block whose walls repeat the same photographs (for false loops).
Examples::

    eifslam render --out builtin --frames 54 --noise 1.0
    eifslam render --scene loop --out loopworld
    eifslam render --scene aliasing --out aliasing
"""

from __future__ import annotations

import argparse
import math
import time

from ..errors import ConfigError, EifslamError

__all__ = ["add_parser", "run"]

#: most frames ``render`` writes (one loop round the table; 54 in the paper)
MAX_FRAMES = 10_000
#: per scene: frames, width, height, horizontal field of view (degrees), laps
DEFAULTS = {"boxes": (54, 1024, 768, 56.0, 1), "loop": (1040, 640, 480, 60.0, 2),
            "aliasing": (400, 640, 480, 60.0, 1)}


def add_parser(sub: "argparse._SubParsersAction") -> argparse.ArgumentParser:
    """Register the ``render`` sub-command."""
    p = sub.add_parser(
        "render",
        help="render a built-in scene (three boxes on a table, the loop world or the aliasing "
        "scene) to a data set folder",
        description="Render a built-in scene into the data set folder layout: images/, "
        "camera.yaml, times.txt, groundtruth.tum (and boxes.json for the boxes). "
        "--scene boxes: the paper's first experiment (three boxes on an oval table, one loop "
        "of a camera round it). --scene loop: the loop world (a camera walking laps round a "
        "block of walls with posters and pillars, photographs from scikit-image). --scene "
        "aliasing: one lap and a little more round a block whose wall panels repeat the same "
        "photographs, facing different ways and the same way at other places (every loop "
        "before the path's last part is false, the last part comes back to the start).",
    )
    p.add_argument("--scene", choices=tuple(DEFAULTS), default="boxes",
                   help="which scene (default boxes)")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--frames", type=int, default=None,
                   help="number of images (default 54 for boxes, 1040 for loop, 400 for aliasing)")
    p.add_argument("--laps", type=int, default=None,
                   help="laps of the path, loop scene only (default 2)")
    p.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                   help="Gaussian pixel noise, grey levels (default 0)")
    p.add_argument("--blur", type=float, default=0.0, metavar="SIGMA",
                   help="Gaussian blur, pixels (default 0)")
    p.add_argument("--width", type=int, default=None, help="image width (default 1024 boxes, 640 loop and aliasing)")
    p.add_argument("--height", type=int, default=None, help="image height (default 768 boxes, 480 loop and aliasing)")
    p.add_argument("--hfov", type=float, default=None,
                   help="horizontal field of view, degrees (default 56 boxes, 60 loop and aliasing)")
    p.add_argument("--seed", type=int, default=0, help="seed of textures, wobble and noise")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Render the scene as the arguments ask; returns the exit code."""
    from tqdm import tqdm

    from ..io.files import ensure_output_dir
    from ..io.image_header import check_image_size
    from ..sim.scene import make_scene
    from ..sim.scene.aliasing import make_aliasing_scene
    from ..sim.scene.loop import make_loop_scene
    from ..sim.scene.render import render_scene

    frames, width, height, hfov, laps = DEFAULTS[args.scene]
    frames = frames if args.frames is None else args.frames
    width = width if args.width is None else args.width
    height = height if args.height is None else args.height
    hfov = hfov if args.hfov is None else args.hfov
    if args.laps is not None and args.scene != "loop":
        raise ConfigError("--laps applies to --scene loop only")
    laps = laps if args.laps is None else args.laps
    if not (math.isfinite(args.noise) and math.isfinite(args.blur) and args.noise >= 0 and args.blur >= 0):
        raise ConfigError(f"--noise and --blur must be finite and >= 0, got {args.noise} and {args.blur}")
    if not math.isfinite(hfov):
        raise ConfigError(f"--hfov must be finite, got {hfov}")
    if not 2 <= frames <= MAX_FRAMES:
        raise ConfigError(f"--frames must lie in [2, {MAX_FRAMES}], got {frames}")
    if not 1 <= laps <= 100:
        raise ConfigError(f"--laps must lie in [1, 100], got {laps}")
    try:
        check_image_size(width, height, "--width/--height")
    except EifslamError as exc:
        raise ConfigError(str(exc)) from None
    ensure_output_dir(args.out)
    if args.scene == "loop":
        scene = make_loop_scene(n_frames=frames, n_laps=laps, width=width, height=height,
                                hfov_deg=hfov, seed=args.seed)
    elif args.scene == "aliasing":
        scene = make_aliasing_scene(n_frames=frames, width=width, height=height, hfov_deg=hfov,
                                    seed=args.seed)
    else:
        scene = make_scene(n_frames=frames, width=width, height=height, hfov_deg=hfov, seed=args.seed)
    t0 = time.perf_counter()
    with tqdm(total=scene.n_frames, desc="render", unit="frame") as bar:
        out = render_scene(scene, args.out, noise_sigma=args.noise, blur_sigma=args.blur,
                           seed=args.seed, progress=lambda k: bar.update(1))
    dt = time.perf_counter() - t0
    print(f"wrote {scene.n_frames} frames of {width}x{height} to {out} "
          f"({dt / scene.n_frames:.3f} s/frame incl. textures and PNG)")
    return 0
