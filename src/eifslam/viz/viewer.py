"""A live view of a run on rerun (``eifslam run SOURCE --viewer`` / ``--rerun-save FILE.rrd``).

:class:`RerunViewer` takes each frame's :class:`~eifslam.system.results.TrackResult` as it
is tracked and streams, on the ``frame`` timeline (the system's frame id):

=================================  ==========================================================
entity                             what
=================================  ==========================================================
``world/camera``                   the frame's pose (``Transform3D``) and the camera (``Pinhole``)
``world/camera/image``             the image
``world/camera/image/features``    its keypoints, by class (:data:`FEATURE_CLASSES`)
``world/trajectory``               positions of the tracked frames (one line strip); its last
                                   value (:meth:`RerunViewer.finish`) is the final trajectory,
                                   one position per row of ``trajectory.tum``
``world/ground_truth``             the ground truth, Sim(3)-aligned to the estimate (display only)
``world/map``                      map features with their colours
``world/keyframes``                positions of the poses in the state
``world/loops``                    one segment per loop closure, current frame to old frame
``loops``                          one text line per loop closure, as it is fused
``stats/*``                        map size and tracking milliseconds per frame (sent with the map)
=================================  ==========================================================

The stream costs the tracking little: the per-frame part is the image (JPEG-encoded where
it is decoded, in the runner's prefetch thread), its keypoints and the pose; the map, the
trajectory, the keyframes, the aligned ground truth and the per-frame figures are sent
every ``every`` keyframes (and at each loop closure). The viewer only reads the system:
it reads the filter's estimate as it stands (``filter.features()``, never
:meth:`Slam.map`, whose back substitution would change what tracking reads next), and
the ground truth it is given is drawn, never handed to the estimator.

The images reach the viewer through :meth:`RerunViewer.watch`, which wraps the source so
that each image it decodes (in the runner's prefetch thread or in the caller's) is kept
until its frame is shown; no image is decoded twice.
"""

from __future__ import annotations

import os
import sys
from collections import deque
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from ..errors import EifslamError
from ..geometry.camera import PinholeCamera
from ..io.trajectory import Trajectory
from ..system.results import TrackResult
from ..system.slam import Slam

Array = NDArray[np.float64]

__all__ = ["FEATURE_CLASSES", "RerunViewer", "classify_features", "import_rerun"]

#: keypoint classes of ``world/camera/image/features``: ``(class id, label, RGB)``
FEATURE_CLASSES = (
    (0, "map", (40, 200, 60)),  # its track is a map feature and the frame's pose predicts it (gate passed)
    (1, "tracked", (70, 150, 255)),  # extends a track of an earlier frame, not a map feature
    (2, "new", (255, 200, 0)),  # starts a track in this frame
    (3, "outlier", (235, 40, 40)),  # its track is a map feature, but the filter's gate refuses it
)
MAP, TRACKED, NEW, OUTLIER = (c[0] for c in FEATURE_CLASSES)

#: JPEG quality of the streamed images
JPEG_QUALITY = 85

#: the message for a missing rerun-sdk
MISSING = "the viewer needs rerun-sdk: pip install 'eifslam[viewer]'"


def import_rerun(spawn: bool = False):
    """The ``rerun`` module, or :class:`~eifslam.errors.EifslamError` with one line saying
    how to install it; with ``spawn``, also when the viewer cannot open a window (Linux
    without ``DISPLAY`` or ``WAYLAND_DISPLAY``)."""
    try:
        import rerun
    except ImportError:
        raise EifslamError(MISSING) from None
    if spawn and sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                           or os.environ.get("WAYLAND_DISPLAY")):
        raise EifslamError("the viewer needs a display (DISPLAY and WAYLAND_DISPLAY are not set); "
                           "record the run with --rerun-save FILE.rrd and open it where there is one")
    return rerun


class _SeenTracks:
    """Which track ids were seen in an earlier frame (a growing boolean array by id)."""

    def __init__(self) -> None:
        self._seen = np.zeros(1024, bool)

    def first_seen(self, ids: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Mask of the ids never seen before; all of ``ids`` are then marked seen."""
        ids = np.asarray(ids, np.int64)
        if not len(ids):
            return np.zeros(0, bool)
        top = int(ids.max())
        if top >= len(self._seen):
            grown = np.zeros(max(2 * len(self._seen), top + 1), bool)
            grown[: len(self._seen)] = self._seen
            self._seen = grown
        ok = ids >= 0
        new = np.ones(len(ids), bool)
        new[ok] = ~self._seen[ids[ok]]
        self._seen[ids[ok]] = True
        return new


def classify_features(slam: Slam, res: TrackResult, seen: _SeenTracks) -> tuple[Array, NDArray[np.uint8]]:
    """Keypoints of a frame just tracked and what became of them.

    Parameters
    ----------
    slam : Slam
        Right after :meth:`Slam.track` returned ``res``.
    res : TrackResult
    seen : _SeenTracks
        The tracks of the earlier frames (updated).

    Returns
    -------
    uv : (N, 2) float64
        Pixels as detected (with the lens distortion: where they are in the image).
    classes : (N,) uint8
        :data:`FEATURE_CLASSES` ids: ``map`` when the track is a map feature whose
        projection from the frame's pose passes the filter's gate (:meth:`Mapper.fits`),
        ``outlier`` when it does not, ``new`` when the track starts in this frame, else
        ``tracked``. Without a pose, map features are ``map``.
    """
    try:
        fr = slam.frontend.frame(res.frame_id)
    except EifslamError:  # a frame the front end did not keep
        return np.zeros((0, 2)), np.zeros(0, np.uint8)
    ids = np.asarray(fr.track_ids, np.int64)
    cls = np.full(len(ids), TRACKED, np.uint8)
    cls[seen.first_seen(ids)] = NEW
    layout = slam.filter.layout
    in_map = layout.has_features(ids) if len(ids) else np.zeros(0, bool)
    cls[in_map] = MAP
    if in_map.any() and res.position is not None:
        X = slam.filter.x[layout.feature_columns(ids[in_map])]
        n = len(X)
        ok = slam.mapper.fits(X, np.broadcast_to(res.position, (n, 3)), np.broadcast_to(res.quat_wxyz, (n, 4)),
                              np.asarray(fr.uv)[in_map])
        idx = np.flatnonzero(in_map)
        cls[idx[~ok]] = OUTLIER
    uv = np.asarray(fr.uv_raw if fr.uv_raw is not None else fr.uv, float).reshape(-1, 2)
    return uv, cls


class _ImageTap:
    """A source whose decoded images are also kept for the viewer (the last ``keep``),
    each as ``prepare`` makes it: called where the image is decoded (the runner's prefetch
    thread, which then also pays for the JPEG encoding).

    Everything but ``load`` is the wrapped source's."""

    def __init__(self, seq, prepare: Callable[[np.ndarray], Any], keep: int = 32) -> None:
        self._seq, self._prepare = seq, prepare
        self._images: deque = deque(maxlen=keep)

    def load(self, k: int, *args, **kwargs):
        img = self._seq.load(k, *args, **kwargs)
        try:
            kept = self._prepare(img)
        except Exception:  # noqa: BLE001 - an image the viewer cannot show is not shown; the run goes on
            kept = None
        self._images.append((self._seq.frames[k].timestamp, kept))
        return img

    def take(self, timestamp: float):
        """What was kept of the image of the frame of ``timestamp`` (None when nothing
        is); what was kept of the frames before it is dropped."""
        for i, (ts, img) in enumerate(list(self._images)):
            if ts == timestamp:
                for _ in range(i + 1):
                    self._images.popleft()
                return img
        return None

    def __len__(self) -> int:
        return len(self._seq)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._seq, name)


class RerunViewer:
    """Streams a run to the rerun viewer and/or an ``.rrd`` recording.

    Parameters
    ----------
    camera : PinholeCamera
    spawn : bool
        Start the rerun viewer and stream to it.
    save : path, optional
        Also (or only) record the stream into this ``.rrd`` file.
    every : int >= 1
        Keyframes between two updates of the map, trajectory, keyframes and ground truth.
    ground_truth : Trajectory, optional
        Drawn aligned (Sim(3), on the frames tracked so far) to the estimate; for display only.
    color_order : {"bgr", "rgb"}
        Channel order of 3-channel images (``frontend.color_order``).

    Raises
    ------
    EifslamError
        rerun-sdk is not installed, or neither ``spawn`` nor ``save`` is asked.

    Examples
    --------
    >>> viewer = RerunViewer(seq.camera, save="run.rrd")          # doctest: +SKIP
    >>> seq = viewer.watch(seq)                                   # doctest: +SKIP
    >>> run = run_sequence(seq, config, slam=slam, on_frame=viewer.on_frame(slam))  # doctest: +SKIP
    >>> viewer.finish(run.slam)                                   # doctest: +SKIP
    """

    def __init__(self, camera: PinholeCamera, *, spawn: bool = False, save: str | Path | None = None,
                 every: int = 10, ground_truth: Trajectory | None = None, color_order: str = "bgr") -> None:
        if not spawn and save is None:
            raise EifslamError("the viewer needs somewhere to stream: spawn the viewer or give a file to save")
        if int(every) < 1:
            raise EifslamError(f"the viewer's update interval must be >= 1 keyframe, got {every}")
        rr = self._rr = import_rerun(spawn)
        import rerun.blueprint as rrb

        self.camera, self.every, self.color_order = camera, int(every), color_order
        self.ground_truth = ground_truth
        self.rec = rr.RecordingStream("eifslam")
        blueprint = rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map and trajectory"),
            rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="image"),
                         rrb.TimeSeriesView(origin="stats", name="stats"),
                         rrb.TextLogView(origin="loops", name="loop closures"), row_shares=[3, 2, 1]),
            column_shares=[3, 2])
        try:
            if spawn:
                self.rec.spawn(connect=save is None, default_blueprint=blueprint)
            if spawn and save is not None:
                self.rec.set_sinks(rr.GrpcSink(), rr.FileSink(str(save)), default_blueprint=blueprint)
            elif save is not None:
                self.rec.save(str(save), default_blueprint=blueprint)
        except (OSError, RuntimeError) as exc:
            raise EifslamError(f"the rerun viewer could not be started or the recording opened: {exc}") from None
        self._tap: _ImageTap | None = None
        self._seen = _SeenTracks()
        self._positions: list[Array] = []  # positions of the tracked frames, as tracked
        self._times: list[float] = []  # and timestamps
        self._keyframes = 0
        self._loops = 0
        self._stats: list[tuple[int, float, float]] = []  # (frame, map features, tracking ms) not yet sent
        self._broken: str | None = None
        self._log_static()

    # -- set-up ---------------------------------------------------------------------
    def _log_static(self) -> None:
        rr, rec, cam = self._rr, self.rec, self.camera
        rec.log("world", rr.ViewCoordinates.RDF, static=True)  # the world is the first camera's frame
        rec.log("world/camera", rr.Pinhole(focal_length=[cam.fx, cam.fy], principal_point=[cam.cx, cam.cy],
                                           width=cam.width, height=cam.height, camera_xyz=rr.ViewCoordinates.RDF),
                static=True)
        rec.log("world/camera/image/features",
                rr.AnnotationContext([(i, label, color) for i, label, color in FEATURE_CLASSES]), static=True)

    def watch(self, seq):
        """``seq`` with its decoded images kept for the viewer: give the result to the runner."""
        self._tap = _ImageTap(seq, self._image)
        return self._tap

    # -- per frame ------------------------------------------------------------------
    def on_frame(self, slam: Slam) -> Callable[[TrackResult], None]:
        """The ``on_frame`` callback of :func:`~eifslam.system.runner.run_sequence` for the
        run of ``slam``. A failure of the viewer is reported once and ends the stream, never
        the run."""

        def show(res: TrackResult) -> None:
            if self._broken is not None:
                return
            try:
                image = self._tap.take(res.timestamp) if self._tap is not None else None
                self.log_frame(slam, res, image)
            except Exception as exc:  # noqa: BLE001 - a view must not cost the run
                self._broken = f"{type(exc).__name__}: {exc}"
                print(f"eifslam: warning: the viewer stopped streaming ({self._broken})", file=sys.stderr)

        return show

    def log_frame(self, slam: Slam, res: TrackResult, image=None) -> None:
        """Stream one tracked frame (``image``: the one given to :meth:`Slam.track`, as an
        array or as :meth:`_image` made it, or None)."""
        rr, rec = self._rr, self.rec
        rec.set_time("frame", sequence=res.frame_id)
        if image is not None:
            rec.log("world/camera/image", self._image(image) if isinstance(image, np.ndarray) else image)
        uv, cls = classify_features(slam, res, self._seen)
        rec.log("world/camera/image/features", rr.Points2D(uv, class_ids=cls, radii=2.0))
        self._stats.append((res.frame_id, float(res.map_features), float(res.timings_ms.get("total", 0.0))))
        if res.position is not None:
            q = res.quat_wxyz
            rec.log("world/camera", rr.Transform3D(translation=res.position,
                                                   quaternion=rr.Quaternion(xyzw=[q[1], q[2], q[3], q[0]])))
            self._positions.append(np.asarray(res.position, float))
            self._times.append(res.timestamp)
            if res.keyframe:
                self._keyframes += 1
        update = res.keyframe and res.position is not None and self._keyframes % self.every == 0
        closures = slam.loops.closures
        if len(closures) > self._loops:
            for c in closures[self._loops:]:
                rec.log("loops", rr.TextLog(f"frame {c.frame} closed a loop with frame {c.matched_frame} "
                                            f"({c.inliers} inliers, correction {c.correction_m:.3g})"))
            self._loops = len(closures)
            update = True
        if update:
            self._log_state(slam, np.array(self._positions).reshape(-1, 3), np.array(self._times), final=False)

    def _image(self, image: np.ndarray):
        """The image for rerun: 8-bit images as JPEG (about a tenth of the raw size, 1 ms
        for 640x480), others raw. Safe to call from the runner's prefetch thread."""
        import cv2

        rr = self._rr
        if image.ndim == 3 and image.shape[2] == 4:
            image = image[:, :, :3]
        color = image.ndim == 3 and image.shape[2] == 3
        if image.dtype == np.uint8 and (image.ndim == 2 or color):
            bgr = image if not color or self.color_order == "bgr" else image[:, :, ::-1]
            ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(bgr), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if ok:
                return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")
        if color:
            return rr.Image(image, color_model="BGR" if self.color_order == "bgr" else "RGB")
        return rr.Image(image, color_model="L")

    # -- every few keyframes, and at the end ---------------------------------------
    def _log_state(self, slam: Slam, P: Array, t: Array, final: bool) -> None:
        """The trajectory ``P (N, 3)`` at times ``t (N,)``, the map, keyframes, loops and
        the ground truth aligned to ``P``."""
        rr, rec = self._rr, self.rec
        if self._stats:  # the per-frame figures since the last update, in one message each
            frames, features, ms = (np.array(c) for c in zip(*self._stats))
            self._stats = []
            index = [rr.TimeColumn("frame", sequence=frames)]
            rec.send_columns("stats/map_features", indexes=index, columns=rr.Scalars.columns(scalars=features))
            rec.send_columns("stats/track_ms", indexes=index, columns=rr.Scalars.columns(scalars=ms))
        rec.log("world/trajectory", rr.LineStrips3D([P], colors=[(255, 120, 0)], radii=rr.Radius.ui_points(2.0)))
        if final:
            ids, X, colors = slam.map()
        else:  # the estimate as it stands (no back substitution: see the module's notes)
            ids, X = slam.filter.features()
            colors = slam.mapper.colors(ids)
        rec.log("world/map", rr.Points3D(X, colors=colors, radii=rr.Radius.ui_points(1.5)))
        _, KP, _ = slam.filter.poses()
        rec.log("world/keyframes", rr.Points3D(KP, colors=[(255, 255, 255)], radii=rr.Radius.ui_points(3.0)))
        segments = []
        for c in slam.loops.closures:
            a, b = self._position(slam, c.frame), self._position(slam, c.matched_frame)
            if a is not None and b is not None:
                segments.append([a, b])
        if segments:
            rec.log("world/loops", rr.LineStrips3D(segments, colors=[(255, 0, 255)], radii=rr.Radius.ui_points(2.0)))
        G = self._aligned_ground_truth(P, t)
        if G is not None:
            rec.log("world/ground_truth", rr.LineStrips3D([G], colors=[(160, 160, 160)],
                                                          radii=rr.Radius.ui_points(1.5)))

    @staticmethod
    def _position(slam: Slam, frame: int) -> Array | None:
        if slam.filter.layout.has_pose(frame):
            return slam.filter.pose(frame)[0]
        mp = slam.keyframes.get(frame)
        return None if mp is None else mp.p

    def _aligned_ground_truth(self, P: Array, t: Array) -> Array | None:
        """The ground truth's positions in the estimate's frame (Sim(3) on the frames
        associated by time, within 10 ms), or None when there are too few to align."""
        from ..evaluation.metrics import EvaluationError, align_sim3

        gt = self.ground_truth
        if gt is None or len(P) < 3 or len(gt) < 3:
            return None
        order = np.argsort(gt.timestamps)
        ts = gt.timestamps[order]
        j = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)
        j = np.where(np.abs(ts[j - 1] - t) < np.abs(ts[j] - t), j - 1, j)
        ok = np.abs(ts[j] - t) < 0.01
        if ok.sum() < 3:
            return None
        G = gt.positions[order]
        try:
            sim = align_sim3(G[j[ok]], P[ok])
        except EvaluationError:
            return None
        return sim.apply(G)

    def finish(self, slam: Slam) -> None:
        """Stream the final estimate (after :meth:`Slam.finish`): ``world/trajectory`` then
        holds :meth:`Slam.trajectory`, one position per row of ``trajectory.tum``; the map
        is :meth:`Slam.map`. Logged on the ``frame`` timeline one past the last frame; the
        recording is then flushed."""
        if self._broken is None:
            try:
                t, P, _ = slam.trajectory()
                self.rec.set_time("frame", sequence=slam.n_frames)
                self._log_state(slam, P, t, final=True)
            except Exception as exc:  # noqa: BLE001 - a view must not cost the run's outputs
                print(f"eifslam: warning: the viewer could not show the final estimate ({exc})", file=sys.stderr)
        self.close()

    def close(self) -> None:
        """Flush the stream and close the recording (a viewer that cannot be reached is a
        warning: the run's outputs are written by then)."""
        try:
            self.rec.flush(timeout_sec=10.0)
        except RuntimeError as exc:
            print(f"eifslam: warning: the viewer did not receive the whole stream ({exc})", file=sys.stderr)
        finally:
            self.rec.disconnect()
