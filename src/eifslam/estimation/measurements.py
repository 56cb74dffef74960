"""Measurement types exchanged between the front end and the estimator (pure NumPy).

Poses are identified by integer **frame ids**, map features by integer **track ids**;
:class:`eifslam.estimation.state.StateLayout` maps ids to slices of the state vector.

* :class:`FeatureObservations` is a batch of ``Zm`` (paper eq. 3): undistorted pixels of
  map features (tracks in ``Ωm``) seen from poses.
* :class:`RelativePose` is one ``ZR`` + ``ZT`` pair (paper eqs. 4-6) between two poses,
  computed from the ``Ωp`` tracks, with the joint 5x5 covariance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..geometry.rotations import quat_normalize

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class FeatureObservations:
    """A batch of image measurements ``Zm`` of map features.

    Attributes
    ----------
    pose : (N,) int64
        Frame id of the observing pose.
    feature : (N,) int64
        Track id of the observed map feature.
    uv : (N, 2) float64
        Undistorted pixel coordinates.
    sigma_px : (N,) float64
        Standard deviation of each pixel coordinate (isotropic), pixels.
    """

    pose: IntArray
    feature: IntArray
    uv: Array
    sigma_px: Array

    @staticmethod
    def make(pose, feature, uv, sigma_px: float | Array = 1.0) -> "FeatureObservations":
        """Build a batch from array-likes, broadcasting a scalar ``sigma_px``."""
        pose = np.asarray(pose, dtype=np.int64).reshape(-1)
        feature = np.asarray(feature, dtype=np.int64).reshape(-1)
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        sig = np.broadcast_to(np.asarray(sigma_px, dtype=float), pose.shape).copy()
        if not (len(pose) == len(feature) == len(uv)):
            raise ValueError("pose, feature and uv must have the same length")
        if not (np.all(np.isfinite(uv)) and np.all(sig > 0) and np.all(np.isfinite(sig))):
            raise ValueError("feature observations must be finite with positive sigma")
        return FeatureObservations(pose, feature, uv, sig)

    @staticmethod
    def empty() -> "FeatureObservations":
        """A batch of zero measurements with the right dtypes and widths."""
        return FeatureObservations(
            np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
        )

    def __len__(self) -> int:
        return int(len(self.pose))

    def subset(self, mask) -> "FeatureObservations":
        """The measurements selected by a boolean mask or index array."""
        return FeatureObservations(self.pose[mask], self.feature[mask], self.uv[mask], self.sigma_px[mask])

    @staticmethod
    def concatenate(batches: "list[FeatureObservations]") -> "FeatureObservations":
        """Join batches into one."""
        if not batches:
            return FeatureObservations.empty()
        return FeatureObservations(
            np.concatenate([b.pose for b in batches]),
            np.concatenate([b.feature for b in batches]),
            np.concatenate([b.uv for b in batches]),
            np.concatenate([b.sigma_px for b in batches]),
        )


@dataclass(frozen=True)
class RelativePose:
    """Relative pose of camera *j* seen from camera *i*: ``ZR`` and ``ZT`` jointly.

    Attributes
    ----------
    i, j : int
        Frame ids of the reference pose and the other pose.
    q_ij : (4,) float64
        ``ZR``: unit quaternion ``[w, x, y, z]`` of ``R_ij = R_wi.T @ R_wj``.
    t_ij : (3,) float64
        Unit direction of ``R_wi.T @ (p_j - p_i)``, camera *j*'s centre in frame *i*
        (``ZT`` is ``[t_x / t_z, t_y / t_z]`` of it).
    cov : (5, 5) float64
        Joint covariance of the error ``[dtheta (3, rad), dt (2)]`` where the true
        rotation is ``R_ij @ Exp(dtheta)`` and the true direction is
        ``normalize(t_ij + tangent_basis(t_ij) @ dt)``.
    n_inliers : int
        Number of ``Ωp`` correspondences behind the estimate.
    """

    i: int
    j: int
    q_ij: Array
    t_ij: Array
    cov: Array
    n_inliers: int = 0

    def __post_init__(self) -> None:
        q = quat_normalize(np.asarray(self.q_ij, dtype=float))
        t = np.asarray(self.t_ij, dtype=float)
        nt = np.linalg.norm(t)
        cov = np.asarray(self.cov, dtype=float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t)) and nt > 0):
            raise ValueError("relative pose must be finite with a non-zero translation")
        if cov.shape != (5, 5) or not np.all(np.isfinite(cov)):
            raise ValueError("relative pose covariance must be a finite 5x5 matrix")
        object.__setattr__(self, "q_ij", q)
        object.__setattr__(self, "t_ij", t / nt)
        object.__setattr__(self, "cov", 0.5 * (cov + cov.T))


def pack_relative(rps: "list[RelativePose]") -> dict[str, NDArray]:
    """Relative poses as arrays (sessions): ``ij (R, 2)``, ``q (R, 4)``, ``t (R, 3)``,
    ``cov (R, 5, 5)``, ``inliers (R,)``."""
    return {
        "ij": np.array([[r.i, r.j] for r in rps], np.int64).reshape(-1, 2),
        "q": np.array([r.q_ij for r in rps], float).reshape(-1, 4),
        "t": np.array([r.t_ij for r in rps], float).reshape(-1, 3),
        "cov": np.array([r.cov for r in rps], float).reshape(-1, 5, 5),
        "inliers": np.array([r.n_inliers for r in rps], np.int64),
    }


def unpack_relative(d) -> "list[RelativePose]":
    """The relative poses of :func:`pack_relative`'s arrays, checked.

    Raises
    ------
    SessionError
        On a missing or malformed array.
    """
    from ..errors import SessionError
    from .statedict import take, take_ids

    ij = take(d, "ij", np.int64, (None, 2))
    n = len(ij)
    q, t = take(d, "q", np.float64, (n, 4)), take(d, "t", np.float64, (n, 3))
    cov, inl = take(d, "cov", np.float64, (n, 5, 5)), take_ids(d, "inliers", n)
    try:
        return [RelativePose(int(a), int(b), qq, tt, cc, int(m)) for (a, b), qq, tt, cc, m in zip(ij, q, t, cov, inl)]
    except ValueError as exc:
        raise SessionError(f"bad relative pose: {exc}") from None


def pack_features(obs: FeatureObservations) -> dict[str, NDArray]:
    """A batch of ``Zm`` as arrays (sessions): ``pose``, ``feature``, ``uv``, ``sigma_px``."""
    return {"pose": obs.pose, "feature": obs.feature, "uv": obs.uv, "sigma_px": obs.sigma_px}


def unpack_features(d) -> FeatureObservations:
    """The batch of :func:`pack_features`'s arrays, checked (:class:`SessionError`)."""
    from ..errors import SessionError
    from .statedict import take, take_ids

    pose = take_ids(d, "pose")
    n = len(pose)
    feature, uv, sig = take_ids(d, "feature", n), take(d, "uv", np.float64, (n, 2)), take(d, "sigma_px", np.float64, (n,))
    if n and not sig.min() > 0:
        raise SessionError("array 'sigma_px' holds a value that is not positive")
    return FeatureObservations(pose.copy(), feature.copy(), uv.copy(), sig.copy())


@dataclass
class MeasurementStore:
    """Every measurement fused so far, kept for smoothing (paper III-E).

    Attributes
    ----------
    features : list of FeatureObservations
        Batches of ``Zm`` in fusion order.
    relative : list of RelativePose
        ``ZR``/``ZT`` pairs in fusion order.
    """

    features: list[FeatureObservations] = field(default_factory=list)
    relative: list[RelativePose] = field(default_factory=list)

    def all_features(self) -> FeatureObservations:
        """Every stored ``Zm`` as one batch."""
        return FeatureObservations.concatenate(self.features)

    def remove_features(self, drop) -> int:
        """Take stored ``Zm`` out (a loop taken back): ``drop`` maps a batch to a boolean
        mask ``(N,)`` of the measurements to remove. Batches left empty are removed; the
        order of the rest is kept. Returns how many were removed."""
        kept, n = [], 0
        for b in self.features:
            m = np.asarray(drop(b), bool).reshape(-1)
            n += int(m.sum())
            if not m.all():
                kept.append(b if not m.any() else b.subset(~m))
        self.features = kept
        return n


@dataclass
class PriorStore:
    """Priors kept for relinearisation: gauge poses, the scale, weak priors at initial guesses."""

    pose: dict[int, tuple[Array, Array]] = field(default_factory=dict)  # fid -> (p, q)
    scale: tuple[int, int, float] | None = None  # (fid_a, fid_b, distance)
    weak: dict[tuple[str, int], Array] = field(default_factory=dict)  # (kind, id) -> initial guess
