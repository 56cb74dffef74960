"""Observation models with analytic Jacobians, vectorised over measurements (pure NumPy).

Every model returns the predicted measurement ``h`` and its Jacobians with respect to the
*full* 7-vector of each pose involved (``[p (3), q (4)]``) and the 3-vector of a feature.
All models use the normalised quaternion ``q / |q|``, so they are invariant to the
quaternion's norm; the norm itself is fixed by a pseudo-measurement
(:func:`quat_norm_model`).

Models
------
``feature_model``      ``Zm`` (paper eqs. 2-3): pixel of a world point.
``feature_model_one_pose``  the same for many points seen from one pose (localisation).
``rotation_model``     ``ZR`` (paper eq. 4) as a 3-vector error ``2 vec(ZR^* ⊗ q_i^* ⊗ q_j)``
                       (zero at the measurement, equal to ``dtheta`` to first order), so the
                       rank-3 rotation uncertainty has a full-rank 3x3 covariance.
``translation_model``  ``ZT`` (paper eqs. 5-6): ``[x/z, y/z]`` of ``R_wi.T (p_j - p_i)``.
``bearing_model``      non-singular ``ZT``: tangent-plane components
                       ``B(t_meas).T @ X / |X|`` of the unit direction; zero at the
                       measurement, defined for sideways motion.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .rotations import quat_left_matrix, quat_right_matrix, tangent_basis, unit_quat_to_rotmat

Array = NDArray[np.float64]

_CONJ = np.diag([1.0, -1.0, -1.0, -1.0])


def _normalize_with_jacobian(q: Array) -> tuple[Array, Array]:
    """Unit quaternions ``(N, 4)`` and ``d(q/|q|)/dq`` ``(N, 4, 4)``."""
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    qn = q / n
    J = (np.eye(4) - qn[:, :, None] * qn[:, None, :]) / n[:, :, None]
    return qn, J


def rotate_inverse_with_jacobian(q: Array, d: Array) -> tuple[Array, Array]:
    """``R(q).T @ d`` and its Jacobian with respect to the (unnormalised) quaternion.

    Parameters
    ----------
    q : (N, 4) quaternions ``[w, x, y, z]`` (any non-zero norm).
    d : (N, 3) vectors in the world frame.

    Returns
    -------
    v : (N, 3) ``R(q/|q|).T @ d``.
    J_q : (N, 3, 4) ``dv/dq``.
    """
    qn, Jn = _normalize_with_jacobian(q)
    v, Jqn = _rotate_inverse_unit(qn, d)
    return v, Jqn @ Jn


def _rotate_inverse_unit(qn: Array, d: Array) -> tuple[Array, Array]:
    """``R(qn).T @ d`` ``(N, 3)`` and its Jacobian ``(N, 3, 4)`` with respect to the unit
    quaternion ``qn (N, 4)`` (before the normalisation's Jacobian), element by element."""
    w, u = qn[:, 0], qn[:, 1:]
    ud = np.sum(u * d, -1)
    uu = np.sum(u * u, -1)
    cross_ud = _cross(u, d)
    v = (w * w - uu)[:, None] * d + 2.0 * ud[:, None] * u - 2.0 * w[:, None] * cross_ud
    J = np.empty((len(qn), 3, 4))
    J[:, :, 0] = 2.0 * w[:, None] * d - 2.0 * cross_ud
    t1 = (-2.0 * d)[:, :, None] * u[:, None, :]  # -2 d u^T
    t3 = (2.0 * u)[:, :, None] * d[:, None, :]  # 2 u d^T
    dv_du = J[:, :, 1:]
    np.add(t1, t3, out=dv_du)
    ud2 = 2.0 * ud
    for i in range(3):
        dv_du[:, i, i] = (t1[:, i, i] + ud2) + t3[:, i, i]
    w2 = 2.0 * w
    wx, wy, wz = w2 * d[:, 0], w2 * d[:, 1], w2 * d[:, 2]  # + 2 w [d]x
    dv_du[:, 0, 1] -= wz
    dv_du[:, 0, 2] += wy
    dv_du[:, 1, 0] += wz
    dv_du[:, 1, 2] -= wx
    dv_du[:, 2, 0] -= wy
    dv_du[:, 2, 1] += wx
    return v, J


def _cross(a: Array, b: Array) -> Array:
    """``np.cross(a, b)`` of ``(N, 3)`` arrays, with the same arithmetic and less overhead."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    out[:, 0] = a1 * b2 - a2 * b1
    out[:, 1] = a2 * b0 - a0 * b2
    out[:, 2] = a0 * b1 - a1 * b0
    return out


def _zm(Xc: Array, Rt: Array, J_q: Array, fx: float, fy: float, cx: float, cy: float
        ) -> tuple[Array, Array, Array, Array]:
    """:func:`feature_model`'s outputs from the camera-frame points ``Xc (N, 3)``,
    ``R_cw`` (``(3, 3)`` or ``(N, 3, 3)``) and ``d Xc / dq`` ``(N, 3, 4)`` (a depth within
    1e-12 of zero taken as 1e-12 in the projection)."""
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
    h = np.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    P = np.zeros((len(z), 2, 3))
    P[:, 0, 0] = fx / zs
    P[:, 0, 2] = -fx * x / zs**2
    P[:, 1, 1] = fy / zs
    P[:, 1, 2] = -fy * y / zs**2
    J_feat = P @ Rt
    J_pose = np.concatenate([-J_feat, P @ J_q], axis=2)
    return h, J_pose, J_feat, z


def feature_model(
    p: Array, q: Array, X: Array, fx: float, fy: float, cx: float, cy: float
) -> tuple[Array, Array, Array, Array]:
    """``Zm``: pixel of world point ``X`` seen from pose ``(p, q)`` (paper eqs. 2-3).

    Parameters
    ----------
    p : (N, 3) camera centres, world frame.
    q : (N, 4) camera orientations ``q_wc``.
    X : (N, 3) feature positions, world frame.
    fx, fy, cx, cy : intrinsics in pixels.

    Returns
    -------
    h : (N, 2) predicted pixels.
    J_pose : (N, 2, 7) Jacobian with respect to ``[p, q]``.
    J_feat : (N, 2, 3) Jacobian with respect to ``X``.
    depth : (N,) depth ``z`` in the camera frame (callers reject ``z <= 0``).
    """
    d = X - p
    qn, Jn = _normalize_with_jacobian(q)
    Xc, Jqn = _rotate_inverse_unit(qn, d)
    J_q = Jqn @ Jn
    Rt = np.swapaxes(unit_quat_to_rotmat(qn[:, 0], qn[:, 1:]), -1, -2)  # R_cw, (N, 3, 3)
    return _zm(Xc, Rt, J_q, fx, fy, cx, cy)


def feature_model_one_pose(
    p: Array, q: Array, X: Array, fx: float, fy: float, cx: float, cy: float
) -> tuple[Array, Array, Array, Array]:
    """:func:`feature_model` of the points ``X (N, 3)`` from one pose ``p (3,)``, ``q (4,)``:
    the same values up to rounding, for a fraction of the cost. ``R(q)ᵀ d`` is linear in
    ``d``, so its quaternion Jacobian is ``Σ_k d_k M_k`` with ``M_k (3, 4)`` that of the
    axis ``e_k``, computed once, rather than element by element.

    Returns
    -------
    h, J_pose, J_feat, depth : as :func:`feature_model`, ``(N, 2)``, ``(N, 2, 7)``,
        ``(N, 2, 3)``, ``(N,)``.
    """
    X = np.asarray(X, float).reshape(-1, 3)
    q3 = np.broadcast_to(np.asarray(q, float).reshape(1, 4), (3, 4))
    axes, M = rotate_inverse_with_jacobian(q3, np.eye(3))  # R^T e_k (rows: k) and d(R^T e_k)/dq
    Rt = axes.T  # R_cw: column k is R^T e_k
    d = X - np.asarray(p, float).reshape(1, 3)
    Xc = d @ Rt.T
    J_q = (d @ M.reshape(3, 12)).reshape(-1, 3, 4)  # sum_k d_k M_k
    return _zm(Xc, Rt, J_q, fx, fy, cx, cy)


def relative_position_with_jacobian(
    p_i: Array, q_i: Array, p_j: Array
) -> tuple[Array, Array, Array]:
    """``X = R_wi.T (p_j - p_i)`` (paper eq. 5) and Jacobians.

    Returns
    -------
    X : (N, 3) position of camera *j* in frame *i*.
    J_i : (N, 3, 7) with respect to pose *i* ``[p_i, q_i]``.
    J_pj : (N, 3, 3) with respect to ``p_j``.
    """
    from .rotations import quat_to_rotmat

    X, J_q = rotate_inverse_with_jacobian(q_i, p_j - p_i)
    Rt = np.swapaxes(quat_to_rotmat(q_i), -1, -2)
    return X, np.concatenate([-Rt, J_q], axis=2), Rt


def translation_model(p_i: Array, q_i: Array, p_j: Array) -> tuple[Array, Array, Array]:
    """``ZT = [x/z, y/z]`` of camera *j*'s centre in frame *i* (paper eqs. 5-6).

    Singular when ``z -> 0`` (sideways motion); see :func:`bearing_model`.

    Returns
    -------
    h : (N, 2); J_i : (N, 2, 7) w.r.t. pose *i*; J_j : (N, 2, 7) w.r.t. pose *j*
    (zero in the quaternion columns).
    """
    X, J_i3, J_pj = relative_position_with_jacobian(p_i, q_i, p_j)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
    h = np.stack([x / zs, y / zs], -1)
    P = np.zeros((len(z), 2, 3))
    P[:, 0, 0] = 1.0 / zs
    P[:, 0, 2] = -x / zs**2
    P[:, 1, 1] = 1.0 / zs
    P[:, 1, 2] = -y / zs**2
    J_j = np.zeros((len(z), 2, 7))
    J_j[:, :, :3] = P @ J_pj
    return h, P @ J_i3, J_j


def bearing_model(
    p_i: Array, q_i: Array, p_j: Array, t_meas: Array
) -> tuple[Array, Array, Array]:
    """Non-singular ``ZT``: tangent components of the unit direction to camera *j*.

    ``h = B(t_meas).T @ X / |X|`` with ``X = R_wi.T (p_j - p_i)`` and ``B`` from
    :func:`eifslam.geometry.rotations.tangent_basis`; the measurement is ``z = 0`` and its
    covariance is that of ``dt`` in :class:`eifslam.estimation.measurements.RelativePose`.

    Returns
    -------
    h : (N, 2); J_i : (N, 2, 7); J_j : (N, 2, 7).
    """
    X, J_i3, J_pj = relative_position_with_jacobian(p_i, q_i, p_j)
    B = tangent_basis(t_meas)  # (N, 3, 2)
    n = np.linalg.norm(X, axis=-1, keepdims=True)
    b = X / n
    Jb = (np.eye(3) - b[:, :, None] * b[:, None, :]) / n[:, :, None]
    Bt = np.swapaxes(B, -1, -2)
    h = np.einsum("nij,nj->ni", Bt, b)
    G = Bt @ Jb
    J_j = np.zeros((len(X), 2, 7))
    J_j[:, :, :3] = G @ J_pj
    return h, G @ J_i3, J_j


def rotation_model(q_i: Array, q_j: Array, q_meas: Array) -> tuple[Array, Array, Array]:
    """``ZR`` as a 3-vector error: ``h = 2 s vec(q_meas^* ⊗ q_i^* ⊗ q_j)``.

    ``s = ±1`` picks the hemisphere with non-negative scalar part. The measurement is
    ``z = 0``; to first order ``h`` equals ``dtheta`` of
    :class:`eifslam.estimation.measurements.RelativePose`, whose covariance applies directly.

    Parameters
    ----------
    q_i, q_j : (N, 4) orientations ``q_wc`` of the two poses (any norm).
    q_meas : (N, 4) measured ``q_ij`` (unit).

    Returns
    -------
    h : (N, 3); J_i : (N, 3, 4) w.r.t. ``q_i``; J_j : (N, 3, 4) w.r.t. ``q_j``.
    """
    qi, Jni = _normalize_with_jacobian(q_i)
    qj, Jnj = _normalize_with_jacobian(q_j)
    Lm = quat_left_matrix(q_meas * np.array([1.0, -1.0, -1.0, -1.0]))
    qi_c = qi @ _CONJ
    e_inner = np.einsum("nij,nj->ni", quat_right_matrix(qj), qi_c)  # q_i^* ⊗ q_j
    e = np.einsum("nij,nj->ni", Lm, e_inner)
    s = np.where(e[:, 0] < 0, -1.0, 1.0)
    h = 2.0 * s[:, None] * e[:, 1:]
    de_dqj = Lm @ quat_left_matrix(qi_c)
    de_dqi = Lm @ quat_right_matrix(qj) @ _CONJ
    k = 2.0 * s[:, None, None]
    return h, k * (de_dqi @ Jni)[:, 1:, :], k * (de_dqj @ Jnj)[:, 1:, :]


def quat_norm_model(q: Array) -> tuple[Array, Array]:
    """Pseudo-measurement of the quaternion norm: ``h = |q|^2`` (measured as 1).

    Returns
    -------
    h : (N,) ; J : (N, 1, 4).
    """
    return np.sum(q * q, -1), 2.0 * q[:, None, :]


def distance_model(a: Array, b: Array) -> tuple[Array, Array, Array]:
    """Distance ``|b - a|`` between two points (scale prior and scale recovery).

    Returns
    -------
    h : (N,) ; J_a : (N, 1, 3) ; J_b : (N, 1, 3).
    """
    d = b - a
    n = np.linalg.norm(d, axis=-1)
    u = d / np.where(n > 0, n, 1.0)[:, None]
    return n, -u[:, None, :], u[:, None, :]


def zt_paper_covariance(t_meas: Array) -> tuple[Array, Array]:
    """The paper's ``[ζ, η]`` of a measured direction and its Jacobian w.r.t. ``dt``.

    Parameters
    ----------
    t_meas : (N, 3) measured unit directions (``t_z`` must not be near zero).

    Returns
    -------
    z : (N, 2) the measured ``[ζ, η] = [t_x/t_z, t_y/t_z]``.
    G : (N, 2, 2) the Jacobian ``d[ζ, η]/d(dt)``; the covariance is ``G cov_dt G^T``.
    """
    x, y, zc = t_meas[:, 0], t_meas[:, 1], t_meas[:, 2]
    P = np.zeros((len(x), 2, 3))
    P[:, 0, 0] = 1.0 / zc
    P[:, 0, 2] = -x / zc**2
    P[:, 1, 1] = 1.0 / zc
    P[:, 1, 2] = -y / zc**2
    G = P @ tangent_basis(t_meas)
    return np.stack([x / zc, y / zc], -1), G
