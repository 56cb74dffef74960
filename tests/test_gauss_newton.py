"""The shared Gauss-Newton pass (estimation/gauss_newton.py)."""

from __future__ import annotations

import numpy as np

from eifslam.errors import EstimatorError
from eifslam.estimation.factors import Linearised
from eifslam.estimation.gauss_newton import begin_pass, gauss_newton, information_terms, state_scale
from eifslam.estimation.relinearisation import contribution
from test_incremental import full_solve, rel_err, run_slam, scene
from eifslam.estimation.filter import InformationFilter


def test_information_terms_are_eq8_for_the_batch_and_the_online_relinearisation():
    rng = np.random.default_rng(0)
    N, m, k = 4, 2, 10
    J, innov, x0 = rng.normal(size=(N, m, k)), rng.normal(size=(N, m)), rng.normal(size=(N, k))
    A = rng.normal(size=(N, m, m))
    W = A @ A.transpose(0, 2, 1) + np.eye(m)
    Lam, eta = information_terms(J, W, innov + np.einsum("nmk,nk->nm", J, x0))
    for n in range(N):
        np.testing.assert_allclose(Lam[n], J[n].T @ W[n] @ J[n], rtol=1e-12)
        np.testing.assert_allclose(eta[n], J[n].T @ W[n] @ (innov[n] + J[n] @ x0[n]), rtol=1e-12)
    idx = np.arange(N * k).reshape(N, k)
    x = np.zeros(N * k)
    x[idx] = x0
    for got in (contribution(idx, J, W, innov, x0), Linearised(idx, J, W, innov).information(x)):
        np.testing.assert_array_equal(got[0], Lam)
        np.testing.assert_array_equal(got[1], eta)


def test_passes_converge_to_the_relinearised_solution_and_a_failed_solve_is_undone():
    sc, m = scene(12, 3)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="full"))
    assert state_scale(f) >= 1.0
    p = begin_pass(f)
    assert np.array_equal(p.before, f.x) and p.fused.all() and p.change(f) == 0.0
    assert 1 <= gauss_newton(f, 5, 1e-10, lambda n: f.recover()) <= 5
    assert rel_err(f.x, full_solve(f)) < 1e-8  # at the fixed point of relinearise-then-solve
    x = f.x.copy()

    def failing(n):
        f.x[:] += 1.0
        raise EstimatorError("singular")

    assert gauss_newton(f, 3, 1e-10, failing) == 0
    np.testing.assert_array_equal(f.x, x)  # undone
