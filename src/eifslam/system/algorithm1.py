"""Algorithm 1 of Wang & Dissanayake (2010): the sequential fusion of one keyframe.

:func:`algorithm1` is the whole update of the state for one image, its body the paper's
five steps in the paper's order, one call each:

1. a known pose and the relative pose ``ZR``/``ZT`` between it and the new pose ``Pk``;
2. the initial guess of the new pose, by triangulation from that pose and old features;
3. initial guesses of new features, by triangulation from ``Pk`` and old poses;
4. zeros in the information matrix ``I`` and vector ``i`` for the new pose and features;
5. every measurement of the image fused by the EIF (eq. 8), then the state recovered (eq. 9).

The policy around the steps lives in the named helpers below it: which linearisation
point the new pose gets and when the map contradicts the relative pose
(:func:`initial_pose`, :func:`pose_from_reference`, :func:`agrees`), when a ``ZR``/``ZT``
is fused (:func:`relative_ok`). Which known pose is the reference is the
:class:`~.tracking.Tracker`'s choice (:meth:`~.tracking.Tracker.find_reference`: recent
poses first, older ones after relocalisation); without any, a frame is placed on the known
map alone (:class:`OnMap`: the same steps without ``ZR``/``ZT``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError
from ..estimation.initialisation import pose_from_relative
from ..estimation.localisation import localise_pose, map_pose_sensitivity
from ..estimation.measurements import RelativePose
from ..frontend.results import RelativePoseResult
from ..geometry.camera import PinholeCamera
from ..geometry.rotations import quat_conjugate, quat_left_matrix, quat_log, quat_multiply, quat_normalize
from .mapping import project

if TYPE_CHECKING:
    from .tracking import Tracker

Array = NDArray[np.float64]

__all__ = ["OnMap", "Placement", "PoseGuess", "agrees", "algorithm1", "initial_pose", "inlier_fraction",
           "map_pose_uncertainty", "pose_from_reference", "pose_on_map", "relative_gate_statistic", "relative_ok"]


@dataclass(frozen=True)
class OnMap:
    """A frame to place on the known map alone: Algorithm 1 without ``ZR``/``ZT`` (no
    usable baseline to a known pose).

    Attributes
    ----------
    guess : tuple of (3,), (4,) arrays, optional
        Position and ``q_wc`` the localisation starts from (default: the nearest known pose).
    min_features : int, optional
        Fewest known map features the frame must see (default:
        ``TrackingConfig.min_map_features``).
    """

    guess: tuple[Array, Array] | None = None
    min_features: int | None = None


@dataclass(frozen=True)
class PoseGuess:
    """Step 2: the initial guess of the new pose (its linearisation point).

    Attributes
    ----------
    p : (3,) camera centre, world frame.
    q : (4,) orientation ``q_wc`` (the state holds it normalised).
    step : float
        Distance from the reference pose the guess took (0: none; the scale guess of the
        next frame).
    relative_usable : bool
        False when the known map contradicts the relative pose: its ``ZR``/``ZT`` is not fused.
    refined : bool
        The guess is the map's pose, fitting most known features: the ``ZR``/``ZT`` is then
        tested against it (:func:`relative_ok`).
    sets_scale : bool
        The first step of the map: the scale prior is set on it.
    """

    p: Array
    q: Array
    step: float = 0.0
    relative_usable: bool = False
    refined: bool = False
    sets_scale: bool = False


@dataclass(frozen=True)
class Placement:
    """What :func:`algorithm1` did with a keyframe.

    Attributes
    ----------
    frame_id : int
    reference : int or None
        The known pose of the ``ZR``/``ZT`` (None: placed on the map alone).
    relative_fused : bool
        Whether the ``ZR``/``ZT`` was fused (False: none, or refused by :func:`relative_ok`).
    new_features : int
        Map features added by step 3.
    """

    frame_id: int
    reference: int | None
    relative_fused: bool
    new_features: int


def algorithm1(k: int, reference: RelativePoseResult | OnMap, tracker: Tracker, timings: dict[str, float],
               recover: bool = True) -> Placement | None:
    """Sequential fusion of keyframe *k* (Wang & Dissanayake 2010, Algorithm 1).

    Parameters
    ----------
    k : int
        The frame (known to the front end, not yet a pose of the state).
    reference : RelativePoseResult or OnMap
        The relative pose to a known pose the tracker chose (step 1), or :class:`OnMap`.
    tracker : Tracker
        The camera, settings, front end, back end and mapper, and what tracking keeps
        between frames (the last step length, the refused relative poses).
    timings : dict
        Receives ``init`` (steps 1-4), ``fuse`` (step 5) and ``recover``, milliseconds.
    recover : bool
        False: fuse without the recovery (the caller recovers once after several frames).

    Returns
    -------
    Placement or None
        None when the frame cannot be placed on the map alone (nothing changed).

    Raises
    ------
    EstimatorError
        When the initial guess of the pose is not finite, or the recovery fails.
    """
    backend, mapper = tracker.filter, tracker.mapper
    t0 = time.perf_counter()
    zr_zt = relative_measurement(reference)                              # 1. relative pose with a known pose
    guess = initial_pose(k, zr_zt, reference, tracker)                   # 2. initial guess of the new pose
    if guess is None:
        return None
    mapper.reobserve(k, guess.p, guess.q)                                #    lost map features found again
    ids, uv = mapper.record_observations(k)                              #    the image's Zm, kept per track
    new = mapper.triangulate_new(k, ids, uv, guess.p, guess.q)           # 3. initial guesses of new features
    backend.add_pose(k, guess.p, guess.q)                                # 4. zeros in I and i: the new pose
    if guess.sets_scale:                                                 #    (the first step fixes the scale)
        backend.set_scale(zr_zt.i, k, tracker.config.tracking.scale_distance)
    tracker.remember_step(guess.step)
    backend.add_features(new.ids, new.X)                                 #    and the new features
    t1 = time.perf_counter()
    fused = relative_ok(zr_zt, guess, tracker)                           # 5. fuse every measurement:
    if fused:
        backend.fuse_relative([zr_zt])                                   #    ZR and ZT jointly,
    elif zr_zt is not None:
        tracker.rejected_relative.append(zr_zt)
    mapper.fuse_zm(new.zm)                                               #    every Zm of the image
    t2 = time.perf_counter()
    if recover:
        mapper.recover()                                                 #    and the state (eq. 9)
    t3 = time.perf_counter()
    timings.update(init=1e3 * (t1 - t0), fuse=1e3 * (t2 - t1), recover=1e3 * (t3 - t2))
    return Placement(k, None if zr_zt is None else zr_zt.i, fused, len(new.ids))


# -- step 1 ------------------------------------------------------------------------------
def relative_measurement(reference: RelativePoseResult | OnMap) -> RelativePose | None:
    """The ``ZR``/``ZT`` of step 1 (None on the map alone)."""
    return None if isinstance(reference, OnMap) else reference.measurement


# -- step 2 ------------------------------------------------------------------------------
def initial_pose(k: int, zr_zt: RelativePose | None, reference: RelativePoseResult | OnMap,
                 tracker: Tracker) -> PoseGuess | None:
    """Step 2: the initial guess of pose *k*, from the relative pose
    (:func:`pose_from_reference`) or from the known map alone (:func:`pose_on_map`; None
    when it cannot place the frame).

    Raises
    ------
    EstimatorError
        When the guess is not finite.
    """
    guess = pose_on_map(k, reference, tracker) if zr_zt is None else pose_from_reference(k, zr_zt, tracker)
    if guess is not None and not (np.all(np.isfinite(guess.p)) and np.all(np.isfinite(guess.q))):
        raise EstimatorError(f"initial guess of pose {k} is not finite")
    return guess


def pose_from_reference(k: int, zr_zt: RelativePose, tracker: Tracker) -> PoseGuess:
    """Step 2 with a relative pose: orientation from ``ZR``, centre along ``ZT`` at the
    step length that puts known map features on their rays
    (:func:`~eifslam.estimation.initialisation.pose_from_relative`), then, where the frame
    sees ``TrackingConfig.min_map_features`` known features, refined on the known map
    (:func:`~eifslam.estimation.localisation.localise_pose`), a better linearisation point:

    - the map's pose agrees with the relative pose (:func:`agrees`): the map's pose;
    - it disagrees and fits ``contradiction_ratio`` times more features
      (:func:`inlier_fraction`): the map's pose, and the ``ZR``/``ZT`` is not fused (a
      wrong five-point solution would wreck the estimate);
    - it disagrees but fits ``map_inlier_fraction`` of the features (on a short baseline
      both guesses fit the map): the map's pose, and :func:`relative_ok` decides on the
      ``ZR``/``ZT``.

    When the map does not converge from the relative pose's guess, it is localised from
    the nearest known pose, as a frame without a relative pose.
    """
    filt, cfg, camera = tracker.filter, tracker.config, tracker.camera
    known, Xk, uvk, map_cov, _ = tracker.known_map(k)
    p_i, q_i = filt.pose(zr_zt.i)
    first_step = filt.layout.n_poses == 1
    p_k, q_k, step = pose_from_relative(p_i, q_i, zr_zt, camera, Xk, uvk,
                                        default_step=cfg.tracking.scale_distance if first_step
                                        else tracker.last_step)
    use_relative, refined = True, False
    if known.sum() >= cfg.tracking.min_map_features:
        sol = localise_pose(camera, p_k, q_k, Xk, uvk, X_cov=map_cov)
        if sol is None:
            p0, q0 = filt.pose(tracker.nearest_known(k)[0])
            sol = localise_pose(camera, p0, q0, Xk, uvk, X_cov=map_cov)
        frac = sol[2].mean() if sol is not None else 0.0
        if sol is not None and agrees(p_i, p_k, q_k, sol, max_rot_deg=cfg.tracking.agree_rotation_deg,
                                      max_dir_deg=cfg.tracking.agree_direction_deg):
            p_k, q_k, refined = sol[0], sol[1], frac >= cfg.tracking.map_inlier_fraction
        elif sol is not None and frac > cfg.tracking.contradiction_ratio * inlier_fraction(
                camera, p_k, q_k, Xk, uvk, cfg.tracking.inlier_radius_px):
            p_k, q_k, use_relative = sol[0], sol[1], False
        elif sol is not None and frac >= cfg.tracking.map_inlier_fraction:
            p_k, q_k, refined = sol[0], sol[1], True
    return PoseGuess(p_k, q_k, step, relative_usable=use_relative, refined=refined, sets_scale=first_step)


def pose_on_map(k: int, start: OnMap, tracker: Tracker) -> PoseGuess | None:
    """Step 2 without a relative pose: pose *k* localised on the ``Zm`` of known map
    features alone, from ``start.guess`` (default: the nearest known pose). None when the
    map has fewer than two poses, the frame sees fewer than ``start.min_features`` known
    features, or the localisation does not converge."""
    filt = tracker.filter
    if filt.layout.n_poses < 2 or filt.layout.n_features == 0:
        return None
    known, X, uv, map_cov, _ = tracker.known_map(k)
    n_min = tracker.config.tracking.min_map_features if start.min_features is None else int(start.min_features)
    if known.sum() < n_min:
        return None
    p0, q0 = filt.pose(tracker.nearest_known(k)[0]) if start.guess is None else start.guess
    sol = localise_pose(tracker.camera, p0, q0, X, uv, min_inliers=min(n_min, 12), X_cov=map_cov)
    return None if sol is None else PoseGuess(sol[0], sol[1])


def agrees(p_i: Array, p_k: Array, q_k: Array, sol, max_rot_deg: float, max_dir_deg: float) -> bool:
    """Whether a map-refined pose agrees with the relative-pose guess.

    Parameters
    ----------
    p_i : (3,) position of the reference pose.
    p_k, q_k : (3,), (4,) the relative-pose guess of the new pose.
    sol : tuple
        ``(p, q, inliers)`` from :func:`~eifslam.estimation.localisation.localise_pose`.
    max_rot_deg, max_dir_deg : float
        Largest rotation between the two, and largest angle between their step
        directions from ``p_i``, degrees.

    Returns
    -------
    bool
        Rotation and direction within bounds and most known features fit; a refinement
        that disagrees was pulled away by bad matches.
    """
    p, q, inl = sol
    rot = np.degrees(np.linalg.norm(quat_log(quat_multiply(quat_conjugate(q_k), q))))
    a, b = p_k - p_i, p - p_i
    cosang = float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))
    return bool(rot <= max_rot_deg and cosang >= np.cos(np.radians(max_dir_deg)) and inl.mean() >= 0.5)


def inlier_fraction(camera: PinholeCamera, p: Array, q: Array, X: Array, uv: Array, px: float) -> float:
    """Fraction of known features ``X`` (N, 3) that pose ``(p, q)`` projects within ``px``
    pixels of their measurements ``uv`` (N, 2)."""
    h, z = project(camera, p, q, X)
    return float(np.mean((z > 0) & (np.linalg.norm(uv - h, axis=1) < px)))


# -- step 5 ------------------------------------------------------------------------------
def relative_ok(zr_zt: RelativePose | None, guess: PoseGuess, tracker: Tracker) -> bool:
    """Whether step 5 fuses the ``ZR``/``ZT``: there is one, the map did not contradict it
    (:func:`pose_from_reference`), and, when the new pose was refined on the map, its
    normalised innovation squared against its innovation covariance at the pose the map
    supports is within ``ExperimentalConfig.relative_gate_chi2``
    (:func:`relative_gate_statistic`; the new pose must be in the state)."""
    if zr_zt is None or not guess.relative_usable:
        return False
    chi2 = tracker.config.experimental.relative_gate_chi2
    if not guess.refined or chi2 is None:
        return True
    return relative_gate_statistic(tracker.filter, zr_zt, map_pose_uncertainty(zr_zt.j, tracker)) <= chi2


def map_pose_uncertainty(k: int, tracker: Tracker) -> tuple[NDArray[np.int64], Array, Array] | None:
    """How pose *k*, at its guess localised on the known map (in the state, not fused
    yet), is uncertain: ``(ids (F,), A (6, 3F), C (6, 6))`` with the pose's error ``[dp,
    dtheta] = A dX + e``, ``dX`` the errors of the map features ``ids`` it fits and ``e``
    independent of the map with covariance ``C``
    (:func:`~eifslam.estimation.localisation.map_pose_sensitivity`); None when the frame
    fits too few of them."""
    filt, cfg = tracker.filter, tracker.config
    _, X, uv, _, ids = tracker.known_map(k)
    p, q = filt.pose(k)
    h, z = project(tracker.camera, p, q, X)
    inl = (z > filt.config.min_depth) & (np.linalg.norm(uv - h, axis=1) < cfg.tracking.inlier_radius_px)
    out = map_pose_sensitivity(tracker.camera, p, q, X[inl], cfg.zm_sigma_px)
    return None if out is None else (ids[inl], out[1], out[0])


def relative_gate_statistic(filt, rp: RelativePose,
                            pose_j: tuple[NDArray[np.int64], Array, Array] | None = None) -> float:
    """Normalised innovation squared of a ``ZR``/``ZT`` (5 DOF) at the filter's current
    estimate of its two poses, against its innovation covariance ``S = Q + J P J^T``.

    ``Q`` is the measurement's own covariance; ``P`` the joint covariance of pose ``i`` (a
    state of the recovery window) and pose ``j`` at a guess localised on the map
    (``pose_j``, :func:`map_pose_uncertainty`): ``J P J^T = G P_(i, X) G^T + J_j C J_j^T``
    with ``G = [J_i, J_j A]`` over pose ``i`` and the map features pose ``j`` fits
    (:meth:`InformationFilter.propagate`, so that the correlation of pose ``i`` with
    those features counts). Without ``pose_j``, or where the filter has no cheap
    covariance, the states count as exact (against ``Q`` alone).
    """
    idx, J, W, innov = filt.linearise_relative([rp])
    r = innov[0]
    if pose_j is None:
        return float(r @ W[0] @ r)
    ids, A, C = pose_j
    _, qj = filt.pose(rp.j)
    E = np.zeros((7, 6))  # [dp, dtheta] -> [dp, dq], dq = q ⊗ [0, dtheta / 2]
    E[:3, :3] = np.eye(3)
    E[3:, 3:] = 0.5 * quat_left_matrix(quat_normalize(qj))[:, 1:]
    Ji, Jj = J[0][:, :7], J[0][:, 7:] @ E
    S = np.linalg.inv(W[0]) + Jj @ C @ Jj.T
    G = np.concatenate([Ji, Jj @ A], 1)
    M = filt.propagate([rp.i], ids, G)
    if M is None:
        M = filt.feature_propagate(ids, Jj @ A)
    if np.all(np.isfinite(M)):
        S = S + M
    try:
        return float(r @ np.linalg.solve(S, r))
    except np.linalg.LinAlgError:
        return float(r @ W[0] @ r)
