"""Drive a :class:`~eifslam.system.slam.Slam` over a sequence with a progress bar; lose nothing.

Ctrl-C, a stop request (:func:`request_stop`: the CLI's SIGTERM and SIGHUP) or a failing
frame stops the loop; :meth:`Slam.finish` then ends the run as the
configured mode says, and what was estimated so far is returned. Writing the outputs is
the caller's job (:func:`eifslam.evaluation.outputs.run_to_folder`).
"""

from __future__ import annotations

import contextlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from tqdm import tqdm

from ..errors import EifslamError, ImageError
from .config import SlamConfig
from .finishing import FinishReport
from .slam import Slam, TrackResult

__all__ = ["RunResult", "request_stop", "resume_index", "run_sequence", "stop_requests"]


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


def run_sequence(seq, config: SlamConfig, max_frames: int | None = None, scale: tuple | None = None,
                 quiet: bool = False, on_frame: Callable[[TrackResult], None] | None = None, *,
                 slam: Slam | None = None, save_session: str | Path | None = None) -> RunResult:
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

    Returns
    -------
    RunResult

    Raises
    ------
    EifslamError
        When ``slam`` was made with another camera than the sequence's.
    """
    with stop_requests():
        return _run(seq, config, max_frames, scale, quiet, on_frame, slam, save_session)


def _run(seq, config: SlamConfig, max_frames: int | None, scale: tuple | None, quiet: bool,
         on_frame: Callable[[TrackResult], None] | None, slam: Slam | None,
         save_session: str | Path | None) -> RunResult:
    if slam is None:
        slam, start = Slam(seq.camera, config), 0
    else:
        if slam.camera != seq.camera:
            raise EifslamError(f"the session was made with another camera ({slam.camera}) than the "
                               f"source's ({seq.camera})")
        start = resume_index(seq, slam)
    n = len(seq) if max_frames is None else min(len(seq), start + max_frames)
    t0 = time.perf_counter()
    stopped = None
    bar = tqdm(range(start, n), desc="eifslam", unit="frame", disable=quiet, file=sys.stderr)
    try:
        for k in bar:
            if _STOP.reason is not None:
                raise KeyboardInterrupt(_STOP.reason)
            try:
                image = seq.load(k)
            except ImageError as exc:  # a missing/corrupt image: report it, keep going
                tqdm.write(f"eifslam: skipping frame {k}: {exc}", file=sys.stderr)
                continue
            res = slam.track(image, seq.frames[k].timestamp)
            bar.set_postfix(state=res.state.value, map=res.map_features)
            if on_frame is not None:
                on_frame(res)
    except KeyboardInterrupt as exc:  # Ctrl-C, or a stop request (raised between frames)
        stopped = f"interrupted ({exc})" if str(exc) else "interrupted"
    except EifslamError as exc:
        stopped = f"stopped at a failing frame: {exc}"
    finally:
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
    fin = slam.finish(retry=stopped is None or stopped.startswith("stopped"))
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
