"""Exact against FLANN matching of SIFT descriptors: where ``EXACT_ROWS`` comes from.

Usage::

    python -m benchmarks.matching --data ../shared/datasets --out out/matching

For frame pairs ``(k, k + 2)`` of each data set (SIFT at the front end's defaults), times
:meth:`DescriptorMatcher.match` with every keypoint free and with a share of them free
(the older-frame search, where only keypoints left unmatched are searched), once exact
(the matrix of all distances) and once by FLANN on prebuilt indices (their building not
counted: a frame's index is built once for several searches), on one BLAS and one OpenCV
thread, medians of ``--repeat`` runs. Writes ``OUT/matching.json``::

    {"rows": [{"dataset", "pair", "free", "n1", "n2", "exact_ms", "flann_ms",
               "exact_matches", "flann_matches", "common"}, ...],
     "machine": {...}, "command": "..."}

and prints one table row per measurement.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from eifslam.frontend import FrontEnd, FrontEndConfig
from eifslam.frontend import matching
from eifslam.io import open_source

from ._common import command_line, discover_datasets, fmt, machine_info, markdown_table, write_json


def _median_ms(f, repeat: int) -> tuple[float, tuple]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = f()
        times.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(times)), out


def measure(d1: np.ndarray, d2: np.ndarray, free: float, repeat: int, seed: int = 0) -> dict:
    """One pair of descriptor sets (float32 ``(N1, 128)``, ``(N2, 128)``), a share ``free`` of
    each side's rows free."""
    rng = np.random.default_rng(seed)
    f1, f2 = rng.random(len(d1)) < free, rng.random(len(d2)) < free
    m = matching.DescriptorMatcher()
    i1, i2 = m.index(d1, seed), m.index(d2, seed)
    exact_ms, exact = _median_ms(lambda: m.match(d1, d2, f1, f2), repeat)
    rows = matching.EXACT_ROWS
    matching.EXACT_ROWS = 0  # FLANN on the prebuilt indices
    try:
        i1.build(), i2.build()
        flann_ms, flann = _median_ms(lambda: m.match(d1, d2, f1, f2, i1, i2), repeat)
    finally:
        matching.EXACT_ROWS = rows
    a, b = set(zip(*map(list, exact))), set(zip(*map(list, flann)))
    return dict(free=free, n1=int(f1.sum()), n2=int(f2.sum()), exact_ms=exact_ms, flann_ms=flann_ms,
                exact_matches=len(a), flann_matches=len(b), common=len(a & b))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="folder of data sets")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--pairs", type=int, default=3, help="frame pairs per data set")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--free", default="1.0,0.5", help="comma-separated shares of free rows")
    args = ap.parse_args(argv)
    shares = [float(s) for s in args.free.split(",")]
    rows = []
    cv2.setNumThreads(1)
    with threadpool_limits(limits=1):
        for ds in discover_datasets(args.data):
            seq = open_source(ds)
            fe = FrontEnd(seq.camera, FrontEndConfig())
            for k in np.linspace(0, len(seq) - 3, args.pairs).astype(int):
                a, b = (np.asarray(fe.detect(seq.load(int(j))).descriptors, np.float32) for j in (k, k + 2))
                for free in shares:
                    r = dict(dataset=ds.name, pair=[int(k), int(k) + 2], **measure(a, b, free, args.repeat))
                    rows.append(r)
                    print(f"{ds.name} {k}-{k + 2} free {free}: {r['n1']} x {r['n2']} exact {r['exact_ms']:.1f} ms "
                          f"FLANN {r['flann_ms']:.1f} ms", file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "matching.json",
               dict(rows=rows, machine=machine_info(), command=command_line("benchmarks.matching", sys.argv[1:])))
    print(markdown_table(["data set", "pair", "free rows", "exact ms", "FLANN ms", "exact matches", "FLANN matches",
                          "common"],
                         [[r["dataset"], f"{r['pair'][0]}-{r['pair'][1]}", f"{r['n1']} x {r['n2']}",
                           fmt(r["exact_ms"]), fmt(r["flann_ms"]), str(r["exact_matches"]),
                           str(r["flann_matches"]), str(r["common"])] for r in rows]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
