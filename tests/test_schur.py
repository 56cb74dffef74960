"""The window's pose Schur complement by chunks of its staircase (estimation/schur.py)
against the dense product."""

import numpy as np
import pytest

from eifslam.estimation.schur import coupled_poses, staircase_chunks, subtract_gram


def _window(rng, F, p, staircase=True, empty=0):
    """A coupling ``B (3F, 7p)``: each feature coupled to a run of poses (a staircase,
    most runs short and ending at the last pose) or to random poses; ``empty`` features
    coupled to none."""
    coupled = np.zeros((F, p), bool)
    for f in range(F - empty):
        if staircase:
            m = min(p, 2 + int(rng.geometric(0.2)))
            end = p - int(rng.integers(0, 3))
            coupled[f, max(0, end - m):end] = True
        else:
            coupled[f, rng.choice(p, size=int(rng.integers(1, p + 1)), replace=False)] = True
    B = rng.normal(size=(3 * F, 7 * p)) * np.repeat(np.repeat(coupled, 3, axis=0), 7, axis=1)
    return B, coupled


@pytest.mark.parametrize("staircase", [True, False])
def test_chunks_cover_each_coupled_feature_once_within_their_span(staircase):
    rng = np.random.default_rng(1)
    B, coupled = _window(rng, 300, 40, staircase, empty=5)
    assert np.array_equal(coupled_poses(B, 40), coupled)
    chunks = staircase_chunks(coupled)
    rows = np.concatenate([r for r, _, _ in chunks])
    assert sorted(rows.tolist()) == list(range(295))  # every coupled feature once, no empty one
    for r, lo, hi in chunks:
        assert 0 <= lo < hi <= 40
        assert not coupled[r][:, :lo].any() and not coupled[r][:, hi:].any()
    if staircase:  # the point of it: far fewer columns than the whole window per row
        work = sum(len(r) * (hi - lo) ** 2 for r, lo, hi in chunks)
        assert work < 0.5 * 300 * 40 ** 2


@pytest.mark.parametrize("staircase", [True, False])
@pytest.mark.parametrize("lower", [True, False])
def test_subtract_gram_equals_the_dense_product(staircase, lower):
    rng = np.random.default_rng(2)
    F, p = 250, 30
    B, coupled = _window(rng, F, p, staircase, empty=3)
    A = rng.normal(size=(7 * p, 7 * p))
    P = A @ A.T
    want = P - B.T @ B
    got = subtract_gram(P.copy(), B, coupled, lower=lower)
    scale = np.abs(want).max()
    if lower:
        assert np.allclose(np.tril(got), np.tril(want), rtol=0, atol=1e-12 * scale)
        assert np.array_equal(np.triu(got, 1), np.triu(P, 1))  # above the diagonal: untouched
    else:
        assert np.allclose(got, want, rtol=0, atol=1e-12 * scale)


def test_no_feature_or_no_coupling_changes_nothing():
    P = np.eye(14)
    assert staircase_chunks(np.zeros((0, 2), bool)) == []
    assert staircase_chunks(np.zeros((4, 2), bool)) == []
    assert np.array_equal(subtract_gram(P.copy(), np.zeros((12, 14)), np.zeros((4, 2), bool)), P)


def _slam_information(rng, n_poses=6, n_feats=40):
    """A random information matrix of SLAM form: poses (7) then features (3), each feature
    measured from 2-4 poses, consecutive poses linked; positive definite."""
    n = 7 * n_poses + 3 * n_feats
    I = np.zeros((n, n))
    for a in range(n_poses - 1):
        J = rng.normal(size=(6, 14))
        I[7 * a:7 * a + 14, 7 * a:7 * a + 14] += J.T @ J
    for f in range(n_feats):
        c = 7 * n_poses + 3 * f
        for a in rng.choice(n_poses, size=int(rng.integers(2, 5)), replace=False):
            J = rng.normal(size=(2, 10))
            idx = np.r_[7 * a:7 * a + 7, c:c + 3]
            I[np.ix_(idx, idx)] += J.T @ J
    I += 1e-3 * np.eye(n)
    return I, np.arange(7 * n_poses), np.arange(7 * n_poses, n)


def test_factorize_equals_the_dense_solve_on_all_and_on_part_of_the_state():
    import scipy.sparse as sp

    from eifslam.estimation.recovery import factorize

    rng = np.random.default_rng(3)
    I, pidx, fidx = _slam_information(rng)
    b = rng.normal(size=len(I))
    x = factorize(sp.csr_matrix(I), pidx, fidx).solve(b)
    assert np.allclose(x, np.linalg.solve(I, b), rtol=1e-9, atol=1e-9 * np.abs(x).max())
    keep_p, keep_f = pidx[7:], fidx[6:]  # the first pose and two features left out
    part = np.sort(np.r_[keep_p, keep_f])
    y = factorize(sp.csr_matrix(I), keep_p, keep_f).solve_entries(b[part], part)
    want = np.linalg.solve(I[np.ix_(part, part)], b[part])
    assert np.allclose(y, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


def test_factorize_refuses_two_features_in_one_measurement():
    import scipy.sparse as sp

    from eifslam.errors import EstimatorError
    from eifslam.estimation.recovery import factorize

    I, pidx, fidx = _slam_information(np.random.default_rng(4))
    I[fidx[0], fidx[3]] = I[fidx[3], fidx[0]] = 0.5
    with pytest.raises(EstimatorError, match="share a measurement"):
        factorize(sp.csr_matrix(I), pidx, fidx)


@pytest.mark.parametrize("which", ["poses and features", "features only", "poses only"])
def test_sparse_right_side_solve_equals_the_dense_solve(which):
    """A rebuild's back substitution solves for right sides that are zero outside the few
    entries its coupling touches (recovery.SparseSolve): the same answer as the dense
    solve of the factorised block, on every entry, whatever kind of entry is touched."""
    import scipy.sparse as sp

    from eifslam.estimation.recovery import factorize

    rng = np.random.default_rng(5)
    I, pidx, fidx = _slam_information(rng)
    keep_p, keep_f = pidx[7:], fidx[6:]
    part = np.sort(np.r_[keep_p, keep_f])
    solver = factorize(sp.csr_matrix(I), keep_p, keep_f).restricted(part)
    is_pose = np.isin(part, keep_p)
    pool = {"poses and features": np.arange(len(part)), "features only": np.flatnonzero(~is_pose),
            "poses only": np.flatnonzero(is_pose)}[which]
    rows = np.sort(rng.choice(pool, size=9, replace=False))
    r = rng.normal(size=len(rows))
    full = np.zeros(len(part))
    full[rows] = r
    want = np.linalg.solve(I[np.ix_(part, part)], full)
    got = solver.sparse(rows).solve(r)
    assert np.allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    assert np.allclose(got, solver.solve(full), rtol=1e-12, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("n_keep", [1, 3])
def test_factorize_onto_equals_the_dense_schur_complement(n_keep, monkeypatch):
    """A rebuild's marginal of the kept poses, from the trailing block of the reduced
    matrix's factor, against ``I_kk - I_km I_mm^-1 I_mk`` in dense algebra; the active
    features (the last two) take no part. Without the fallback to the solves."""
    import scipy.sparse as sp

    from eifslam.estimation.recovery import SchurFactor, factorize_onto

    def no_fallback(*a, **k):
        raise AssertionError("fell back to SchurFactor.project")

    monkeypatch.setattr(SchurFactor, "project", no_fallback)

    rng = np.random.default_rng(5)
    I, pidx, fidx = _slam_information(rng, n_poses=8, n_feats=60)
    i = rng.normal(size=len(I))
    keep = pidx[7 * (8 - n_keep):]
    mp, mf = pidx[: 7 * (8 - n_keep)], fidx[:-6]
    m = np.r_[mp, mf]
    factor, P, b = factorize_onto(sp.csr_matrix(I), mp, mf, keep, i)
    Imm_inv = np.linalg.inv(I[np.ix_(m, m)])
    want_P = I[np.ix_(keep, keep)] - I[np.ix_(keep, m)] @ Imm_inv @ I[np.ix_(m, keep)]
    want_b = i[keep] - I[np.ix_(keep, m)] @ Imm_inv @ i[m]
    assert np.allclose(P, want_P, rtol=0, atol=1e-9 * np.abs(want_P).max())
    assert np.allclose(b, want_b, rtol=0, atol=1e-9 * np.abs(want_b).max())
    assert np.allclose(P, P.T, rtol=0, atol=0)
    # the factor is that of I_mm, as factorize's
    r = rng.normal(size=len(m))
    assert np.allclose(factor.solve_entries(r, m), Imm_inv @ r, rtol=1e-9, atol=1e-9 * np.abs(Imm_inv @ r).max())


def test_factorize_onto_falls_back_to_the_solves_when_the_ordered_factorisation_fails(monkeypatch):
    """If SuperLU refuses the factorisation with the kept poses last, the marginal comes
    from the pose system's solves, and is the same."""
    import scipy.sparse as sp

    import eifslam.estimation.recovery as recovery

    rng = np.random.default_rng(6)
    I, pidx, fidx = _slam_information(rng, n_poses=8, n_feats=60)
    i = rng.normal(size=len(I))
    keep, mp, mf = pidx[42:], pidx[:42], fidx[:-6]
    want = recovery.factorize_onto(sp.csr_matrix(I), mp, mf, keep, i)
    real = recovery.splu

    def refusing(A, permc_spec=None, **kw):
        if permc_spec == "NATURAL":
            raise RuntimeError("Factor is exactly singular")
        return real(A, permc_spec=permc_spec, **kw)

    monkeypatch.setattr(recovery, "splu", refusing)
    _, P, b = recovery.factorize_onto(sp.csr_matrix(I), mp, mf, keep, i)
    np.testing.assert_allclose(P, want[1], rtol=0, atol=1e-9 * np.abs(want[1]).max())
    np.testing.assert_allclose(b, want[2], rtol=0, atol=1e-9 * np.abs(want[2]).max())
