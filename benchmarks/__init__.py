"""Benchmarks of eifslam: programs that measure accuracy and cost, run from the repository's root.

Each is a module run as ``python -m benchmarks.<name> --help``; each prints its figures,
writes them as JSON (with the machine and the command that produced them) and, where a
picture helps, a PNG:

* :mod:`benchmarks.run_all`: accuracy and cost over every shared data set, mode and
  detector (writes ``docs/results.md`` with ``--docs``);
* :mod:`benchmarks.realtime`: frames per second and per-stage milliseconds;
* :mod:`benchmarks.frontend`: front-end stage timings and relative-pose accuracy;
* :mod:`benchmarks.backend_scaling`: back-end cost against the state dimension;
* :mod:`benchmarks.ekf_vs_eif`: the EIF's back-end cost against a dense EKF;
* :mod:`benchmarks.consistency`: NEES of the latest pose over Monte Carlo runs;
* :mod:`benchmarks.loop_closure`: loops found and false loops against the ground truth;
* :mod:`benchmarks.loop_world`: drift and lap gap on the rendered loop world;
* :mod:`benchmarks.batch_speedup`: what ``eifslam batch`` gains on a Dask cluster.

:mod:`benchmarks._common` holds the shared helpers, among them the provenance header
(date, machine, commit, command) of every Markdown page a benchmark writes. This package
imports nothing at import time, so a benchmark can set BLAS's threads before NumPy loads.
"""
