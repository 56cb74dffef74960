"""Does a measured pose agree with the estimate? The loop-closure consistency test.

A loop closure measures where the current camera is relative to an old place. Before it is
fused, the pose it implies for the current frame *k* is compared with the pose the estimate
predicts, both expressed relative to the old frame *j*:

``T_jk = T_j^-1 T_k``, with ``t_jk = R_j^T (p_k - p_j)`` and ``R_jk = R_j^T R_k``.

The innovation is ``[t_loop - t_pred, log(R_pred^T R_loop)]`` (6,), and its covariance is
the covariance of the predicted relative pose (from the joint marginal of poses *j* and *k*
in the estimate) plus the covariance of the loop's own pose. Its normalised squared norm is
chi-square with 6 degrees of freedom when the loop is right and the covariances are honest;
:func:`chi2_quantile` turns a false-alarm rate into the threshold.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2 as _chi2

from ..geometry.rotations import quat_conjugate, quat_log, quat_multiply, quat_to_rotmat, skew

Array = NDArray[np.float64]

__all__ = ["relative_pose_jacobians", "relative_pose_innovation", "pose_agreement", "rotation_agreement", "chi2_quantile"]


def chi2_quantile(dof: int, false_alarm: float) -> float:
    """The value a chi-square variable with ``dof`` degrees of freedom exceeds with
    probability ``false_alarm``."""
    return float(_chi2.isf(float(false_alarm), int(dof)))


def relative_pose_jacobians(p_j: Array, q_j: Array, p_k: Array, q_k: Array) -> tuple[Array, Array]:
    """Jacobians of the relative pose ``[t_jk, phi_jk]`` with respect to the two poses'
    tangent errors ``[dp, dtheta]`` (``dtheta`` right-multiplied, camera frame, as
    :func:`~eifslam.estimation.state.pose_tangent_covariance`).

    Parameters
    ----------
    p_j, p_k : (3,) camera centres, world frame.
    q_j, q_k : (4,) orientations ``q_wc`` ``[w, x, y, z]``.

    Returns
    -------
    J_j, J_k : (6, 6) each.
    """
    R_j, R_k = quat_to_rotmat(q_j), quat_to_rotmat(q_k)
    R = R_j.T @ R_k
    t = R_j.T @ (np.asarray(p_k, float) - np.asarray(p_j, float))
    J_j, J_k = np.zeros((6, 6)), np.zeros((6, 6))
    J_j[:3, :3], J_j[:3, 3:], J_j[3:, 3:] = -R_j.T, skew(t), -R.T
    J_k[:3, :3], J_k[3:, 3:] = R_j.T, np.eye(3)
    return J_j, J_k


def relative_pose_innovation(p_j: Array, q_j: Array, p_k: Array, q_k: Array, p_m: Array, q_m: Array) -> Array:
    """``[t_m - t_k, log(R_k^T R_m)]`` (6,): how the measured pose ``(p_m, q_m)`` of frame
    *k* differs from its estimate ``(p_k, q_k)``, relative to pose *j* (position in *j*'s
    camera frame, world units; rotation vector in *k*'s camera frame, rad)."""
    R_jT = quat_to_rotmat(q_j).T
    dt = R_jT @ (np.asarray(p_m, float) - np.asarray(p_k, float))
    dphi = quat_log(quat_multiply(quat_conjugate(np.asarray(q_k, float)), np.asarray(q_m, float)))
    return np.concatenate([dt, dphi])


def pose_agreement(p_j: Array, q_j: Array, p_k: Array, q_k: Array, C_jk: Array,
                   p_m: Array, q_m: Array, C_m: Array) -> tuple[float, Array]:
    """Normalised innovation squared of a measured pose of frame *k* against the estimate,
    relative to frame *j*.

    Parameters
    ----------
    p_j, q_j, p_k, q_k : the estimate's poses of frames *j* and *k* ((3,), (4,) ``q_wc``).
    C_jk : (12, 12) joint covariance of ``[dp_j, dtheta_j, dp_k, dtheta_k]``.
    p_m, q_m : the measured pose of frame *k*, in the same world frame.
    C_m : (6, 6) covariance of the measured pose's ``[dp, dtheta]``.

    Returns
    -------
    nis : float
        ``v^T S^-1 v``; ``inf`` when ``S`` is singular or not finite.
    v : (6,) the innovation (:func:`relative_pose_innovation`).
    """
    J_j, J_k = relative_pose_jacobians(p_j, q_j, p_k, q_k)
    J = np.concatenate([J_j, J_k], 1)
    S = J @ np.asarray(C_jk, float) @ J.T + J_k @ np.asarray(C_m, float) @ J_k.T
    v = relative_pose_innovation(p_j, q_j, p_k, q_k, p_m, q_m)
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(v))):
        return float("inf"), v
    try:
        return float(v @ np.linalg.solve(0.5 * (S + S.T), v)), v
    except np.linalg.LinAlgError:
        return float("inf"), v


def rotation_agreement(q_k: Array, q_m: Array, C_k: Array, C_m: Array) -> float:
    """Normalised innovation squared of a measured orientation ``q_m`` of frame *k* against
    its estimate ``q_k`` (``q_wc``, (4,)): ``phi^T (C_k + C_m)^-1 phi`` with ``phi =
    log(R_k^T R_m)`` (3,), rad, in *k*'s camera frame; ``C_k``, ``C_m`` (3, 3) the
    covariances of the two (same frame). ``inf`` when singular or not finite."""
    phi = quat_log(quat_multiply(quat_conjugate(np.asarray(q_k, float)), np.asarray(q_m, float)))
    S = np.asarray(C_k, float) + np.asarray(C_m, float)
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(phi))):
        return float("inf")
    try:
        return float(phi @ np.linalg.solve(0.5 * (S + S.T), phi))
    except np.linalg.LinAlgError:
        return float("inf")
