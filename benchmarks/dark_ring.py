"""Dark images: a sparse ring of views, darkened, with and without the gain normalisation.

Usage::

    python benchmarks/dark_ring.py --data ../shared/datasets --out out/dark
    python benchmarks/dark_ring.py --data ../shared/datasets --out out/dark --factors 1,0.5,0.3 \\
        --detectors sift,orb --step 3

A stand-in for the sparse ring of a dark object the issue names (1 view of 16 placed):
every ``--step``-th view of ``middlebury-templering`` (3: 11 views about 23 deg apart), its
images multiplied by each brightness ``--factors`` and written as a data folder under
``OUT/rings/`` (ground truth and camera copied), then run (``--mode``, other settings the
system's defaults) with ``frontend.normalise_gain`` false and true. Records per run the views
placed, the map features and the ATE, and per ring the images' 99.99th percentile (the
level the normalisation maps to 255). Writes ``OUT/dark_ring.json``; the table is printed
on stdout. Ground truth is used for scoring only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (  # noqa: E402
    command_line, fmt, log, machine_info, markdown_table, run_one, short_error, split_list, write_json,
)

SOURCE = "middlebury-templering"
HEADERS = ("brightness", "detector", "99.99th percentile", "normalise_gain", "placed", "map features", "ATE",
           "note")


def make_ring(src: Path, dst: Path, step: int, factor: float) -> tuple[Path, list[float]]:
    """Write every ``step``-th view of ``src`` times ``factor`` as a data folder ``dst``.

    Returns
    -------
    (folder, levels)
        The folder and the 99.99th percentile of each written image (grayscale).
    """
    images = sorted((src / "images").iterdir())
    gt = [line for line in (src / "groundtruth.tum").read_text().splitlines() if line and not line.startswith("#")]
    if len(gt) != len(images):
        raise ValueError(f"{src}: {len(images)} images but {len(gt)} ground-truth poses")
    (dst / "images").mkdir(parents=True, exist_ok=True)
    (dst / "camera.yaml").write_text((src / "camera.yaml").read_text())
    lines, times, levels = ["# timestamp tx ty tz qx qy qz qw"], [], []
    for n, k in enumerate(range(0, len(images), step)):
        img = cv2.imread(str(images[k]), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"{images[k]}: unreadable image")
        dark = np.clip(np.round(img.astype(np.float64) * factor), 0, 255).astype(np.uint8)
        cv2.imwrite(str(dst / "images" / f"{n:04d}.png"), dark)
        levels.append(float(np.percentile(cv2.cvtColor(dark, cv2.COLOR_BGR2GRAY), 99.99)))
        lines.append(" ".join([f"{n:.6f}"] + gt[k].split()[1:]))
        times.append(f"{n:.6f}")
    (dst / "groundtruth.tum").write_text("\n".join(lines) + "\n")
    (dst / "times.txt").write_text("\n".join(times) + "\n")
    return dst, levels


def main(argv: Sequence[str] | None = None) -> int:
    """Run the study; 0 when every run produced a report, 1 when some failed, 2 on bad input."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="folder of data sets (holds middlebury-templering)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--factors", default="1,0.7,0.5,0.3,0.15", help="brightness factors")
    ap.add_argument("--detectors", default="sift", help="comma-separated detectors")
    ap.add_argument("--step", type=int, default=3, help="keep every STEP-th view")
    ap.add_argument("--mode", default="smooth", choices=("filter", "smooth"))
    args = ap.parse_args(argv)
    src = args.data / SOURCE
    if not (src / "images").is_dir():
        log(f"{src}: no such data set (needs ../shared/datasets/{SOURCE})")
        return 2
    try:
        factors = [float(f) for f in split_list(args.factors)]
    except ValueError:
        log(f"--factors {args.factors!r}: not a list of numbers")
        return 2
    if not factors or any(not 0.0 < f <= 1.0 for f in factors) or args.step < 1:
        log("--factors must lie in (0, 1] and --step be at least 1")
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {"command": command_line(__file__, argv), "machine": machine_info(),
                              "source": SOURCE, "step": args.step, "mode": args.mode, "rows": []}
    failed = False
    for factor in factors:
        folder, levels = make_ring(src, args.out / "rings" / f"x{factor:g}", args.step, factor)
        for det in split_list(args.detectors):
            for on in (False, True):
                log(f"brightness {factor:g}, {det}, normalise_gain {on}")
                row = run_one(folder, f"ring-x{factor:g}", args.mode, det, args.out / f"x{factor:g}-{det}-{int(on)}",
                              frontend={"normalise_gain": on})
                row.update(brightness=factor, normalise_gain=on, level_min=min(levels), level_max=max(levels),
                           views=len(levels))
                failed |= bool(row.get("error"))
                result["rows"].append(row)
    write_json(args.out / "dark_ring.json", result)
    table = [(fmt(r["brightness"]), r["detector"], f"{r['level_min']:.0f}-{r['level_max']:.0f}",
              str(r["normalise_gain"]).lower(), f"{r.get('frames_tracked')}/{r['views']}", fmt(r.get("map_features")),
              fmt(r.get("ate_rmse")), short_error(r.get("error") or r.get("evaluation_error") or ""))
             for r in result["rows"]]
    print(markdown_table(HEADERS, table))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
