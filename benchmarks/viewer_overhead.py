"""What the rerun viewer costs the tracking: runs with and without it, alternated.

Usage::

    python -m benchmarks.viewer_overhead --data out/loopworld --max-frames 100 --repeats 2

Runs :func:`eifslam.system.runner.run_sequence` on the first ``--max-frames`` frames of
``--data`` (default settings), alternately without the viewer and with
:class:`eifslam.viz.viewer.RerunViewer` recording to a temporary ``.rrd`` file, and prints
per run: the wall time, the process's CPU time (every thread: the rerun SDK's included),
the summed tracking time of :meth:`Slam.track` and the time spent in the viewer's
per-frame callback. The cost of the viewer is the callback's time against the tracking
time, and the CPU time with against without. Timings depend on the machine's load.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def measure(data: Path, max_frames: int, viewer: bool, rrd: Path) -> dict[str, float]:
    """One run; seconds of wall time, CPU, tracking and viewer callback."""
    from eifslam.io import open_source
    from eifslam.system.config import SlamConfig
    from eifslam.system.runner import run_sequence
    from eifslam.system.slam import Slam
    from eifslam.viz.viewer import RerunViewer

    seq, config = open_source(data), SlamConfig()
    slam, spent, on_frame, v = Slam(seq.camera, config), [0.0], None, None
    if viewer:
        gt = seq.ground_truth() if getattr(seq, "has_ground_truth", False) else None
        v = RerunViewer(seq.camera, save=rrd, ground_truth=gt, color_order=config.frontend.color_order)
        seq, show = v.watch(seq), v.on_frame(slam)

        def on_frame(res) -> None:
            t = time.perf_counter()
            show(res)
            spent[0] += time.perf_counter() - t

    c0, t0 = _cpu(), time.perf_counter()
    run_sequence(seq, config, max_frames=max_frames, quiet=True, on_frame=on_frame, slam=slam)
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    if v is not None:
        v.finish(slam)
    track = sum(r.timings_ms.get("total", 0.0) for r in slam.results) / 1e3
    return dict(wall=wall, cpu=cpu, track=track, viewer=spent[0])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a data folder eifslam run reads")
    ap.add_argument("--max-frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            for viewer in (False, True):
                r = measure(args.data, args.max_frames, viewer, Path(tmp) / f"run{k}.rrd")
                rows.append((viewer, r))
                print(f"viewer {'on ' if viewer else 'off'}: wall {r['wall']:.2f} s, cpu {r['cpu']:.2f} s, "
                      f"tracking {r['track']:.2f} s, viewer callback {r['viewer']:.3f} s", flush=True)
    on = [r for v, r in rows if v]
    off = [r for v, r in rows if not v]
    callback = sum(r["viewer"] for r in on) / sum(r["track"] for r in on)
    cpu = sum(r["cpu"] for r in on) / sum(r["cpu"] for r in off)
    print(f"viewer callback / tracking time: {100 * callback:.1f} %; CPU time with / without: {cpu:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
