"""Linearisation of every measurement kind at a given estimate (pure NumPy).

Both back ends consume the same linearised measurements: the information filter
(:class:`~eifslam.estimation.filter.InformationFilter`) adds ``J^T W J`` to ``I`` and
``J^T W (innov + J x)`` to ``i`` (paper eq. 8); the dense EKF
(:class:`~eifslam.baselines.ekf.DenseEKF`) applies the covariance update. Each function
here reads the state through a :class:`~eifslam.estimation.state.StateLayout` and an
estimate ``x`` and returns a :class:`Linearised` batch; none of them changes anything.

Kinds: ``Zm`` (:func:`features`), ``ZR``/``ZT`` (:func:`relative`), the gauge prior on a
pose (:func:`pose_prior`), the scale prior (:func:`scale_prior`), the ``|q|^2 = 1``
pseudo-measurement (:func:`quat_norm`) and the weak priors at initial guesses
(:func:`weak_prior`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError
from ..geometry import models
from ..geometry.camera import PinholeCamera
from .measurements import FeatureObservations, RelativePose
from .options import FilterConfig
from .gauss_newton import information_terms
from .state import StateLayout

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Linearised:
    """``N`` measurements linearised at ``x``: ``z ~ h(x0) + J (x - x0)`` with information ``W``.

    Attributes
    ----------
    idx : (N, k) int64
        State indices each measurement involves.
    J : (N, m, k) float64
        Jacobians of the predictions with respect to ``x[idx]``.
    W : (N, m, m) float64
        Information (inverse covariance) of each measurement.
    innov : (N, m) float64
        Innovation ``z - h(x)``.
    z : (N, m) float64 or None
        For a linear measurement (``h(x) = J x``, the priors): its value, so that
        ``innov + J x`` is taken as ``z`` exactly.
    """

    idx: IntArray
    J: Array
    W: Array
    innov: Array
    z: Array | None = None

    def __len__(self) -> int:
        return int(len(self.idx))

    def information(self, x: Array) -> tuple[Array, Array]:
        """``(J^T W J (N, k, k), J^T W (innov + J x[idx]) (N, k))``: paper eq. 8's terms."""
        rhs = self.z if self.z is not None else self.innov + np.einsum("nmk,nk->nm", self.J, x[self.idx])
        return information_terms(self.J, self.W, rhs)


def _direct(idx: IntArray, z: Array, x: Array, w: float) -> Linearised:
    """A prior ``x[idx] ~ N(z, I / w)`` on ``N`` blocks of ``k`` entries (``J = I``)."""
    N, k = idx.shape
    eye = np.broadcast_to(np.eye(k), (N, k, k))
    return Linearised(idx, eye, np.broadcast_to(w * np.eye(k), (N, k, k)).copy(), z - x[idx], z)


def pose_prior(layout: StateLayout, x: Array, frame_id: int, p: Array, q: Array, sigma: float) -> Linearised:
    """Strong prior ``[p, q] ~ N(z, sigma^2 I)`` on one pose (the gauge): ``N = 1``, ``k = 7``."""
    cols = layout.pose_columns([frame_id])  # (1, 7)
    return _direct(cols, np.concatenate([p, q])[None], x, 1.0 / sigma**2)


def weak_prior(cols: IntArray, X: Array, x: Array, sigma: float) -> Linearised:
    """Weak prior ``x[cols] ~ N(X, sigma^2 I)`` at initial guesses ``X (N, k)``."""
    return _direct(np.asarray(cols, np.int64), np.asarray(X, float), x, 1.0 / sigma**2)


def scale_prior(layout: StateLayout, x: Array, frame_a: int, frame_b: int, distance: float,
                rel_sigma: float) -> Linearised:
    """``|p_b - p_a| = distance`` with standard deviation ``rel_sigma * distance``."""
    ca = layout.pose_columns([frame_a])[:, :3]
    cb = layout.pose_columns([frame_b])[:, :3]
    h, Ja, Jb = models.distance_model(x[ca], x[cb])
    W = np.array([[[1.0 / (rel_sigma * distance) ** 2]]])
    return Linearised(np.concatenate([ca, cb], 1), np.concatenate([Ja, Jb], axis=2), W, (distance - h)[:, None])


def quat_norm(layout: StateLayout, x: Array, frame_ids, sigma: float) -> Linearised:
    """Pseudo-measurements ``|q|^2 = 1`` (standard deviation ``sigma``) of poses ``frame_ids``."""
    cols = layout.pose_columns(list(frame_ids))[:, 3:]
    h, J = models.quat_norm_model(x[cols])
    W = np.full((len(cols), 1, 1), 1.0 / sigma**2)
    return Linearised(cols, J, W, (1.0 - h)[:, None])


def features(layout: StateLayout, x: Array, camera: PinholeCamera, config: FilterConfig,
             obs: FeatureObservations, gate: bool = True):
    """Linearise ``Zm`` at ``x``.

    Returns
    -------
    ok : (N,) bool, usable (predicted depth above ``config.min_depth``, finite, inside
    the gate ``config.gate_chi2`` when ``gate``).
    idx : (N, 10) state indices ``[pose 7, feature 3]``; J : (N, 2, 10);
    W : (N, 2, 2) information (pixels^-2); innov : (N, 2) ``z - h(x)`` (pixels);
    chi2 : (N,) normalised innovation squared (``inf`` where not finite or behind the camera).
    """
    idx = np.concatenate([layout.pose_columns(obs.pose), layout.feature_columns(obs.feature)], 1)
    h, J, depth = feature_model_at(idx, x, camera)
    innov = obs.uv - h
    chi2 = np.sum(innov**2, 1) / obs.sigma_px**2
    ok = (depth > config.min_depth) & np.isfinite(chi2)
    chi2 = np.where(ok, chi2, np.inf)
    if gate and config.gate_chi2 is not None:
        ok &= chi2 <= config.gate_chi2
    W = np.eye(2)[None] / (obs.sigma_px**2)[:, None, None]
    return ok, idx, J, W, innov, chi2


def feature_model_at(idx: NDArray[np.int64], x: Array, camera: PinholeCamera) -> tuple[Array, Array, Array]:
    """The ``Zm`` model of stored state indices ``idx (N, 10)`` (``[pose 7, feature 3]``)
    at the estimate ``x``.

    Returns
    -------
    h : (N, 2) predicted pixels; J : (N, 2, 10) Jacobian; depth : (N,) depth in the camera.
    """
    c = camera
    h, Jp, Jf, depth = models.feature_model(x[idx[:, :3]], x[idx[:, 3:7]], x[idx[:, 7:]], c.fx, c.fy, c.cx, c.cy)
    return h, np.concatenate([Jp, Jf], 2), depth


MIN_FEATURE_CONDITION = 1e-12
"""Smallest ratio of the eigenvalues of a feature's 3x3 information block (weak prior
included) that :func:`constrained_features` accepts: below it the block is singular to
working precision (a Cholesky of it fails or amplifies rounding by more than 1e12)."""


def constrained_features(feature: IntArray, ok: NDArray[np.bool_], Jf: Array, W: Array,
                         weak_info: float) -> NDArray[np.bool_]:
    """Which ``Zm`` of a batch to fuse so that every feature's information block stays
    positive definite: a feature keeps its usable measurements only when at least two of
    them are usable and its block ``sum Jf^T W Jf + weak_info I`` has an eigenvalue ratio
    above :data:`MIN_FEATURE_CONDITION`; otherwise none of its measurements is fused (its
    weak prior holds it). Used when every stored measurement is relinearised at a new
    estimate, where a feature can have slid behind or onto one of its cameras.

    Parameters
    ----------
    feature : (N,) int64 feature id of each measurement.
    ok : (N,) bool, usable at the estimate (:func:`features`' ``ok``).
    Jf : (N, 2, 3) Jacobians with respect to the feature; W : (N, 2, 2) information.
    weak_info : float
        Information of the weak prior on each coordinate (``1 / weak_prior_sigma^2``).

    Returns
    -------
    (N,) bool
        ``ok`` and the feature kept.
    """
    feature = np.asarray(feature, np.int64)
    if len(feature) == 0:
        return np.asarray(ok, bool).copy()
    _, inv = np.unique(feature, return_inverse=True)
    F = int(inv.max()) + 1
    Jf = np.where(np.asarray(ok, bool)[:, None, None], Jf, 0.0)
    Jf = np.where(np.isfinite(Jf), Jf, 0.0)
    D = np.zeros((F, 3, 3))
    np.add.at(D, inv, np.swapaxes(Jf, 1, 2) @ W @ Jf)
    D += weak_info * np.eye(3)
    n = np.bincount(inv, weights=np.asarray(ok, float), minlength=F)
    ev = np.linalg.eigvalsh(D)
    good = (n >= 2) & np.all(np.isfinite(ev), 1) & (ev[:, 0] > MIN_FEATURE_CONDITION * ev[:, 2])
    return np.asarray(ok, bool) & good[inv]


#: Largest angle, degrees, between a measured translation direction and the optical axis
#: for which ``ZT`` takes the paper's form ``[x/z, y/z]``; beyond it the bearing form, which
#: stays regular as the direction turns sideways, where ``x/z`` and ``y/z`` blow up.
ZT_PAPER_MAX_ANGLE_DEG = 60.0


def zt_uses_paper(t: Array) -> NDArray[np.bool_]:
    """Which measured unit directions ``t (N, 3)`` use the paper's ``ZT`` form (within
    :data:`ZT_PAPER_MAX_ANGLE_DEG` of the optical axis); the others the bearing form."""
    return t[:, 2] >= np.cos(np.radians(ZT_PAPER_MAX_ANGLE_DEG))


def relative(layout: StateLayout, x: Array, config: FilterConfig, rps: list[RelativePose]):
    """Linearise ``ZR`` and ``ZT`` jointly at ``x``.

    Returns
    -------
    idx : (N, 14) state indices ``[pose i, pose j]``; J : (N, 5, 14);
    W : (N, 5, 5) information of the joint measurement; innov : (N, 5).
    """
    ci = layout.pose_columns([r.i for r in rps])
    cj = layout.pose_columns([r.j for r in rps])
    qm = np.stack([r.q_ij for r in rps])
    tm = np.stack([r.t_ij for r in rps])
    cov = np.stack([r.cov for r in rps])
    hR, JRi, JRj = models.rotation_model(x[ci[:, 3:]], x[cj[:, 3:]], qm)
    N = len(rps)
    J = np.zeros((N, 5, 14))
    J[:, :3, 3:7], J[:, :3, 10:14] = JRi, JRj
    innov = np.zeros((N, 5))
    innov[:, :3] = -hR
    paper = zt_uses_paper(tm)
    hB, JBi, JBj = models.bearing_model(x[ci[:, :3]], x[ci[:, 3:]], x[cj[:, :3]], tm)
    T = np.broadcast_to(np.eye(5), (N, 5, 5)).copy()
    J[:, 3:, :7], J[:, 3:, 7:] = JBi, JBj
    innov[:, 3:] = -hB
    if np.any(paper):
        hT, JTi, JTj = models.translation_model(x[ci[paper, :3]], x[ci[paper, 3:]], x[cj[paper, :3]])
        zT, G = models.zt_paper_covariance(tm[paper])
        J[paper, 3:, :7], J[paper, 3:, 7:] = JTi, JTj
        innov[paper, 3:] = zT - hT
        T[paper, 3:, 3:] = G
    Q = T @ cov @ np.swapaxes(T, 1, 2)
    W = np.linalg.inv(Q)
    if not np.all(np.isfinite(W)) or not np.all(np.isfinite(innov)):
        raise EstimatorError("relative pose measurement produced a non-finite information")
    return np.concatenate([ci, cj], 1), J, 0.5 * (W + np.swapaxes(W, 1, 2)), innov


__all__ = ["Linearised", "features", "relative", "pose_prior", "scale_prior", "quat_norm", "weak_prior",
           "zt_uses_paper"]
