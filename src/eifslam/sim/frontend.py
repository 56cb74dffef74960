"""A front end that measures a synthetic scene: the system's Algorithm 1 on known answers.

:class:`SyntheticFrontEnd` has the methods :class:`eifslam.system.slam.Slam` calls on
:class:`eifslam.frontend.FrontEnd`, but its "images" are frames of a
:class:`~eifslam.sim.synthetic.SyntheticScene` and its measurements are simulated with
:class:`~eifslam.sim.synthetic.NoiseModel`. Fed to ``Slam(camera, config,
frontend=SyntheticFrontEnd(scene))``, the benchmarks and the back end's tests run the
same pose guessing, triangulation, gating and fusion as a run over images::

    fe = SyntheticFrontEnd(scene, seed=0)
    slam = Slam(scene.camera, fe.slam_config(), frontend=fe)
    for k in range(len(scene.positions)):
        slam.track(k)            # the "image" is the scene's frame index

Pure NumPy (no OpenCV): the scene's points are the tracks (track id = point index, the
same in every frame), so there is no matching; a point is visible or not.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError
from ..estimation.measurements import RelativePose
from ..frontend.results import FrameFeatures, FrameResult, Reason, RelativePoseResult
from ..frontend.twoview import median_parallax_deg
from ..geometry.rotations import quat_to_rotmat
from .synthetic import NoiseModel, _rng, SyntheticScene, relative_covariance, true_relative

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["SyntheticFrontEnd"]


class SyntheticFrontEnd:
    """Simulated ``Zm`` and ``ZR``/``ZT`` of a synthetic scene behind the front end's interface.

    The scene's points are split once, by a generator keyed by ``(seed, 0)``, into the
    relative-pose set ``Ωp`` and the map set ``Ωm`` (a point is in ``Ωm`` with probability
    ``map_fraction``). Every measurement is drawn by the scene's :class:`NoiseModel`, so it
    is the same however often it is asked for: pixel noise per (frame, point), relative-pose
    noise per ordered pair of frames (as :func:`~eifslam.sim.synthetic.simulate` draws for
    consecutive frames; with the same ``seed`` both give the same values).

    Parameters
    ----------
    scene : SyntheticScene
    seed : int
        Seed of the ``Ωp``/``Ωm`` split and of every noise draw.
    sigma_px : float
        Standard deviation of each pixel coordinate of ``Zm``, pixels.
    rel_sigma_rot, rel_sigma_dir : float
        Standard deviations of the relative pose's rotation (radians) and unit direction
        (see :func:`~eifslam.sim.synthetic.relative_covariance`).
    max_range : float
        Points further than this from the camera (scene units) are not seen.
    map_fraction : float in [0, 1]
        Share of the points in ``Ωm``; 1 puts every point in the map (as
        :func:`~eifslam.sim.synthetic.simulate` does), and the relative poses' parallax and
        point counts are then taken over the map points, as if ``Ωp`` shared them.
    min_common : int
        A relative pose needs at least this many points (of ``Ωp``) seen by both frames;
        fewer gives ``ok=False``, ``reason=Reason.TOO_FEW_COMMON``.
    min_parallax_deg : float
        A relative pose whose true median parallax is below this is refused
        (``Reason.NO_PARALLAX``), as the image front end refuses one; 0 (default) refuses
        none and leaves the parallax rules to the system.
    noise : bool
        False: exact measurements (their covariances are unchanged).

    Notes
    -----
    The ``image`` given to :meth:`add_frame` (and so to ``Slam.track``) is the index of a
    frame of the scene, an ``int``; frame ids (the system's) and scene indices are
    usually the same, but any scene frames may be fed in any order.
    """

    def __init__(self, scene: SyntheticScene, seed: int = 0, *, sigma_px: float = 1.0,
                 rel_sigma_rot: float = 1e-3, rel_sigma_dir: float = 2e-3, max_range: float = 12.0,
                 map_fraction: float = 0.5, min_common: int = 20, min_parallax_deg: float = 0.0,
                 noise: bool = True) -> None:
        if not 0.0 <= map_fraction <= 1.0:
            raise ValueError(f"map_fraction must be in [0, 1], got {map_fraction}")
        self.scene = scene
        self.camera = scene.camera
        self.model = NoiseModel(int(seed), float(sigma_px), relative_covariance(rel_sigma_rot, rel_sigma_dir),
                                bool(noise))
        self.max_range = float(max_range)
        self.min_common = int(min_common)
        self.min_parallax_deg = float(min_parallax_deg)
        M = len(scene.points)
        self.in_map: NDArray[np.bool_] = _rng(int(seed), 0).random(M) < map_fraction
        self._all_map = bool(self.in_map.all())
        self._frames: dict[int, FrameFeatures] = {}
        self._scene_index: dict[int, int] = {}
        self._seen = np.zeros(M, bool)  # points seen in any added frame

    # -- what the system asks -----------------------------------------------------------
    @property
    def sigma_px(self) -> float:
        """Pixel noise standard deviation of ``Zm``, pixels."""
        return self.model.sigma_px

    @property
    def frame_ids(self) -> list[int]:
        """Frame ids added so far, in order."""
        return list(self._frames)

    def scene_index(self, frame_id: int) -> int:
        """The scene frame that frame *frame_id* shows."""
        try:
            return self._scene_index[int(frame_id)]
        except KeyError:
            raise EstimatorError(f"frame {frame_id} is not in the front end") from None

    def add_frame(self, image: Any, frame_id: int) -> FrameResult:
        """Measure scene frame ``image`` (an int index) as frame *frame_id*.

        Returns
        -------
        FrameResult
            ``n_features`` points visible, ``n_matches`` of them seen in an earlier added
            frame, ``n_new_tracks`` the others; not ok (``Reason.NO_FEATURES``) when none
            is visible.

        Raises
        ------
        EstimatorError
            When ``frame_id`` was already added.
        ValueError
            When ``image`` is not a frame index of the scene.
        """
        t0 = time.perf_counter()
        fid = int(frame_id)
        if fid in self._frames:
            raise EstimatorError(f"frame {fid} was already added to the front end")
        if not isinstance(image, (int, np.integer)) or not 0 <= int(image) < len(self.scene.positions):
            raise ValueError(f"a synthetic front end's image is a scene frame index in "
                             f"[0, {len(self.scene.positions)}), got {image!r}")
        k = int(image)
        idx = np.flatnonzero(self.scene.visible(k, self.max_range))
        uv = self.model.pixels(self.scene, k, idx)
        self._frames[fid] = FrameFeatures(fid, uv, uv, idx.astype(np.int64), self.in_map[idx],
                                          np.full((len(idx), 3), 200, np.uint8))
        self._scene_index[fid] = k
        old = self._seen[idx]
        self._seen[idx] = True
        ok, reason = (True, Reason.OK) if len(idx) else (False, Reason.NO_FEATURES)
        return FrameResult(fid, ok, reason, len(idx), int(old.sum()), int((~old).sum()),
                           {"detect": 1e3 * (time.perf_counter() - t0), "match": 0.0})

    def frame(self, frame_id: int) -> FrameFeatures:
        """Every visible point of a frame (``Ωp`` and ``Ωm``), noisy pixels ``(N, 2)``."""
        self.scene_index(frame_id)
        return self._frames[int(frame_id)]

    def map_observations(self, frame_id: int, min_track_length: int = 1) -> tuple[IntArray, Array]:
        """``Zm`` of a frame: track ids ``(N,)`` of its visible ``Ωm`` points and their
        noisy pixels ``(N, 2)`` (``min_track_length`` is accepted for the interface and
        ignored: a scene point is a track from the start)."""
        ff = self.frame(frame_id)
        return ff.track_ids[ff.in_map], ff.uv[ff.in_map]

    def _common(self, i: int, j: int) -> IntArray:
        """Points (of ``Ωp``, or of the map when ``Ωp`` is empty) seen by frames *i* and *j*."""
        a, b = self.frame(i), self.frame(j)
        ids = np.intersect1d(a.track_ids, b.track_ids)
        return ids if self._all_map else ids[~self.in_map[ids]]

    def relative_pose(self, i: int, j: int) -> RelativePoseResult:
        """``ZR``/``ZT`` from frame *i* to frame *j* with the noise model's covariance.

        ``parallax_deg`` is the true median parallax of the common points (noise-free
        bearings, true rotation), so the system's parallax rules see the geometry; every
        common point counts as an inlier.
        """
        t0 = time.perf_counter()
        if int(i) == int(j):
            return RelativePoseResult(False, Reason.SAME_FRAME, None, timings_ms={"relative_pose": 0.0, "covariance": 0.0})
        ki, kj = self.scene_index(i), self.scene_index(j)
        ids = self._common(i, j)
        n = len(ids)
        par = self._parallax(ki, kj, ids) if n else 0.0
        reason = Reason.TOO_FEW_COMMON if n < self.min_common else \
            Reason.NO_PARALLAX if par < self.min_parallax_deg else Reason.OK
        rp = self.model.relative(self.scene, ki, kj) if not reason else None
        if rp is not None and (ki, kj) != (int(i), int(j)):  # scene indices -> frame ids
            rp = RelativePose(int(i), int(j), rp.q_ij, rp.t_ij, rp.cov)
        ms = {"relative_pose": 1e3 * (time.perf_counter() - t0), "covariance": 0.0}
        return RelativePoseResult(not reason, reason, rp, n_common=n, n_inliers=n if not reason else 0,
                                  parallax_deg=par, inlier_track_ids=ids if not reason else ids[:0],
                                  timings_ms=ms)

    def _parallax(self, ki: int, kj: int, ids: IntArray) -> float:
        """True median parallax, degrees, of points ``ids`` between scene frames."""
        sc = self.scene
        q, _ = true_relative(sc, ki, kj)
        bi = (sc.points[ids] - sc.positions[ki]) @ quat_to_rotmat(sc.quats[ki])
        bj = (sc.points[ids] - sc.positions[kj]) @ quat_to_rotmat(sc.quats[kj])
        bi /= np.linalg.norm(bi, axis=1, keepdims=True)
        bj /= np.linalg.norm(bj, axis=1, keepdims=True)
        return median_parallax_deg(quat_to_rotmat(q), bi, bj)

    def relocalise(self, frame_id: int, candidate_frame_ids) -> list[tuple[int, int]]:
        """``(candidate, points seen by both)`` for each candidate; nothing to merge, as a
        scene point keeps its track id in every frame."""
        out = []
        for c in candidate_frame_ids:
            c = int(c)
            ok = c != int(frame_id) and c in self._frames
            out.append((c, len(self._common(frame_id, c)) if ok else 0))
        return out

    def reobserve(self, frame_id: int, track_ids: IntArray, uv_predicted: Array, radius_px: float,
                  ratio: float | None = None) -> int:
        """Found again: none (every visible map point is already measured; tracking never
        loses a scene point). Returns 0."""
        self.scene_index(frame_id)
        return 0

    def forget(self, frame_id: int) -> None:
        """Nothing to drop (there are no descriptors)."""
        self.scene_index(frame_id)

    def release(self, frame_id: int) -> None:
        """Nothing to drop (there are no descriptors)."""
        self.scene_index(frame_id)

    # -- helpers for runs on the scene --------------------------------------------------
    def true_distance(self, i: int = 0, j: int = 1) -> float:
        """Distance between the centres of scene frames *i* and *j*, scene units."""
        return float(np.linalg.norm(self.scene.positions[j] - self.scene.positions[i]))

    def slam_config(self, base=None, **sections: dict[str, Any]):
        """A :class:`~eifslam.system.config.SlamConfig` matched to this simulation.

        ``frontend.sigma_px`` is the simulated pixel noise and ``tracking.scale_distance`` the
        true distance between scene frames 0 and 1 (the pair that initialises the map when
        ``experimental.init_map_features`` is 0: frame 1 initialises it whatever features it
        gives), so estimates compare with the truth
        directly; ``sections`` (e.g. ``mapping={"min_feature_parallax_deg": 3.0}``) are
        applied last.
        """
        from ..system.config import SlamConfig

        base = base or SlamConfig()
        cfg = base.replace(frontend={"sigma_px": self.sigma_px}, tracking={"scale_distance": self.true_distance(0, 1)},
                           experimental={"init_map_features": 0})
        return cfg.replace(**sections) if sections else cfg
