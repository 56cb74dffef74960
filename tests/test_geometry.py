"""Quaternion conventions against scipy.spatial.transform, and purity of the core."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eifslam.geometry import rotations as g
from eifslam.geometry.camera import PinholeCamera
from eifslam.errors import CalibrationError


def test_quaternion_conventions_match_scipy():
    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=1)
    q = g.quat_normalize(R.as_quat(scalar_first=True))
    np.testing.assert_allclose(g.quat_to_rotmat(q), R.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(g.rotmat_to_quat(R.as_matrix()), q, atol=1e-12)
    R2 = Rotation.random(50, random_state=2)
    q2 = R2.as_quat(scalar_first=True)
    np.testing.assert_allclose(g.quat_to_rotmat(g.quat_multiply(q, q2)), (R * R2).as_matrix(), atol=1e-12)
    phi = rng.normal(size=(50, 3))
    np.testing.assert_allclose(g.rotvec_exp(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    small = 1e-3 * phi
    np.testing.assert_allclose(g.quat_log(g.quat_exp(small)), small, atol=1e-12)
    np.testing.assert_allclose(g.quat_xyzw_to_wxyz(R.as_quat()), R.as_quat(scalar_first=True))
    np.testing.assert_allclose(g.quat_wxyz_to_xyzw(q) * np.sign(q[:, :1]), R.as_quat() * np.sign(R.as_quat()[:, 3:]), atol=1e-12)


def test_skew_and_rotation_matrices_of_any_leading_shape():
    rng = np.random.default_rng(4)
    for shape in [(), (7,), (3, 5)]:
        v, w = rng.normal(size=shape + (3,)), rng.normal(size=shape + (3,))
        S = g.skew(v)
        assert S.shape == shape + (3, 3)
        np.testing.assert_allclose(np.einsum("...ij,...j->...i", S, w), np.cross(v, w), atol=1e-12)
        q = rng.normal(size=shape + (4,))  # any norm: normalised inside
        R = g.quat_to_rotmat(q)
        assert R.shape == shape + (3, 3)
        ref = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(shape + (3, 3))
        np.testing.assert_allclose(R, ref, atol=1e-12)


def test_tangent_basis_is_orthonormal():
    t = np.random.default_rng(3).normal(size=(100, 3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    B = g.tangent_basis(t)
    np.testing.assert_allclose(np.swapaxes(B, 1, 2) @ B, np.broadcast_to(np.eye(2), (100, 2, 2)), atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,ni->nj", B, t), 0.0, atol=1e-12)


def test_camera_projection_and_validation():
    cam = PinholeCamera(500, 500, 320, 240, 640, 480)
    uv = cam.project(np.array([[0.2, -0.1, 2.0]]))
    np.testing.assert_allclose(uv, [[370.0, 215.0]])
    np.testing.assert_allclose(cam.bearing(uv)[0], np.array([0.2, -0.1, 2.0]) / np.linalg.norm([0.2, -0.1, 2.0]))
    with pytest.raises(CalibrationError, match="focal"):
        PinholeCamera(-1, 500, 320, 240, 640, 480)


@pytest.mark.parametrize("module", ["geometry.rotations", "geometry.camera", "geometry.models", "estimation.state", "estimation.filter", "estimation.recovery", "estimation.smoothing", "estimation.incremental", "estimation.localisation", "sim.synthetic", "sim.frontend", "estimation.initialisation", "baselines.bundle_adjustment", "baselines.ekf", "evaluation.metrics", "system.config"])
def test_core_modules_import_neither_cv2_nor_matplotlib(module):
    code = f"import sys, eifslam.{module}; bad=[m for m in ('cv2','matplotlib') if m in sys.modules]; print(','.join(bad)); sys.exit(1 if bad else 0)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, f"eifslam.{module} imports {r.stdout.strip()} {r.stderr[-300:]}"
