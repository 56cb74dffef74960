"""What ``eifslam batch`` gains: the smallest shared sets one after another against a Dask cluster.

Takes the ``--count`` data sets under ``--data`` with the fewest images (4: on the shared
data strecha-fountain-p11, strecha-herzjesu-p25, strecha-castle-p30,
middlebury-templering), builds the tasks of ``eifslam batch`` (one per set, ``--mode``,
``--features``) and runs them

1. ``sequential``: one after another in this process (:func:`run_serial`), with the
   threads a plain ``eifslam run`` gets (OpenCV's default, BLAS as the environment says);
2. ``dask``: on a local cluster of a scheduler and ``--workers`` single-threaded worker
   processes (:func:`eifslam.cli.cluster.run_on_dask`), the start and stop of the cluster
   included in the wall time;

each ``--repeat`` times, alternating. Prints the figures and writes
``OUT/batch_speedup.json``: per round and mode the wall seconds, the 1-minute load average
before and after, the tasks' CPU seconds and the cores they used on average (CPU / wall:
on a shared Linux machine with ``sched_autogroup`` the kernel gives each session a share,
however many processes it runs), and each task's wall and CPU seconds, tracked frames and
ATE; the median speed-up (sequential / dask); and the bound the
longest task sets (``max(sum / workers, longest)`` of the sequential task times).

    python -m benchmarks.batch_speedup --data ../shared/datasets --out out/batch_speedup
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from ._common import command_line, discover_datasets, log, machine_info, write_json

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}


def smallest_datasets(data: Path, count: int) -> list[tuple[str, int]]:
    """The ``count`` data sets under ``data`` with the fewest image files, as ``(name, images)``."""
    sizes = [(sum(f.suffix.lower() in IMAGE_SUFFIXES for f in (d / "images").iterdir()), d.name)
             for d in discover_datasets(data)]
    return [(name, n) for n, name in sorted(sizes)[:count]]


def _phase(name: str, run) -> dict[str, Any]:
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    rows = run()
    wall = time.perf_counter() - t0
    log(f"{name}: {wall:.1f} s wall; " + ", ".join(f"{r['dataset']} {r['seconds']} s" for r in rows))
    cpu = sum(r["cpu_seconds"] or 0.0 for r in rows)
    return dict(wall_seconds=round(wall, 3), load_average_1min=[round(load0, 2), round(os.getloadavg()[0], 2)],
                task_cpu_seconds=round(cpu, 3), cores_used=round(cpu / wall, 3),
                tasks=[{k: r[k] for k in ("dataset", "status", "seconds", "cpu_seconds", "frames",
                                                                         "tracked", "ate_rmse", "error")}
                                                    for r in rows])


def _autogroup() -> bool | None:
    """Whether the kernel shares CPU between sessions (``/proc/sys/kernel/sched_autogroup_enabled``)."""
    try:
        return Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return None


def main(argv: list[str] | None = None) -> dict[str, Any]:
    from eifslam.cli.cluster import run_on_dask
    from eifslam.evaluation.batch import make_tasks, run_serial
    from eifslam.system.config import SlamConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets"), help="folder of data sets")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--count", type=int, default=4, help="how many of the smallest data sets (default 4)")
    ap.add_argument("--workers", type=int, default=2, help="single-threaded Dask workers (default 2)")
    ap.add_argument("--mode", default="filter", help="system mode (default filter)")
    ap.add_argument("--features", default=None, help="detector (default: the configuration's)")
    ap.add_argument("--repeat", type=int, default=1, help="rounds of both, alternating (default 1)")
    args = ap.parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)

    sets = smallest_datasets(args.data, args.count)
    if not sets:
        raise SystemExit(f"no data sets under {args.data}")
    log(f"data sets: {sets}")
    fe = {} if args.features is None else {"detector": args.features}
    config = SlamConfig().replace(smoothing={"mode": args.mode}, frontend=fe)
    sources = [args.data / name for name, _ in sets]
    rounds = []
    for r in range(args.repeat):
        seq = make_tasks(sources, [config], args.out / "sequential", html=False)
        dsk = make_tasks(sources, [config], args.out / "dask", html=False)
        rounds.append(dict(
            sequential=_phase(f"round {r + 1} sequential", lambda: run_serial(seq, force=True)),
            dask=_phase(f"round {r + 1} dask ({args.workers} workers)",
                        lambda: run_on_dask(dsk, workers=args.workers, force=True, progress=False)),
        ))
    speedups = [rd["sequential"]["wall_seconds"] / rd["dask"]["wall_seconds"] for rd in rounds]
    task_s = [[t["seconds"] for t in rd["sequential"]["tasks"]] for rd in rounds]
    bounds = [sum(ts) / max(sum(ts) / args.workers, max(ts)) for ts in task_s]
    res = dict(machine=machine_info(), command=command_line(__spec__.name, argv), datasets=dict(sets),
               mode=args.mode, detector=config.frontend.detector, workers=args.workers, rounds=rounds,
               speedup_median=round(statistics.median(speedups), 3), speedups=[round(s, 3) for s in speedups],
               speedup_bound_median=round(statistics.median(bounds), 3),
               note="wall times on a machine shared with other jobs; the dask time includes starting and "
                    "stopping the cluster; bound = sum of the sequential task times / max(sum / workers, "
                    "longest task)",
               sched_autogroup=_autogroup())
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "batch_speedup.json", res)
    for k, rd in enumerate(rounds):
        print(f"round {k + 1}: sequential {rd['sequential']['wall_seconds']:.1f} s "
              f"({rd['sequential']['cores_used']:.2f} cores), dask {args.workers} workers "
              f"{rd['dask']['wall_seconds']:.1f} s ({rd['dask']['cores_used']:.2f} cores), "
              f"speed-up {speedups[k]:.2f} (bound {bounds[k]:.2f})")
    print(f"median speed-up {res['speedup_median']:.2f}; wrote {args.out / 'batch_speedup.json'}")
    return res


if __name__ == "__main__":
    main()
