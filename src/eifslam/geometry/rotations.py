"""Rotations, quaternions and small tangent-space helpers.

Conventions (the only place they are defined)
---------------------------------------------
* Quaternions are **Hamilton**, **scalar first**: ``q = [w, x, y, z]``.
* ``q_wc`` (the paper's ``q^{WC}``) is the orientation of the camera in the world:
  ``R(q_wc) = R_wc`` maps camera-frame vectors into the world frame, so a world point
  ``X_w`` is seen in the camera at ``X_c = R_wc.T @ (X_w - p)`` (paper eq. 2, with
  ``R^{CW} = R_wc.T``).
* The relative rotation between poses *i* and *j* is ``q_ij = q_i^* ⊗ q_j`` so that
  ``R_ij = R_wi.T @ R_wj`` (the orientation of camera *j* seen from camera *i*). The paper
  writes ``q^{WCj} = q^{CiCj} ⊗ q^{WCi}``, the same quantity under the opposite product
  order convention.
* Rotation errors are right-multiplied rotation vectors: ``R_true = R_meas @ Exp(dtheta)``.

Everything is vectorised over leading dimensions and is pure NumPy / SciPy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Array = NDArray[np.float64]

__all__ = [
    "skew",
    "quat_normalize",
    "quat_conjugate",
    "quat_multiply",
    "quat_to_rotmat",
    "unit_quat_to_rotmat",
    "rotmat_to_quat",
    "quat_exp",
    "quat_log",
    "rotvec_exp",
    "tangent_basis",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "quat_left_matrix",
    "quat_right_matrix",
]


def skew(v: Array) -> Array:
    """Cross-product matrix.

    Parameters
    ----------
    v : (..., 3) array

    Returns
    -------
    (..., 3, 3) array ``S`` with ``S @ w == cross(v, w)``.
    """
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    S[..., 0, 1], S[..., 0, 2] = -z, y
    S[..., 1, 0], S[..., 1, 2] = z, -x
    S[..., 2, 0], S[..., 2, 1] = -y, x
    return S


def quat_normalize(q: Array) -> Array:
    """Unit quaternion(s) with non-negative scalar part, shape ``(..., 4)``."""
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    q = q / np.where(n > 0, n, 1.0)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def quat_conjugate(q: Array) -> Array:
    """Conjugate ``[w, -x, -y, -z]`` of quaternion(s) ``(..., 4)``."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_left_matrix(q: Array) -> Array:
    """Matrix ``L(q)`` with ``q ⊗ p == L(q) @ p``; shape ``(..., 4, 4)``."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([w, -x, -y, -z], -1),
            np.stack([x, w, -z, y], -1),
            np.stack([y, z, w, -x], -1),
            np.stack([z, -y, x, w], -1),
        ],
        -2,
    )


def quat_right_matrix(q: Array) -> Array:
    """Matrix ``R(q)`` with ``p ⊗ q == R(q) @ p``; shape ``(..., 4, 4)``."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([w, -x, -y, -z], -1),
            np.stack([x, w, z, -y], -1),
            np.stack([y, -z, w, x], -1),
            np.stack([z, y, -x, w], -1),
        ],
        -2,
    )


def quat_multiply(a: Array, b: Array) -> Array:
    """Hamilton product ``a ⊗ b`` of quaternion(s) ``(..., 4)``."""
    return np.einsum("...ij,...j->...i", quat_left_matrix(a), np.asarray(b, dtype=float))


def quat_to_rotmat(q: Array) -> Array:
    """Rotation matrix of unit quaternion(s).

    ``R = (w² - |v|²) I + 2 v vᵀ + 2 w [v]×`` for ``q = [w, v]``, written element by element.

    Parameters
    ----------
    q : (..., 4) array, ``[w, x, y, z]``; normalised internally.

    Returns
    -------
    (..., 3, 3) rotation matrices.
    """
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return unit_quat_to_rotmat(q[..., 0], q[..., 1:])


def unit_quat_to_rotmat(w: Array, v: Array) -> Array:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions given as scalar ``w (...)`` and
    vector part ``v (..., 3)`` (not normalised here)."""
    R = (2.0 * v)[..., :, None] * v[..., None, :]  # 2 v v^T
    a = w * w - np.sum(v * v, -1)
    w2 = 2.0 * w
    wx, wy, wz = w2 * v[..., 0], w2 * v[..., 1], w2 * v[..., 2]
    for i in range(3):
        R[..., i, i] = a + R[..., i, i]
    R[..., 0, 1] -= wz
    R[..., 0, 2] += wy
    R[..., 1, 0] += wz
    R[..., 1, 2] -= wx
    R[..., 2, 0] -= wy
    R[..., 2, 1] += wx
    return R


def rotmat_to_quat(R: Array) -> Array:
    """Unit quaternion(s) ``[w, x, y, z]`` (``w >= 0``) of rotation matrices ``(..., 3, 3)``."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    q = Rotation.from_matrix(flat).as_quat(scalar_first=True)
    return quat_normalize(q).reshape(R.shape[:-2] + (4,))


def quat_wxyz_to_xyzw(q: Array) -> Array:
    """Reorder ``[w, x, y, z]`` to the TUM / SciPy order ``[x, y, z, w]``."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 1:], q[..., :1]], -1)


def quat_xyzw_to_wxyz(q: Array) -> Array:
    """Reorder ``[x, y, z, w]`` (TUM / SciPy) to ``[w, x, y, z]``."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 3:], q[..., :3]], -1)


def quat_exp(phi: Array) -> Array:
    """Quaternion of rotation vector(s) ``phi`` (radians), shape ``(..., 3) -> (..., 4)``."""
    phi = np.asarray(phi, dtype=float)
    th = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * th
    # sin(th/2)/th with a series near zero
    k = np.where(th > 1e-8, np.sin(half) / np.where(th > 1e-8, th, 1.0), 0.5 - th**2 / 48.0)
    return np.concatenate([np.cos(half), k * phi], -1)


def quat_log(q: Array) -> Array:
    """Rotation vector(s) of quaternion(s) ``(..., 4) -> (..., 3)``; shortest rotation."""
    q = quat_normalize(q)
    w, v = q[..., :1], q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    th = 2.0 * np.arctan2(s, w)
    k = np.where(s > 1e-10, th / np.where(s > 1e-10, s, 1.0), 2.0 / np.maximum(w, 1e-300))
    return k * v


def rotvec_exp(phi: Array) -> Array:
    """Rotation matrix/matrices ``Exp(phi)`` of rotation vector(s) ``(..., 3) -> (..., 3, 3)``."""
    return quat_to_rotmat(quat_exp(phi))


def tangent_basis(t: Array) -> Array:
    """Orthonormal basis of the plane orthogonal to unit vector(s) ``t``.

    The basis is a deterministic, smooth-almost-everywhere function of ``t`` and is the
    one used to express translation-direction errors: a direction ``t`` perturbed by
    ``d`` (2-vector) is ``normalize(t + B(t) @ d)``.

    Parameters
    ----------
    t : (..., 3) array, unit vector(s).

    Returns
    -------
    (..., 3, 2) array ``B`` with ``B.T @ B = I`` and ``B.T @ t = 0``.
    """
    t = np.asarray(t, dtype=float)
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    # pick the coordinate axis least aligned with t
    idx = np.argmin(np.abs(t), axis=-1)
    a = np.zeros_like(t)
    np.put_along_axis(a, idx[..., None], 1.0, axis=-1)
    b1 = np.cross(t, a)
    b1 /= np.linalg.norm(b1, axis=-1, keepdims=True)
    b2 = np.cross(t, b1)
    return np.stack([b1, b2], -1)
