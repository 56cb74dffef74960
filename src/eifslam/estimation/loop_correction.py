"""Loop correction of the linearisation point before a loop is fused (pure NumPy).

A verified loop gives the current pose ``k`` in the frame of the old map (the PnP pose
on old map features). After a lap the filter's estimate of ``k`` is off by the drift (on
the loop world 3.8 degrees and about a metre after one lap), and the information ``I``,
``i`` was linearised along the drifted path. Fusing the loop's ``Zm`` there is one
Gauss-Newton step from a point where the models are not linear enough: on the loop world
it left 1.4 degrees of the 3.8 and bent the old map.

:func:`distribute_correction` moves the linearisation point first, as a pose graph with
one loop edge would (ORB-SLAM's loop correction, then essential-graph optimisation): the
poses between the matched frame ``j`` and ``k`` are corrected by a growing share of the
loop's error, by the distance travelled since ``j`` (uniform drift per metre, the optimum
of a chain of equally weighted edges to first order):

* rotation: pose ``i`` is rotated (in the world frame) by ``alpha_i`` times the rotation
  that takes ``R_k`` to the loop's ``R_k``;
* position: each step of the path from ``j`` is rotated by its pose's share of the
  rotation and re-integrated from ``p_j``; what is left at ``k`` is spread by ``alpha``.

Poses up to ``j`` do not move. Each map feature moves rigidly with the last pose that
observed it (a feature last seen at or before ``j`` does not move).

:func:`correct_loop` applies it to an :class:`~eifslam.estimation.filter.InformationFilter`
(the estimate only); the caller then fuses the loop and relinearises every stored
measurement at the corrected estimate (:func:`relinearise_all`, Gauss-Newton).
Nothing here changes ``I``: its sparsity pattern is the measurements'.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError
from .gauss_newton import gauss_newton
from ..geometry.rotations import quat_log, quat_multiply, quat_conjugate, quat_exp, quat_normalize, quat_to_rotmat

if TYPE_CHECKING:
    from .filter import InformationFilter

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["LoopCorrection", "correct_loop", "distribute_correction", "relinearise_all"]


@dataclass(frozen=True)
class LoopCorrection:
    """What :func:`correct_loop` moved.

    Attributes
    ----------
    poses, features : int
        States moved.
    rotation_deg : float
        Angle of the rotation correction at ``k``.
    translation : float
        Distance pose ``k`` moved (state units).
    """

    poses: int
    features: int
    rotation_deg: float
    translation: float


def distribute_correction(ids: IntArray, P: Array, Q: Array, j: int, k: int, p_k: Array, q_k: Array
                          ) -> tuple[Array, Array]:
    """Corrected poses after a loop that puts pose ``k`` at ``(p_k, q_k)``.

    Parameters
    ----------
    ids : (n,) frame ids of the poses, increasing.
    P, Q : (n, 3), (n, 4) their positions and unit quaternions ``q_wc`` ``[w, x, y, z]``.
    j, k : int
        The matched old frame and the current frame (``j < k``, both in ``ids``).
    p_k, q_k : the loop's pose of ``k``.

    Returns
    -------
    (n, 3), (n, 4)
        Positions and quaternions; rows with ``id <= j`` are unchanged, rows after ``k``
        follow ``k``'s correction.
    """
    ids = np.asarray(ids, np.int64)
    P, Q0 = np.asarray(P, float), np.asarray(Q, float)
    Q = quat_normalize(Q0)
    if not (j < k and np.any(ids == j) and np.any(ids == k)):
        raise EstimatorError(f"loop correction needs poses j < k in the state, got j={j}, k={k}")
    if not (np.all(np.isfinite(p_k)) and np.all(np.isfinite(q_k))):
        raise EstimatorError("loop correction: the loop's pose is not finite")
    ik = int(np.flatnonzero(ids == k)[0])
    chain = np.flatnonzero((ids >= j) & (ids <= k))  # j first, k last (ids increase)
    steps = np.linalg.norm(np.diff(P[chain], axis=0), axis=1)
    length = float(steps.sum())
    alpha = np.concatenate([[0.0], np.cumsum(steps)]) / length if length > 0 else \
        np.linspace(0.0, 1.0, len(chain))
    q_k = quat_normalize(np.asarray(q_k, float))
    omega = quat_log(quat_multiply(q_k, quat_conjugate(Q[ik])))  # world-frame rotation at k
    dq = quat_exp(alpha[:, None] * omega[None])  # (m, 4) each pose's share
    P2, Q2 = P.copy(), Q0.copy()
    Q2[chain] = quat_normalize(quat_multiply(dq, Q[chain]))
    # re-integrate the path with each step rotated by its end pose's share of the rotation
    Rd = quat_to_rotmat(dq)
    d = np.einsum("nij,nj->ni", Rd[1:], np.diff(P[chain], axis=0))
    Pc = P[chain[0]] + np.concatenate([np.zeros((1, 3)), np.cumsum(d, axis=0)])
    Pc += alpha[:, None] * (np.asarray(p_k, float) - Pc[-1])[None]
    P2[chain] = Pc
    after = ids > k  # poses placed after k (e.g. late): k's whole correction
    if after.any():
        R = quat_to_rotmat(dq[-1])
        P2[after] = (P[after] - P[ik]) @ R.T + P2[ik]
        Q2[after] = quat_normalize(quat_multiply(dq[-1][None], Q[after]))
    return P2, Q2


def correct_loop(filt: "InformationFilter", j: int, k: int, p_k: Array, q_k: Array) -> LoopCorrection:
    """Move the filter's estimate (poses and features) as :func:`distribute_correction`
    says; ``I`` and ``i`` are not changed. The filter must hold the complete estimate
    (:meth:`~eifslam.estimation.filter.InformationFilter.complete_estimate`)."""
    ids, P, Q = filt.poses()
    ids = np.asarray(ids, np.int64)
    order = np.argsort(ids, kind="stable")
    ids, P, Q = ids[order], P[order], Q[order]
    P2, Q2 = distribute_correction(ids, P, Q, j, k, p_k, q_k)
    moved = np.flatnonzero(ids > j)
    x = filt.x.copy()
    cols = filt.layout.pose_columns(ids[moved])  # (m, 7)
    x[cols] = np.concatenate([P2[moved], Q2[moved]], 1)
    # each feature with the last pose that observed it
    obs = filt.store.all_features()
    nf = 0
    if len(obs):
        fid = obs.feature
        srt = np.lexsort((obs.pose, fid))
        last = np.r_[fid[srt][1:] != fid[srt][:-1], True]
        feats, anchor = fid[srt][last], obs.pose[srt][last]
        sel = (anchor > j) & filt.layout.has_features(feats) & np.isin(anchor, ids)
        feats, anchor = feats[sel], anchor[sel]
        if len(feats):
            a = np.searchsorted(ids, anchor)
            R_old, R_new = quat_to_rotmat(Q[a]), quat_to_rotmat(Q2[a])
            fc = filt.layout.feature_columns(feats)  # (f, 3)
            Xc = np.einsum("nji,nj->ni", R_old, x[fc] - P[a])  # camera frame of the anchor
            x[fc] = np.einsum("nij,nj->ni", R_new, Xc) + P2[a]
            nf = len(feats)
    if not np.all(np.isfinite(x)):
        raise EstimatorError("loop correction produced non-finite values")
    ik = int(np.flatnonzero(ids == k)[0])
    rot = float(np.degrees(np.linalg.norm(quat_log(quat_multiply(Q2[ik], quat_conjugate(Q[ik]))))))
    filt.set_estimate(x)
    return LoopCorrection(len(moved), nf, rot, float(np.linalg.norm(P2[ik] - P[ik])))


def relinearise_all(filt: "InformationFilter", passes: int, tol: float = 1e-6) -> int:
    """Gauss-Newton passes (:func:`~eifslam.estimation.gauss_newton.gauss_newton`) over every
    stored measurement from the (corrected) estimate: each rebuilds ``I``, ``i`` at ``x`` (:meth:`~eifslam.estimation.filter.InformationFilter.relinearise`,
    paper III-E) and solves the whole state (the last pass by
    :meth:`~eifslam.estimation.filter.InformationFilter.recover_rebuilt`: in incremental
    mode a rebuild of the recovery window, which the next frame then uses as it is).

    Cheaper than :func:`~eifslam.estimation.smoothing.smooth` (no cost evaluations, no
    damping): after :func:`correct_loop` the estimate is near the optimum and plain
    Gauss-Newton converges. A pass whose solution is not finite is undone (the estimate
    before it is kept, with its information) and the passes stop.

    Parameters
    ----------
    filt : InformationFilter
    passes : int
        At most this many passes (>= 1).
    tol : float
        Stop once a pass changes no state entry by more than ``tol`` times the scale
        (``max(1, scale prior length)``).

    Returns
    -------
    int
        Passes kept.
    """
    def solve(n: int) -> None:
        # the last pass through a rebuild of the recovery window, valid afterwards (no
        # second rebuild at the next frame); the others by the full solve, which costs
        # less than a rebuild that keeps a loop's old place in the window
        filt.recover_rebuilt() if n == int(passes) - 1 else filt.recover()

    return gauss_newton(filt, passes, tol, solve)
