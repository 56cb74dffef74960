"""The multi-view first estimate of new features: points refined on every view of them."""

from __future__ import annotations

import numpy as np

from eifslam.estimation.initialisation import refine_points, triangulate
from eifslam.geometry.rotations import quat_to_rotmat
from eifslam.sim.synthetic import corridor_scene


def test_refine_points_recovers_points_from_many_views():
    """Noise-free views from 8 poses: refinement from a perturbed start lands on the true
    point; with pixel noise it fits every view better than the two-view midpoint."""
    rng = np.random.default_rng(3)
    sc = corridor_scene(8, rng)
    vis = np.flatnonzero(np.all([sc.visible(k) for k in range(8)], 0))[:40]
    P, Q = sc.positions.copy(), sc.quats.copy()
    feature = np.repeat(np.arange(len(vis)), 8)
    k = np.tile(np.arange(8), len(vis))
    uv = np.concatenate([sc.project(kk, vis[[i]]) for i, kk in zip(feature, k)])
    X0, _, ok = triangulate(P[0], Q[0], sc.project(0, vis), P[7], Q[7], sc.project(7, vis), sc.camera)
    assert ok.all()
    X, front = refine_points(X0 + rng.normal(0, 0.05, X0.shape), feature, P[k], Q[k], uv, sc.camera)
    assert front.all()
    np.testing.assert_allclose(X, sc.points[vis], atol=1e-7)
    # with pixel noise: the refined points fit every view at least as well as the midpoints
    uvn = uv + rng.normal(0, 1.0, uv.shape)
    Xm, _, _ = triangulate(P[0], Q[0], uvn[k == 0], P[7], Q[7], uvn[k == 7], sc.camera)
    Xr, _ = refine_points(Xm, feature, P[k], Q[k], uvn, sc.camera)

    def cost(Xs):
        h = np.concatenate([sc.camera.project((Xs[[i]] - P[kk]) @ quat_to_rotmat(Q[kk])) for i, kk in zip(feature, k)])
        return np.sum((h - uvn) ** 2)

    assert cost(Xr) < cost(Xm)
    assert np.median(np.linalg.norm(Xr - sc.points[vis], axis=1)) < np.median(np.linalg.norm(Xm - sc.points[vis], axis=1))
