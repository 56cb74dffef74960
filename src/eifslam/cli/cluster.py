"""The Dask engine of ``eifslam batch``: tasks of :mod:`eifslam.evaluation.batch` on a cluster.

:func:`run_on_dask` starts a local cluster of single-threaded worker processes (or
connects to an existing scheduler), submits one task per (source, setting) whose folder
is not complete, and collects the rows as the tasks finish, with a progress bar over
tasks. Dask is an optional dependency (``pip install "eifslam[batch]"``), imported only
here and only when a batch runs; :func:`import_distributed` raises :class:`DaskMissing`
with the install hint when it is absent.

A task that raises gives a row with its error (:func:`eifslam.evaluation.batch.run_task`
catches it); a task whose worker dies (killed, out of memory) is not retried on the
local cluster (``allowed-failures`` 0: Dask's ``KilledWorker``) and gives a row too. At
most as many tasks as the cluster has threads are submitted at a time, so a dying worker
holds only the task it was running.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import uuid
from typing import Any, Callable, Iterator, Sequence

from ..errors import EifslamError
from ..evaluation.batch import BatchTask, failed_row, is_complete, one_line, run_task, skipped_row

#: what to do when Dask is not installed
INSTALL_HINT = ('eifslam batch needs Dask: pip install "eifslam[batch]" '
                '(in a checkout: pip install -e ".[batch]")')


class DaskMissing(EifslamError):
    """``dask.distributed`` is not installed (the message says how to install it)."""


def import_distributed():
    """The ``distributed`` module.

    Raises
    ------
    DaskMissing
        It cannot be imported; the message is :data:`INSTALL_HINT`.
    """
    try:
        import distributed
    except ImportError:
        raise DaskMissing(INSTALL_HINT) from None
    return distributed


def default_workers() -> int:
    """The number of CPUs this process may use (one single-threaded worker each)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def run_task_single_threaded(task: BatchTask) -> dict[str, Any]:
    """:func:`~eifslam.evaluation.batch.run_task` with OpenCV and BLAS limited to one
    thread (so that workers sharing a machine do not fight over its cores)."""
    from ..frontend.features import set_opencv_threads

    set_opencv_threads(1)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # the worker's OMP/OPENBLAS/MKL_NUM_THREADS still apply (Dask sets them to 1)
        return run_task(task)
    with threadpool_limits(limits=1):
        return run_task(task)


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A ``distributed.Client``: on a new local cluster of ``workers`` single-threaded
    processes, or on the scheduler at ``scheduler`` (``tcp://host:port``); closed after.

    Raises
    ------
    DaskMissing
        Dask is not installed.
    EifslamError
        The scheduler cannot be reached (one line naming it).
    """
    distributed = import_distributed()
    import dask

    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout="15s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise EifslamError(f"{scheduler}: cannot connect to the Dask scheduler ({one_line(exc)})") from None
        with client:
            yield client
        return
    # a worker that dies takes only its task with it: no retry elsewhere, a KilledWorker row;
    # no statistical profiler (a 10 ms tick in each worker; nothing here shows its profiles)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0, "distributed.worker.profile.enabled": False}):
        cluster = distributed.LocalCluster(n_workers=workers or default_workers(), threads_per_worker=1,
                                           processes=True, dashboard_address=None, silence_logs=logging.ERROR)
    with cluster, distributed.Client(cluster) as client:
        yield client


def run_on_dask(tasks: Sequence[BatchTask], workers: int | None = None, scheduler: str | None = None,
                force: bool = False, progress: bool = True,
                on_row: Callable[[int, dict[str, Any]], None] | None = None,
                task_function: Callable[[BatchTask], dict[str, Any]] = run_task_single_threaded,
                ) -> list[dict[str, Any]]:
    """Run the tasks on Dask; every task gets a row, whatever happens to it.

    Parameters
    ----------
    tasks : sequence of BatchTask
    workers : int, optional
        Worker processes of the local cluster (default: the usable CPUs).
    scheduler : str, optional
        Address of an existing scheduler (its workers must have eifslam and see the
        sources and the output folder at the same paths).
    force : bool
        Redo the tasks whose folders are complete (else they are skipped, no cluster is
        started when every task is).
    progress : bool
        A progress bar over tasks on stderr.
    on_row : callable, optional
        ``(index, row)`` as each row arrives (e.g. to rewrite ``results.json``).
    task_function : callable
        What a worker runs for a task (tests replace it).

    Notes
    -----
    The local cluster starts its workers with ``multiprocessing``'s *spawn*: a script that
    calls this needs the ``if __name__ == "__main__":`` guard, as for ``multiprocessing``.

    Returns
    -------
    list of dict
        The rows, in the order of ``tasks``. Interrupted (Ctrl-C), the unfinished tasks
        are given rows saying so (through ``on_row``) before the interrupt goes on; so
        are they when the cluster fails (a scheduler that cannot be reached).

    Raises
    ------
    DaskMissing
        Dask is not installed.
    EifslamError
        The scheduler cannot be reached.
    """
    from tqdm import tqdm

    rows: list[dict[str, Any] | None] = [None] * len(tasks)

    def record(k: int, row: dict[str, Any]) -> None:
        rows[k] = row
        if on_row is not None:
            on_row(k, row)

    todo = []
    for k, task in enumerate(tasks):
        if not force and is_complete(task.out_dir):
            record(k, skipped_row(task))
        else:
            todo.append(k)
    started: dict[int, float] = {}
    try:
        if todo:
            with dask_client(workers, scheduler) as client:
                _collect(client, tasks, todo, task_function, record, started, progress, tqdm)
    except BaseException as exc:
        why = ("not finished: the batch was interrupted" if isinstance(exc, KeyboardInterrupt)
               else f"not finished: {one_line(exc)}")
        for k in todo:
            if rows[k] is None:
                t0 = started.get(k)
                note = " (its folder's report.json is complete)" if t0 is not None and is_complete(
                    tasks[k].out_dir) else ""
                record(k, failed_row(tasks[k], why + note, None if t0 is None else time.perf_counter() - t0))
        raise
    return [r for r in rows if r is not None]


def _collect(client: Any, tasks: Sequence[BatchTask], todo: list[int], task_function: Callable, record: Callable,
             started: dict[int, float], progress: bool, tqdm: Callable) -> None:
    """Submit the tasks ``todo``, at most one per worker thread at a time, and record each
    row as its future completes."""
    from distributed import as_completed

    queue = iter(todo)
    index: dict[str, int] = {}
    done = as_completed()
    batch_id = uuid.uuid4().hex[:8]

    def submit_next() -> None:
        k = next(queue, None)
        if k is None:
            return
        fut = client.submit(task_function, tasks[k], key=f"eifslam-{tasks[k].name}-{batch_id}", pure=False,
                            retries=0)
        index[fut.key] = k
        started[k] = time.perf_counter()
        done.add(fut)

    def slots() -> int:
        return max(1, sum(client.nthreads().values()))

    for _ in range(min(slots(), len(todo))):
        submit_next()
    with tqdm(total=len(tasks), initial=len(tasks) - len(todo), unit="task", desc="eifslam batch",
              disable=not progress) as bar:
        for fut in done:
            k = index.pop(fut.key)
            try:
                row = fut.result()
            except Exception as exc:  # noqa: BLE001 - a dead worker (KilledWorker), a cancelled task
                row = failed_row(tasks[k], one_line(exc), time.perf_counter() - started[k])
            fut.release()
            record(k, row)
            bar.set_postfix_str(f"{tasks[k].name}: {row['status']}", refresh=False)
            bar.update(1)
            while done.count() < slots() and len(started) < len(todo):
                submit_next()
