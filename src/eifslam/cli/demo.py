"""``eifslam demo --out DIR``: render the built-in scene (the paper's first experiment),
run SLAM on it and report the estimated width:length ratio of the 0.80:1 box."""

from __future__ import annotations

import argparse
import math
import sys

from ..system.config import SlamConfig
from .run import add_common_options, announce, base_config, guard_outputs, make_config, provenance

#: The demo's one departure from ``SlamConfig()``: a denser map than run's default
#: features per image, because the box ratio is measured from the features on one small
#: face (0.28 m x 0.35 m), see docs/demo.md.
DEMO_MAX_FEATURES = 4000


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("demo", help="render the built-in three-box scene and run SLAM on it (no download)",
                       description="The paper's first experiment: three boxes on an oval table, 54 images, "
                                   "1024x768, 56 degree field of view. Writes the outputs of 'run' plus the box ratio.")
    add_common_options(p, max_features=DEMO_MAX_FEATURES)
    p.add_argument("--frames", type=int, default=54, help="number of images (default 54)")
    p.add_argument("--noise", type=float, default=0.0, help="image noise sigma (grey levels)")
    p.add_argument("--blur", type=float, default=0.0, help="blur sigma (pixels)")
    p.set_defaults(func=main)
    return p


def main(args: argparse.Namespace) -> int:
    from ..evaluation.box_ratio import add_box_ratio
    from ..evaluation.outputs import run_to_folder
    from ..errors import ConfigError
    from ..io import open_source
    from ..io.files import ensure_output_dir
    from ..sim.scene import make_scene, render_scene

    if args.frames < 3:
        raise ConfigError(f"--frames must be >= 3, got {args.frames}")
    if not (math.isfinite(args.noise) and math.isfinite(args.blur) and args.noise >= 0 and args.blur >= 0):
        raise ConfigError(f"--noise and --blur must be finite and >= 0, got {args.noise} and {args.blur}")
    guard_outputs(args.out, args.force)
    config = make_config(args, base_config(args, SlamConfig().replace(frontend={"max_features": DEMO_MAX_FEATURES})))
    ensure_output_dir(args.out)
    scene = make_scene(n_frames=args.frames)
    data = args.out / "scene"
    if not args.quiet:
        print(f"eifslam: rendering the built-in scene ({args.frames} images) into {data}", file=sys.stderr)
    render_scene(scene, data, noise_sigma=args.noise, blur_sigma=args.blur)
    seq = open_source(data)
    announce(args, config)
    rep = run_to_folder(seq, config, args.out, max_frames=args.max_frames, html=False,
                        extra=provenance(args, config), quiet=args.quiet, verbose=not args.quiet)
    if rep.get("frames_tracked", 0) >= 3:
        add_box_ratio(rep, args.out, scene)
        if rep.get("box_ratio_estimated") is not None and not args.quiet:
            print(f"eifslam: box width:length {rep['box_ratio_estimated']:.3f} (true {rep['box_ratio_true']:.2f}, "
                  f"{rep['box_ratio_points']} map features on its top face)", file=sys.stderr)
    if not args.no_html:  # after the box ratio, which is the demo's headline
        from ..evaluation.metrics import DATASET_UNITS
        from ..evaluation.report import write_report

        write_report(args.out, ground_truth=seq.ground_truth(), units=DATASET_UNITS,
                     title=f"eifslam demo: three boxes on an oval table ({args.frames} images)")
    return 0
