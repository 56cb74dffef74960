"""Drive a :class:`~eifslam.system.slam.Slam` over a sequence with a progress bar; lose nothing.

Ctrl-C, a stop request (:func:`request_stop`: the CLI's SIGTERM and SIGHUP) or a failing
frame stops the loop; :meth:`Slam.finish` then ends the run as the
configured mode says, and what was estimated so far is returned. Writing the outputs is
the caller's job (:func:`eifslam.evaluation.outputs.run_to_folder`).

The front end is pipelined (``config.runtime.prefetch`` frames ahead, 2 by default): worker
threads decode the next images (``seq.load``, in order) and detect their features
(``FrontEnd.detect``; OpenCV releases the GIL) while this thread matches, relates and
fuses the current one. Detection depends on nothing but the image, and everything else
runs in frame order in the calling thread, so the results are those of the sequential
loop (``prefetch=0``).
"""

from __future__ import annotations

import contextlib
import os
import queue
import sys
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from tqdm import tqdm

from ..errors import EifslamError, ImageError
from ..frontend.features import opencv_threads
from .config import SlamConfig
from .finishing import FinishReport
from .slam import Slam, TrackResult

__all__ = ["FramePrefetcher", "RunResult", "request_stop", "resume_index", "run_sequence", "sequential_frames",
           "stop_requests"]


class _StopRequest:
    """A stop asked of a run (by a signal handler): the loop honours it between frames,
    so the system is never left half way through a frame; once the loop is over, the
    run's finishing and saving go on."""

    depth = 0  # runs in progress (nested stop_requests blocks)
    reason: str | None = None


_STOP = _StopRequest()


@contextlib.contextmanager
def stop_requests() -> Iterator[None]:
    """While inside, :func:`request_stop` is accepted. :func:`run_sequence` is inside one;
    a caller that also saves the outputs wraps the saving too, so a stop asked while it
    saves lets it finish."""
    _STOP.depth += 1
    try:
        yield
    finally:
        _STOP.depth -= 1
        if _STOP.depth == 0:
            _STOP.reason = None


def request_stop(reason: str) -> bool:
    """Ask the run in progress to stop after the frame being tracked (it then finishes
    and its outputs are written, as after Ctrl-C). Safe to call from a signal handler.

    Returns
    -------
    bool
        False when no run is in progress or a stop is already pending: the caller should
        then interrupt at once (``raise KeyboardInterrupt``).
    """
    if _STOP.depth == 0 or _STOP.reason is not None:
        return False
    _STOP.reason = reason
    return True


@dataclass
class RunResult:
    """A finished run.

    Attributes
    ----------
    slam : Slam
        The system after :meth:`Slam.finish` (and the scale, when one was given).
    seconds : float
        Wall time of the run, ``finish`` included.
    stopped : str or None
        Why the run stopped early or a finishing step failed (None: it did not).
    finish : FinishReport
    scale_error : str or None
        Why the known length was not applied (a state not in the map, ...); the outputs
        are then unscaled.
    """

    slam: Slam
    seconds: float
    stopped: str | None
    finish: FinishReport
    scale_error: str | None = None


def resume_index(seq, slam: Slam) -> int:
    """The first frame of ``seq`` after the last one ``slam`` has seen (by timestamp): where
    a loaded session continues on the same source (``len(seq)`` when it has them all)."""
    if not slam.results:
        return 0
    last = slam.results[-1].timestamp
    return next((k for k, f in enumerate(seq.frames) if f.timestamp > last), len(seq))


def sequential_frames(seq, n: int, start: int = 0) -> Iterator[tuple[int, Any, float]]:
    """Frames ``start .. n-1`` of ``seq`` decoded in the calling thread.

    Yields
    ------
    (k, item, ms)
        ``item`` is the image (or the :class:`~eifslam.errors.ImageError` its decoding
        raised: the frame is skipped); ``ms`` the decoding time, milliseconds.
    """
    for k in range(start, n):
        t0 = time.perf_counter()
        try:
            item: Any = seq.load(k)
        except ImageError as exc:
            item = exc
        yield k, item, (time.perf_counter() - t0) * 1e3


class FramePrefetcher:
    """Decode and detect frames ahead in worker threads (a bounded queue of ``depth``).

    A sequencer thread decodes the frames in order (``seq.load(k)``) and hands each image to
    one of ``workers`` threads that run ``detect(image)`` (the first frame alone, before any
    other, so that whatever ``detect`` decides on the first image it sees is decided on the
    run's first frame); it takes their results in frame order, runs ``ahead`` on each, and
    hands them to the consumer through a queue holding at most ``depth`` frames. While the
    consumer waits (the queue is empty: detection is the slower side), up to ``workers``
    frames are detected at once, so that on a sequence whose detection is slower than the
    rest of a frame's work both cores detect; while frames wait in the queue, one. The
    threads stop at the next frame (or within 0.1 s when blocked on a full queue) once
    :meth:`close` is called, so an interrupted run never hangs on them.

    Parameters
    ----------
    seq : sequence
        Anything with ``load(k)``; only the sequencer thread calls it, in frame order.
    n : int
        One past the last frame.
    detect : callable
        Image to features, safe to call from several threads at once, the same image
        giving the same features (:meth:`eifslam.frontend.FrontEnd.detect`).
    depth : int >= 1
        Frames decoded and detected ahead of the consumer.
    start : int
        The first frame.
    ahead : callable, optional
        ``ahead(features)``: what the consumer would do next with a frame's features
        that depends on the frames before it only, called in frame order from one thread
        (:meth:`eifslam.frontend.FrontEnd.match_ahead`).
    workers : int >= 1
        Frames decoded and detected at once.

    Notes
    -----
    Iterating yields ``(k, item, wait_ms)`` in frame order: ``item`` is the features of
    frame ``k``; or its image when the detection raised an
    :class:`~eifslam.errors.EifslamError` (the consumer's own detection then raises the
    same error where the sequential loop would); or the :class:`ImageError` of its
    decoding (skip the frame). ``wait_ms`` is how long the consumer waited for it. Any
    other exception of a worker is re-raised in the consumer.
    """

    _DONE = object()

    def __init__(self, seq, n: int, detect: Callable[[Any], Any], depth: int = 2, start: int = 0,
                 ahead: Callable[[Any], Any] | None = None, workers: int = 1) -> None:
        self._seq, self._n, self._detect, self._start = seq, int(n), detect, int(start)
        self._ahead = ahead
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
        self._stop = threading.Event()
        self._pool = ThreadPoolExecutor(max_workers=max(1, int(workers)), thread_name_prefix="eifslam-detect")
        self._workers = max(1, int(workers))
        self._thread = threading.Thread(target=self._work, name="eifslam-prefetch", daemon=True)
        self._thread.start()

    def _put(self, item: tuple) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _detect_image(self, image: Any) -> tuple[Any, BaseException | None, bool]:
        """One frame's detection, in a worker: ``(item, error, detected)``, ``item`` and
        ``error`` as the consumer receives them (see the class's notes)."""
        if self._stop.is_set():
            return None, None, False
        try:
            return self._detect(image), None, True
        except EifslamError:
            return image, None, False  # the consumer's track() raises it again, in order
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer thread
            return None, exc, False

    def _load(self, k: int) -> Future:
        """Decode frame ``k`` here (frames are decoded in order, in one thread: a video is
        read sequentially) and hand its detection to a worker; a failed decoding is a
        result at once."""
        try:
            image = self._seq.load(k)
        except ImageError as exc:
            return _done((exc, None, False))
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer thread
            return _done((None, exc, False))
        return self._pool.submit(self._detect_image, image)

    def _result(self, future: Future) -> tuple[Any, BaseException | None, bool] | None:
        """A worker's result, or None once the prefetcher is closed."""
        while not self._stop.is_set():
            try:
                return future.result(timeout=0.1)
            except FutureTimeout:
                continue
        return None

    def _work(self) -> None:
        pending: deque[Future] = deque()
        submitted = self._start
        starved = False  # the queue was empty when the last frame was ready: the consumer waits
        try:
            for k in range(self._start, self._n):
                # the first frame alone; then up to ``workers`` frames in flight while the
                # consumer waits for frames (detection is the slower side), one otherwise
                # (more would take the cores from the consumer)
                while submitted < self._n and len(pending) < (self._workers if starved else 1):
                    pending.append(self._load(submitted))
                    submitted += 1
                got = self._result(pending.popleft())
                if got is None:
                    return
                item, error, detected = got
                if error is not None:
                    self._put((-1, None, error))
                    return
                if self._ahead is not None and detected:
                    # what the front end's match_ahead hands over (the same results
                    # wherever it is made)
                    item = self._ahead(item)
                starved = self._queue.qsize() == 0
                if not self._put((k, item, None)):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer thread
            self._put((-1, None, exc))
            return
        finally:
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._put((-1, self._DONE, None))

    def __iter__(self) -> Iterator[tuple[int, Any, float]]:
        while True:
            t0 = time.perf_counter()
            while True:
                try:
                    k, item, error = self._queue.get(timeout=0.1)
                    break
                except queue.Empty:
                    if not self._thread.is_alive() and self._queue.empty():
                        raise RuntimeError("the prefetch worker thread ended without a result") from None
            if error is not None:
                raise error
            if item is self._DONE:
                return
            yield k, item, (time.perf_counter() - t0) * 1e3

    def close(self, timeout: float = 2.0) -> None:
        """Stop the threads (each ends after the frame it is on) and wait for them up to
        ``timeout`` s."""
        self._stop.set()
        self._thread.join(timeout)
        self._pool.shutdown(wait=True, cancel_futures=True)

    @property
    def alive(self) -> bool:
        """Whether the sequencer thread is still running."""
        return self._thread.is_alive()


def _done(result: Any) -> Future:
    """A future that already holds ``result``."""
    f: Future = Future()
    f.set_result(result)
    return f


def run_sequence(seq, config: SlamConfig, max_frames: int | None = None, scale: tuple | None = None,
                 quiet: bool = False, on_frame: Callable[[TrackResult], None] | None = None, *,
                 slam: Slam | None = None, save_session: str | Path | None = None,
                 prefetch: int | None = None) -> RunResult:
    """Run SLAM over ``seq`` (an :mod:`eifslam.io` sequence, or anything with ``camera``,
    ``frames[k].timestamp``, ``load(k)`` and ``len``), then :meth:`Slam.finish`.

    Parameters
    ----------
    seq : sequence
    config : SlamConfig
    max_frames : int, optional
        Process at most this many frames.
    scale : ((kind, id), (kind, id), length), optional
        A known length between two states (:meth:`Slam.set_scale`), applied at the end.
    quiet : bool
        Hide the progress bar.
    on_frame : callable, optional
        Called with each frame's :class:`TrackResult` as it is tracked (e.g. to append
        the pose to a file, so that a killed run keeps it).
    slam : Slam, optional
        A loaded session to continue (:meth:`Slam.load`): its configuration is used
        (``config`` is ignored) and tracking starts at :func:`resume_index`; its camera
        must be the sequence's. ``max_frames`` then counts the new frames.
    save_session : path, optional
        Save the session there after the last frame, before :meth:`Slam.finish` (so that
        a resumed run finishes as the uninterrupted one would). A failure to save is
        reported in ``stopped``; the run's outputs are not lost.
    prefetch : int, optional
        Frames decoded and detected ahead in a worker thread (:class:`FramePrefetcher`);
        0 runs everything in this thread. Default: ``config.runtime.prefetch`` (of the
        session's config when ``slam`` is given). The results are the same either way.

    Returns
    -------
    RunResult
        Each frame's ``TrackResult.timings_ms`` also has ``load`` (decoding, in this
        thread) or ``wait`` (time this thread waited for the worker), milliseconds.

    Raises
    ------
    EifslamError
        When ``slam`` was made with another camera than the sequence's.
    """
    threads = (config if slam is None else slam.config).runtime.blas_threads
    with stop_requests(), blas_limit(threads):
        return _run(seq, config, max_frames, scale, quiet, on_frame, slam, save_session, prefetch)


@contextlib.contextmanager
def blas_limit(threads: int | None) -> Iterator[None]:
    """Hold the BLAS library to ``threads`` threads inside the block (threadpoolctl;
    ``None``: leave it as it is). See ``runtime.blas_threads``."""
    if threads is None:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=int(threads), user_api="blas"):
        yield


def _run(seq, config: SlamConfig, max_frames: int | None, scale: tuple | None, quiet: bool,
         on_frame: Callable[[TrackResult], None] | None, slam: Slam | None,
         save_session: str | Path | None, prefetch: int | None) -> RunResult:
    if slam is None:
        slam, start = Slam(seq.camera, config), 0
    else:
        if slam.camera != seq.camera:
            raise EifslamError(f"the session was made with another camera ({slam.camera}) than the "
                               f"source's ({seq.camera})")
        start = resume_index(seq, slam)
    n = len(seq) if max_frames is None else min(len(seq), start + max_frames)
    depth = int(slam.config.runtime.prefetch if prefetch is None else prefetch)
    with opencv_threads(opencv_thread_count(slam.config, depth)):
        return _track_all(seq, slam, start, n, depth, scale, quiet, on_frame, save_session)


def opencv_thread_count(config: SlamConfig, prefetch: int) -> int | None:
    """OpenCV's worker threads for a run (``runtime.opencv_threads`` with ``"auto"``
    resolved: 1 when detection runs in a prefetch worker, ``prefetch > 0``, and the
    tracking thread matches float descriptors (SIFT: one BLAS product, on one thread, or
    FLANN, which is serial), which leaves OpenCV no work to share; else None, OpenCV's
    own setting: binary descriptors are compared by OpenCV's parallel brute force)."""
    v = config.runtime.opencv_threads
    if v != "auto":
        return v
    return 1 if prefetch > 0 and config.float_descriptors else None


def detect_workers(prefetch: int) -> int:
    """Threads that detect at once in a run that prefetches ``prefetch`` frames: as many as
    the frames it may hold ahead and the machine's cores, whichever is fewer (OpenCV's
    detectors release the GIL, so they detect in parallel)."""
    return max(1, min(int(prefetch), os.cpu_count() or 1))


def _track_all(seq, slam: Slam, start: int, n: int, depth: int, scale: tuple | None, quiet: bool,
               on_frame: Callable[[TrackResult], None] | None,
               save_session: str | Path | None) -> RunResult:
    ahead = getattr(slam.frontend, "match_ahead", None)
    t0 = time.perf_counter()
    stopped = None
    bar = tqdm(total=max(n - start, 0), desc="eifslam", unit="frame", disable=quiet, file=sys.stderr)
    pre = FramePrefetcher(seq, n, slam.frontend.detect, depth, start, ahead=ahead, workers=detect_workers(depth)) \
        if depth > 0 and ahead is not None and n > start else None
    wait_key = "load" if pre is None else "wait"
    try:
        for k, item, ms in (sequential_frames(seq, n, start) if pre is None else pre):
            if _STOP.reason is not None:
                raise KeyboardInterrupt(_STOP.reason)
            bar.update(1)
            if isinstance(item, ImageError):  # a missing/corrupt image: report it, keep going
                tqdm.write(f"eifslam: skipping frame {k}: {item}", file=sys.stderr)
                continue
            res = slam.track(item, seq.frames[k].timestamp)
            res.timings_ms[wait_key] = ms
            bar.set_postfix(state=res.state.value, map=res.map_features)
            if on_frame is not None:
                on_frame(res)
    except KeyboardInterrupt as exc:  # Ctrl-C, or a stop request (raised between frames)
        stopped = f"interrupted ({exc})" if str(exc) else "interrupted"
    except EifslamError as exc:
        stopped = f"stopped at a failing frame: {exc}"
    except Exception as exc:  # noqa: BLE001 - a bug must not lose what was estimated
        stopped = f"stopped at a failing frame by an internal error: {type(exc).__name__}: {exc}"
    finally:
        if pre is not None:
            pre.close()
        bar.close()
    if stopped:
        print(f"eifslam: {stopped}; writing what was estimated so far", file=sys.stderr)
    if save_session is not None:
        try:
            slam.save(save_session)
        except EifslamError as exc:
            stopped = (stopped + "; " if stopped else "") + f"session not saved: {exc}"
            print(f"eifslam: session not saved: {exc}", file=sys.stderr)
    # after Ctrl-C the user wants out: no retrying of lost frames, only the mode's step
    fin = slam.finish(retry=stopped is None or stopped.startswith("stopped"),
                      images=seq.load if slam.config.experimental.wide_baseline else None)
    if fin.retry_error is not None:
        print(f"eifslam: retrying lost frames failed ({fin.retry_error})", file=sys.stderr)
    for msg in fin.failures:  # the filter's estimate is kept rather than the run lost
        stopped = (stopped + "; " if stopped else "") + msg
        print(f"eifslam: {msg}; writing the filter's estimate", file=sys.stderr)
    scale_error = None
    if scale is not None and slam.filter.layout.n_poses >= 2:
        a, b, length = scale
        try:
            slam.set_scale(a, b, length)
        except (EifslamError, KeyError) as exc:  # only wrong now the map is known: keep the run
            scale_error = f"--scale-distance not applied: {exc.args[0] if exc.args else exc}"
            print(f"eifslam: warning: {scale_error}; the outputs are unscaled", file=sys.stderr)
    return RunResult(slam, time.perf_counter() - t0, stopped, fin, scale_error)
