"""What losing nothing costs: the per-frame price of ``trajectory.partial.tum`` and of
atomic output writes (issue 16).

Measures, in a temporary folder on the file system of ``--dir``:

* ``TumAppender.append`` (one TUM line, flushed to the OS) per pose, microseconds;
* for a trajectory of ``--poses`` poses, milliseconds: ``write_tum`` (formatting plus an
  atomic write), and the writing alone: ``atomic_write`` (temporary file, fsync,
  ``os.replace``) against a plain ``Path.write_text`` of the same text.

Prints a table and writes ``OUT/safe_outputs.json``.

    python benchmarks/safe_outputs.py --out out/safe_outputs [--poses 5000] [--repeat 5] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import command_line, machine_info, write_json  # noqa: E402


def _time(fn, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def main(argv: list[str] | None = None) -> dict:
    from eifslam.geometry.rotations import quat_normalize
    from eifslam.io.files import atomic_write
    from eifslam.io.trajectory import TumAppender, write_tum

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=5000, help="poses per trajectory (default 5000)")
    ap.add_argument("--repeat", type=int, default=5, help="repetitions (median reported)")
    ap.add_argument("--dir", default=None, help="folder for the temporary files (default: the system's)")
    ap.add_argument("--out", type=Path, required=True, help="folder for safe_outputs.json")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(0)
    n = args.poses
    t = np.arange(n) * 0.1
    P = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    Q = quat_normalize(rng.normal(size=(n, 4)))
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        folder = Path(d)

        def append_all() -> None:
            log = TumAppender(folder / "partial.tum")
            for k in range(n):
                log.append(t[k], P[k], Q[k])
            log.close()

        append_s = _time(append_all, args.repeat)
        atomic_s = _time(lambda: write_tum(folder / "t.tum", t, P, Q), args.repeat)
        text = (folder / "t.tum").read_text()
        plain_s = _time(lambda: (folder / "plain.tum").write_text(text), args.repeat)
        atomic_text_s = _time(lambda: atomic_write(folder / "atomic.tum", text), args.repeat)
    result = dict(
        poses=n, repeat=args.repeat,
        append_us_per_pose=round(statistics.median(append_s) / n * 1e6, 2),
        write_tum_ms=round(statistics.median(atomic_s) * 1e3, 2),
        atomic_write_ms=round(statistics.median(atomic_text_s) * 1e3, 2),
        plain_write_text_ms=round(statistics.median(plain_s) * 1e3, 2),
        machine=machine_info(), command=command_line(__file__, sys.argv[1:] if argv is None else argv),
    )
    print(f"{'TumAppender.append (flushed), per pose':45s} {result['append_us_per_pose']:10.2f} us")
    print(f"{'write_tum (format + atomic), ' + str(n) + ' poses':45s} {result['write_tum_ms']:10.2f} ms")
    print(f"{'atomic_write of that text':45s} {result['atomic_write_ms']:10.2f} ms")
    print(f"{'Path.write_text of that text':45s} {result['plain_write_text_ms']:10.2f} ms")
    write_json(args.out / "safe_outputs.json", result)
    print(f"wrote {args.out / 'safe_outputs.json'}")
    return result


if __name__ == "__main__":
    main()
