"""Incremental recovery over an active window against the full sparse and the dense solve."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import ConfigError
from eifslam.estimation.filter import InformationFilter
from eifslam.estimation.incremental import IncrementalRecovery
from eifslam.estimation.measurements import RelativePose
from eifslam.estimation.options import FilterConfig
from eifslam.estimation.recovery import factorize
from eifslam.estimation.smoothing import smooth
from eifslam.estimation.measurements import FeatureObservations
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import SyntheticScene, corridor_scene, true_relative
from eifslam.system.slam import Slam


def scene(frames: int, seed: int):
    """A corridor and its simulated front end (every point in the map)."""
    rng = np.random.default_rng(seed)
    sc = corridor_scene(frames, rng, points_per_metre=12.0)
    return sc, SyntheticFrontEnd(sc, seed, map_fraction=1.0)


def run_slam(sc, fe: SyntheticFrontEnd, f: InformationFilter, on_frame=None) -> InformationFilter:
    """The system over every frame with back end ``f``; ``on_frame(k, f)`` after each
    frame; then the complete estimate (the marginalised states back-substituted)."""
    fe = SyntheticFrontEnd(sc, fe.model.seed, map_fraction=1.0)  # a fresh one: a front end serves one run
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe, backend=f)
    for k in range(len(sc.positions)):
        slam.track(k)
        if on_frame is not None:
            on_frame(k, f)
    f.complete_estimate()
    return f


def zm(fe: SyntheticFrontEnd, k: int) -> FeatureObservations:
    """``Zm`` of scene frame *k* as the system measured it."""
    fe = SyntheticFrontEnd(fe.scene, fe.model.seed, map_fraction=1.0)
    fe.add_frame(k, k)
    ids, uv = fe.map_observations(k)
    return FeatureObservations.make(np.full(len(ids), k), ids, uv, fe.sigma_px)


def full_solve(f: InformationFilter) -> np.ndarray:
    return factorize(f.information_matrix(), *f.index_sets()).solve(f.information_vector())


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    if a.size == 0:  # the first frame: nothing recovered yet
        return 0.0
    return float(np.max(np.abs(a - b)) / max(1.0, np.abs(b).max()))


@pytest.fixture(scope="module")
def incremental_run():
    """A 40-frame corridor with window 1 (states leave as soon as they go unmeasured),
    checked against the full solve after every frame."""
    sc, m = scene(40, 3)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    diffs, windows = [], []

    def check(k, filt):
        a = filt.incremental.active_indices
        diffs.append(rel_err(filt.x[a], full_solve(filt)[a]))
        windows.append((len(a), filt.dim))

    run_slam(sc, m, f, on_frame=check)
    return sc, m, f, diffs, windows


def test_active_window_equals_full_solve_every_frame(incremental_run):
    _, _, f, diffs, windows = incremental_run
    assert len(diffs) == 40
    assert max(diffs) < 1e-8
    st = f.incremental.stats
    # the window really is a window: states were eliminated, and it stays small
    assert st.marginalised_features > 100 and st.marginalised_poses > 20
    assert windows[-1][0] < 0.5 * windows[-1][1]
    assert st.fallbacks == 0 and st.rebuilds == 1  # the first step builds the window


def test_complete_estimate_equals_full_and_dense_solve(incremental_run):
    _, _, f, _, _ = incremental_run
    I = f.information_matrix().toarray()
    x_dense = np.linalg.solve(I, f.information_vector())
    assert rel_err(f.x, x_dense) < 1e-8  # run_slam back-substituted the whole state
    assert rel_err(f.x, full_solve(f)) < 1e-8


def test_incremental_run_equals_full_run():
    sc, m = scene(25, 4)
    a = run_slam(sc, m, InformationFilter(sc.camera, recovery="full"))
    # the same linearisations: online relinearisation exists with incremental recovery only
    cfg = FilterConfig(relinearise_threshold=None)
    b = run_slam(sc, m, InformationFilter(sc.camera, cfg, recovery="incremental", window=1))
    assert b.incremental.stats.marginalised_poses > 0
    assert a.dim == b.dim
    assert rel_err(b.x, a.x) < 1e-8
    assert rel_err(b.information_vector(), a.information_vector()) < 1e-10


def test_reactivation_when_a_marginalised_state_is_measured_again(incremental_run):
    sc, m, f, _, _ = incremental_run
    last = f.layout.pose_ids[-1]
    obs = zm(m, last)
    seen = obs.subset(f.layout.has_features(obs.feature))
    q, t = true_relative(sc, 1, last)
    st = f.incremental.stats
    before, rebuilds, react = st.fallbacks, st.rebuilds, st.reactivations
    f.fuse_relative([RelativePose(1, last, q, t, m.model.rel_cov)])  # a loop closure to pose 1
    f.fuse_features(seen)  # and the last image again: its features are active
    f.recover_active()
    # pose 1 and the poses eliminated after it come back by undoing their eliminations
    assert st.reactivations == react + 1 and st.reactivated_poses > 1
    assert st.fallbacks == before and st.rebuilds == rebuilds
    a = f.incremental.active_indices
    assert f.layout.pose_offset(1) in a  # pose 1 is back in the window
    assert rel_err(f.x[a], full_solve(f)[a]) < 1e-8
    # the window keeps working: measurements of active states, no fallback
    f.fuse_features(seen)
    f.recover_active()
    assert f.incremental.stats.fallbacks == before
    a = f.incremental.active_indices
    assert rel_err(f.x[a], full_solve(f)[a]) < 1e-8
    marg = f.incremental.stats.marginalised_poses
    f.recover_active()  # nothing new: everything ages out of the window
    assert f.incremental.stats.marginalised_poses > marg
    assert len(f.incremental.active_indices) == 0
    x_full = full_solve(f)
    f.complete_estimate()
    assert rel_err(f.x, x_full) < 1e-8
    assert rel_err(f.x, np.linalg.solve(f.information_matrix().toarray(), f.information_vector())) < 1e-8


def test_rebuild_after_smoothing():
    sc, m = scene(15, 5)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    smooth(f, max_passes=2)  # resets I: the window is stale
    assert not f.incremental.valid
    rebuilds = f.incremental.stats.rebuilds
    x_smoothed = f.x.copy()
    f.complete_estimate()  # must not overwrite the smoothed estimate with stale conditionals
    np.testing.assert_array_equal(f.x, x_smoothed)
    f.recover_active()
    assert f.incremental.stats.rebuilds == rebuilds + 1 and f.incremental.valid
    f.complete_estimate()
    assert rel_err(f.x, full_solve(f)) < 1e-8


def test_bad_settings_are_rejected():
    sc, _ = scene(3, 0)
    with pytest.raises(ConfigError):
        InformationFilter(sc.camera, recovery="sometimes")
    with pytest.raises(ConfigError):
        InformationFilter(sc.camera, recovery="incremental", window=0)
    with pytest.raises(ConfigError):
        IncrementalRecovery(feature_window=2, pose_window=1.5)


def _old_image_again(f: InformationFilter, m, k: int) -> None:
    """Fuse image ``k`` once more: its pose and features are marginalised by now."""
    obs = zm(m, k)
    f.fuse_features(obs.subset(f.layout.has_features(obs.feature)), store=False)


def test_reactivated_features_and_poses_stay_exact_every_frame():
    """Old images fused again in the middle of a run (re-observed features, a frame
    localised late): their marginalised poses and features are re-activated by undoing
    their conditionals, never rebuilt, and the window equals the full solve each frame."""
    sc, m = scene(30, 7)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    diffs = []

    def check(k, filt):
        if k in (12, 13, 20, 27):
            _old_image_again(filt, m, k - 9)  # long marginalised (window 1)
            filt.recover_active()
        a = filt.incremental.active_indices
        diffs.append(rel_err(filt.x[a], full_solve(filt)[a]))

    run_slam(sc, m, f, on_frame=check)
    st = f.incremental.stats
    assert max(diffs) < 1e-8
    assert st.fallbacks == 0 and st.rebuilds == 1
    assert st.reactivations >= 4 and st.reactivated_features > 10 and st.reactivated_poses >= 4
    # the re-activated states were marginalised again, the conditionals stay consistent
    assert rel_err(f.x, full_solve(f)) < 1e-8
    assert rel_err(f.x, np.linalg.solve(f.information_matrix().toarray(), f.information_vector())) < 1e-8


def test_undone_elimination_restores_the_window_exactly():
    """Undoing a conditional then marginalising the same states again gives the same
    window as never having marginalised them (up to rounding)."""
    sc, m = scene(25, 4)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    inc = f.incremental
    x_before = full_solve(f)
    offs = [f.layout.pose_offset(k) for k in f.layout.pose_ids]
    old = next(o for o in offs if inc.window.pos[o] < 0)  # the oldest marginalised pose
    assert inc.reactivate(np.array([old]))
    assert old in inc.active_indices
    inc.window.solve()
    a = inc.active_indices
    x = np.concatenate([inc.window.xp, inc.window.xf])
    assert rel_err(x, x_before[a]) < 1e-8


def test_state_in_a_rebuild_falls_back_to_a_rebuild():
    """A rebuild that keeps the eliminated part as one sparse factorisation (forced here:
    large eliminations do) cannot be undone: measuring a state in it again rebuilds (and
    stays exact)."""
    sc, m = scene(15, 5)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    f.incremental.undoable_rebuild_pose_entries = 0
    smooth(f, max_passes=1)  # I replaced: the next step rebuilds into one factorisation
    f.recover_active()
    st = f.incremental.stats
    fallbacks, rebuilds = st.fallbacks, st.rebuilds
    _old_image_again(f, m, 2)
    f.recover_active()
    assert st.fallbacks == fallbacks + 1 and st.rebuilds == rebuilds + 1
    a = f.incremental.active_indices
    assert rel_err(f.x[a], full_solve(f)[a]) < 1e-8
    f.complete_estimate()
    assert rel_err(f.x, full_solve(f)) < 1e-8


def test_sparse_rebuilds_keep_the_features_elimination_and_stay_exact(monkeypatch):
    """Each sparse rebuild after the first takes the eliminated features' ``G``, ``g`` from
    the previous one (:class:`~eifslam.estimation.elimination.FeatureElimination`), reading
    from ``I`` only the features touched or newly eliminated since: the kept sums equal a
    fresh elimination of the same features, and every rebuild equals the full solve."""
    import scipy.sparse as sp

    import eifslam.estimation.elimination as elimination
    from eifslam.estimation import information
    from eifslam.estimation.recovery import feature_blocks, gram_by_blocks

    read = []  # features read from I by each update of the kept elimination

    def counting(I, feat_idx, pose_idx):
        read.append(len(feat_idx) // 3)
        return feature_blocks(I, feat_idx, pose_idx)

    monkeypatch.setattr(elimination, "feature_blocks", counting)
    monkeypatch.setattr(elimination, "_GATHER_ENTRIES", 50)  # B's rows kept a few at a time
    monkeypatch.setattr(information, "BLOCK_NONZEROS", 200)  # and I's blocks read in many pieces
    sc, m = scene(20, 5)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    inc = f.incremental
    inc.undoable_rebuild_pose_entries = 0  # every rebuild is one sparse factorisation
    inc.rebuild_horizon = 1  # of everything but the states just measured
    smooth(f, max_passes=1)  # I replaced: the next sparse rebuild eliminates afresh
    elim = None
    for k in (19, 2, 5, 3, 12):
        rebuilds = inc.stats.rebuilds
        _old_image_again(f, m, k)
        f.recover_active()
        assert inc.stats.rebuilds == rebuilds + 1
        if elim is not None:
            assert inc._elim is elim  # noqa: SLF001  kept, not made afresh
        elim = inc._elim  # noqa: SLF001
        rebuilt = [c for c in inc.conditionals.slots if c is not None and c.factor is not None]
        assert all(c.factor.factor.B is elim.B for c in rebuilt)  # the coupling shared, not copied
        f.complete_estimate()
        assert rel_err(f.x, full_solve(f)) < 1e-8
        # the kept sums against a fresh elimination of the same features
        I = f.info.matrix_csr()
        poses = np.flatnonzero(~np.isin(np.arange(f.dim), f.index_sets()[1]))
        D, B = feature_blocks(I, elim.entries(), poses)
        np.testing.assert_array_equal(elim.B.toarray()[:, : len(poses)], B.toarray())
        Dinv = np.linalg.inv(D)
        G = gram_by_blocks(B, Dinv).toarray()
        g = B.T @ np.einsum("fij,fj->fi", Dinv, f.info.vector[elim.entries()].reshape(-1, 3)).ravel()
        np.testing.assert_allclose(sp.csr_matrix(elim.G).toarray()[: len(poses), : len(poses)], G,
                                   rtol=0, atol=1e-10 * np.abs(G).max())
        np.testing.assert_allclose(elim.g[: len(poses)], g, rtol=0, atol=1e-10 * np.abs(g).max())
    n_elim = len(elim.starts)
    assert len(read) >= 3 and read[0] > 0
    assert all(r < n_elim for r in read[1:])  # later rebuilds read only part of what they eliminate


def test_indefinite_window_is_solved_without_a_rebuild(monkeypatch):
    """When the Cholesky factorisation of the window fails (a numerically indefinite
    pose Schur complement, as on long real sequences), the window is solved by LDL^T and
    stays valid: no rebuild, no fallback."""
    import eifslam.estimation.window as incmod

    sc, m = scene(20, 9)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    real = incmod.cho_factor
    calls = {"n": 0}

    def flaky(A, *args, **kw):
        calls["n"] += 1
        if A.shape[0] > 7 and calls["n"] % 3 == 0:
            raise np.linalg.LinAlgError("not positive definite (simulated)")
        return real(A, *args, **kw)

    monkeypatch.setattr(incmod, "cho_factor", flaky)
    diffs = []
    run_slam(sc, m, f, on_frame=lambda k, filt: diffs.append(
        rel_err(filt.x[filt.incremental.active_indices], full_solve(filt)[filt.incremental.active_indices])))
    st = f.incremental.stats
    assert st.indefinite_solves > 0 and st.fallbacks == 0 and st.rebuilds == 1
    assert max(diffs) < 1e-8
    assert rel_err(f.x, full_solve(f)) < 1e-8


def test_indefinite_poses_to_eliminate_fall_back_to_the_full_solve(monkeypatch):
    """When the poses to eliminate have numerically indefinite information (a LinAlgError
    in the elimination), the frame is
    solved by the full sparse solve and the window rebuilt: the run goes on, exact."""
    import eifslam.estimation.window as winmod  # the window's eliminations call its pose_cholesky

    sc, m = scene(40, 3)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    real = winmod.pose_cholesky
    calls = {"n": 0}

    def flaky(A):  # every second elimination of poses meets an indefinite block
        calls["n"] += 1
        return real(-A if calls["n"] % 2 == 0 else A)

    monkeypatch.setattr(winmod, "pose_cholesky", flaky)
    diffs = []

    def check(k, filt):
        a = filt.incremental.active_indices if filt.incremental.valid else slice(None)
        diffs.append(rel_err(filt.x[a], full_solve(filt)[a]))

    run_slam(sc, m, f, on_frame=check)
    st = f.incremental.stats
    assert calls["n"] >= 4 and st.fallbacks >= 2 and st.rebuilds >= 2
    assert max(diffs) < 1e-8
    assert rel_err(f.x, full_solve(f)) < 1e-8


def test_loop_closure_too_costly_to_reactivate_restarts_the_window_from_one_factorisation():
    """A loop closure whose re-activation would cost more than a full solve (forced here
    by the cost model) rebuilds the window from one sparse factorisation: the whole
    estimate equals the full and the dense solve at that frame, and the frames after it
    run on a small window again, exact, without another fallback."""
    sc, m = scene(40, 3)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    inc = f.incremental
    diffs, before, windows, at_loop = [], [], [], {}

    def check(k, filt):
        if k == 25:
            st = inc.stats
            react, rebuilds = st.reactivations, st.rebuilds
            inc.full_solve_flops_per_entry, inc.min_rebuild_flops = 0.0, 0.0  # re-activating costs too much
            q, t = true_relative(sc, 1, k)
            filt.fuse_relative([RelativePose(1, k, q, t, m.model.rel_cov)])
            filt.recover_active()
            assert st.fallbacks == 1 and st.rebuilds == rebuilds + 1 and st.reactivations == react
            I = filt.information_matrix().toarray()
            x_dense = np.linalg.solve(I, filt.information_vector())
            at_loop.update(full=rel_err(filt.x, full_solve(filt)), dense=rel_err(filt.x, x_dense),
                           window=len(inc.active_indices), dim=filt.dim)
            inc.full_solve_flops_per_entry, inc.min_rebuild_flops = 2e4, 1e9
        (windows if k > 25 else before).append(len(inc.active_indices))
        a = inc.active_indices
        diffs.append(rel_err(filt.x[a], full_solve(filt)[a]))

    run_slam(sc, m, f, on_frame=check)
    assert at_loop["full"] < 1e-8 and at_loop["dense"] < 1e-8  # every state, not only the window
    assert at_loop["window"] < 0.5 * at_loop["dim"]
    assert max(diffs) < 1e-8
    assert inc.stats.fallbacks == 1  # the frames after the loop: no further rebuild
    assert max(windows) < 0.5 * f.dim and max(windows) <= 1.5 * max(before)  # the window as it was
    assert rel_err(f.x, np.linalg.solve(f.information_matrix().toarray(), f.information_vector())) < 1e-8


def test_cheap_reactivation_is_preferred_and_costly_one_is_not():
    """The cost model: re-activating a pose eliminated one step ago is cheaper than a
    rebuild; bringing back the first pose of a long run is costlier when a full solve is
    priced low."""
    sc, m = scene(25, 4)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    inc = f.incremental
    offs = [f.layout.pose_offset(k) for k in f.layout.pose_ids]
    marg = [o for o in offs if o not in set(inc.active_indices.tolist())]
    near, far = inc.plan_reactivation(np.array([marg[-1]])), inc.plan_reactivation(np.array([marg[0]]))
    assert 0 < inc.reactivation_flops(near) < inc.reactivation_flops(far)
    assert len(far.poses) > len(near.poses)
    assert inc.reactivation_flops(far) < inc.rebuild_flops()  # small state: floor of 1e9


def test_pose_batch_undone_in_part_restores_the_window_exactly():
    """Re-activating one pose of a batch of several brings back that pose alone (with
    the separator it needs); the rest stays eliminated, with the pose in its separator,
    and both the window and the back-substituted estimate equal the full solve."""
    sc, m = scene(25, 4)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    inc = f.incremental
    f.recover_active()  # nothing new: the whole window leaves in one batch
    assert len(inc.active_indices) == 0
    x_before = full_solve(f)
    last = f.layout.pose_offset(f.layout.pose_ids[-1])
    batch = inc.conditionals[inc.conditionals.owner[last]]
    n_batch = len(batch.idx) // 7
    assert n_batch > 2
    assert inc.reactivate(np.array([batch.idx[0]]))
    assert len(inc.window.pidx) == 7 and inc.window.pidx[0] == batch.idx[0]  # that pose alone
    inc.window.solve()
    assert rel_err(inc.window.xp, x_before[inc.window.pidx]) < 1e-8
    x = f.x.copy()
    inc.full_solution(x)
    assert rel_err(x, x_before) < 1e-8
    # and again: the pose ages out into a batch of its own, the rest of the first
    # batch keeps it in its separator; bringing back another of its poses stays exact
    _old_image_again(f, m, int(f.layout.pose_ids[-2]))
    f.recover_active()
    a = inc.active_indices
    assert rel_err(f.x[a], full_solve(f)[a]) < 1e-8
    f.recover_active()
    f.complete_estimate()
    assert rel_err(f.x, full_solve(f)) < 1e-8
    assert rel_err(f.x, np.linalg.solve(f.information_matrix().toarray(), f.information_vector())) < 1e-8


def test_revisiting_stream_stays_exact_without_rebuild_cascade():
    """A camera walking down a corridor and back (looking ahead both ways), its window
    rebuilt at the turn (as after a loop closure): the way back re-observes states
    eliminated by that rebuild. They are re-activated (batches undone in part), the window equals the full solve at
    every frame, and there is no rebuild after the forced one; with the
    sparse-factorisation rebuild the same stream rebuilds again and again (the cascade
    this avoids)."""
    def run(undoable: int):
        c = corridor_scene(20, np.random.default_rng(11), points_per_metre=12.0)
        back = np.r_[np.arange(20), np.arange(18, 4, -1)]
        sc = SyntheticScene(c.camera, c.positions[back], c.quats[back], c.points)
        fe = SyntheticFrontEnd(sc, 11, map_fraction=1.0)
        f = InformationFilter(sc.camera, recovery="incremental", window=1)
        f.incremental.undoable_rebuild_pose_entries = undoable
        diffs, rebuilds = [], []

        def check(k, filt):
            if k == 19:
                filt.incremental.on_invalidate()  # e.g. I replaced: rebuild at the next frame
            a = filt.incremental.active_indices
            diffs.append(rel_err(filt.x[a], full_solve(filt)[a]))
            rebuilds.append(filt.incremental.stats.rebuilds)

        run_slam(sc, fe, f, on_frame=check)
        return f, diffs, rebuilds

    f, diffs, rebuilds = run(2100)
    st = f.incremental.stats
    assert max(diffs) < 1e-8
    assert rebuilds[-1] == 2 and st.fallbacks == 0  # the first frame and the forced one
    assert st.reactivations > 0
    assert rel_err(f.x, full_solve(f)) < 1e-8
    g, gdiffs, grebuilds = run(0)
    assert max(gdiffs) < 1e-8
    # the sparse factorisation cannot be undone: the Zm of the states it eliminated wait
    # (Mapper.fuse_zm) instead of rebuilding the window again at every frame
    assert grebuilds[-1] == rebuilds[-1]
def test_window_feature_covariances_equal_dense_inverse(incremental_run):
    """The window's marginal covariance of each active feature is the block of ``I^-1``;
    features outside the window are NaN (not available cheaply)."""
    _, _, f, _, _ = incremental_run
    fids = np.array(f.layout.feature_ids)
    C = f.feature_covariances(np.concatenate([fids, fids[:3], [10**9]]))  # repeats and an unknown id
    assert C.shape == (len(fids) + 4, 3, 3)
    have = np.isfinite(C[: len(fids), 0, 0])
    assert 0 < have.sum() < len(fids) and np.isnan(C[-1]).all()
    np.testing.assert_array_equal(C[len(fids): -1], C[:3])
    Iinv = np.linalg.inv(f.information_matrix().toarray())
    for t, c in zip(fids[have], C[: len(fids)][have]):
        cols = f.layout.feature_columns([t])[0]
        np.testing.assert_allclose(c, Iinv[np.ix_(cols, cols)], rtol=1e-6, atol=1e-12)


def test_window_feature_propagate_equals_dense(incremental_run):
    """``G P G^T`` from the window equals the dense one over the window's features, the
    others counting as exact."""
    _, _, f, _, _ = incremental_run
    fids = np.array(f.layout.feature_ids)
    active = np.isfinite(f.feature_covariances(fids)[:, 0, 0])
    n = min(20, int(active.sum()))
    assert n >= 5 and (~active).sum() >= 5
    pick = np.concatenate([fids[active][:n], fids[~active][:5]])
    G = np.random.default_rng(1).normal(size=(6, 3 * len(pick)))
    out = f.feature_propagate(pick, G)
    cols = f.layout.feature_columns(pick[:n]).ravel()
    Iinv = np.linalg.inv(f.information_matrix().toarray())
    Ga = G[:, : 3 * n]
    ref = Ga @ Iinv[np.ix_(cols, cols)] @ Ga.T
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-12 * np.abs(ref).max())
    assert np.all(f.feature_propagate([10**9], np.ones((2, 3))) == 0)


def test_window_joint_propagate_of_poses_and_features_equals_dense(incremental_run):
    """``G P G^T`` over a pose and features together (their cross-covariance included)
    equals the dense one; a pose outside the window gives None."""
    _, _, f, _, _ = incremental_run
    fids = np.array(f.layout.feature_ids)
    active = np.isfinite(f.feature_covariances(fids)[:, 0, 0])
    pick = np.concatenate([fids[active][:15], fids[~active][:3]])
    poses = [int(p) for p in f.layout.pose_ids]
    k_last = poses[-1]
    G = np.random.default_rng(2).normal(size=(5, 7 + 3 * len(pick)))
    out = f.propagate([k_last], pick, G)
    cols = np.concatenate([f.layout.pose_columns([k_last]).ravel(), f.layout.feature_columns(pick[:15]).ravel()])
    Iinv = np.linalg.inv(f.information_matrix().toarray())
    Ga = G[:, : 7 + 45]
    ref = Ga @ Iinv[np.ix_(cols, cols)] @ Ga.T
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())
    # the cross terms matter: the pose and the features apart give another answer
    apart = G[:, :7] @ Iinv[np.ix_(cols[:7], cols[:7])] @ G[:, :7].T + f.feature_propagate(pick, G[:, 7:])
    assert np.abs(apart - ref).max() > 1e-3 * np.abs(ref).max()
    assert f.propagate([poses[0]], pick, G) is None  # the first pose left the window long ago
    assert f.propagate([10**9], pick, G) is None  # not a pose of the state


def test_joint_propagate_with_full_recovery_equals_dense():
    """With full recovery the joint ``G P G^T`` comes from the cached factorisation: the
    dense one over every state asked for (no window: nothing counts as exact)."""
    sc, m = scene(12, 5)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="full"))
    fids = np.array(f.layout.feature_ids)[::7][:10]
    poses = [int(p) for p in f.layout.pose_ids][-2:]
    G = np.random.default_rng(5).normal(size=(4, 14 + 3 * len(fids)))
    out = f.propagate(poses, fids, G)
    cols = np.concatenate([f.layout.pose_columns(poses).ravel(), f.layout.feature_columns(fids).ravel()])
    ref = G @ np.linalg.inv(f.information_matrix().toarray())[np.ix_(cols, cols)] @ G.T
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())


def test_states_measured_while_the_window_is_invalid_stay_in_its_rebuild():
    """Measurements fused after ``I`` was replaced (a loop's ``Zm`` of old features after
    the estimate was moved) count as measurements: the rebuild keeps their states in the
    window, so measuring them again next does not rebuild once more. Relinearising every
    stored measurement does not count: the window stays as small as after a plain rebuild."""
    sc, m = scene(15, 5)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    f.incremental.undoable_rebuild_pose_entries = 0  # one factorisation: a fallback would rebuild
    smooth(f, max_passes=1)  # relinearised: the window is invalid
    f.recover_rebuilt()
    f.relinearise()
    _old_image_again(f, m, 2)  # old features measured while the window is invalid
    f.recover_rebuilt()
    st = f.incremental.stats
    rebuilds = st.rebuilds
    old = f.layout.feature_columns(zm(m, 2).feature[f.layout.has_features(zm(m, 2).feature)]).ravel()
    a = f.incremental.active_indices
    feats = a[np.isin(a, f.index_sets()[1])]
    np.testing.assert_array_equal(np.sort(feats), np.sort(old))  # those, and no other feature
    _old_image_again(f, m, 2)
    f.recover_active()
    assert st.rebuilds == rebuilds and st.fallbacks == 0
    f.complete_estimate()
    assert rel_err(f.x, full_solve(f)) < 1e-8


def test_add_split_sums_to_what_add_gives():
    """``add_split`` (the relinearised ``Zm``: pose-pose and feature-feature sub-blocks
    summed per pose and per feature before they become triplets) gives the ``I`` and ``i``
    that ``add`` gives block by block, with fewer triplets, and reports the blocks to the
    listeners as ``add`` does."""
    from eifslam.estimation.incremental import TrackedInformationStore
    from eifslam.estimation.information import InformationStore

    rng = np.random.default_rng(3)
    n_obs, dim = 3000, 7 * 40 + 3 * 400
    pose = rng.integers(0, 40, n_obs) * 7
    feat = 7 * 40 + rng.integers(0, 400, n_obs) * 3
    idx = np.concatenate([pose[:, None] + np.arange(7), feat[:, None] + np.arange(3)], 1)
    A = rng.normal(size=(n_obs, 10, 2))
    Lam, eta = A @ np.swapaxes(A, 1, 2), rng.normal(size=(n_obs, 10))
    ref, new = InformationStore(), TrackedInformationStore()
    ref.grow(dim)
    new.grow(dim)
    seen = []
    new.listeners.append(type("L", (), {"on_add": lambda self, *a: seen.append(a), "on_invalidate": lambda self: None})())
    ref.add(idx, Lam, eta)
    new.add_split(idx, Lam, eta, 7)
    assert len(new.pending_triplets()[0]) < 0.5 * len(ref.pending_triplets()[0])
    D = (ref.matrix() - new.matrix()).toarray()
    assert np.abs(D).max() <= 1e-12 * abs(ref.matrix()).max()
    np.testing.assert_allclose(new.vector, ref.vector, rtol=0, atol=1e-12 * np.abs(ref.vector).max())
    assert len(seen) == 1 and seen[0][0] is idx
    # the CSR view (the CSC arrays of the symmetric I read as rows) is I to rounding
    for store in (ref, new):
        R = store.matrix_csr()
        assert R.format == "csr" and R.shape == (dim, dim)
        assert np.abs((R - store.matrix()).toarray()).max() <= 1e-12 * abs(store.matrix()).max()


def _corridor_and_back() -> tuple[Slam, InformationFilter, int]:
    """A filter-mode run down a 20-frame corridor and back to frame 5 (frames seeing
    features the recovery marginalised on the way down): the Slam, its filter, the frames."""
    c = corridor_scene(20, np.random.default_rng(11), points_per_metre=12.0)
    back = np.r_[np.arange(20), np.arange(18, 4, -1)]
    sc = SyntheticScene(c.camera, c.positions[back], c.quats[back], c.points)
    fe = SyntheticFrontEnd(sc, 11, map_fraction=1.0)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    return Slam(sc.camera, fe.slam_config().replace(smoothing={"mode": "filter"}), frontend=fe, backend=f), f, len(back)


def test_zm_of_marginalised_features_wait_and_are_all_fused_at_the_end(monkeypatch):
    """On the way back down the corridor the frames see features the recovery has
    marginalised; where taking them back would cost a rebuild (forced here: on a short
    corridor re-activation is cheap) their ``Zm`` wait (no re-activation, no rebuild for
    them), and ``Slam.finish`` fuses every one of them, after which the estimate is the
    full solve of the information holding them all."""
    monkeypatch.setattr(IncrementalRecovery, "reactivation_affordable", lambda self, starts: False)
    slam, f, n_frames = _corridor_and_back()
    for k in range(n_frames):
        slam.track(k)
    stored = sum(len(b) for b in f.store.features)
    assert f.incremental.stats.reactivations == 0 and f.incremental.stats.fallbacks == 0
    n_wait = slam.mapper.deferred
    assert n_wait > 50
    slam.finish(retry=False)
    assert sum(len(b) for b in f.store.features) >= stored + 0.9 * n_wait  # fused (a few may fail the gate)
    assert slam.mapper.deferred == 0
    f.complete_estimate()
    assert rel_err(f.x, full_solve(f)) < 1e-8


def test_zm_fused_late_leave_their_features_out_of_the_window(monkeypatch):
    """A revisit's waiting ``Zm`` are fused as late measurements: the solve after them is
    still the full solve of the information, but the old features stay out of the active
    window, so their next ``Zm`` wait again instead of pulling the old poses into it."""
    monkeypatch.setattr(IncrementalRecovery, "reactivation_affordable", lambda self, starts: False)
    monkeypatch.setattr(IncrementalRecovery, "reactivation_flops", lambda self, plan: np.inf)  # as after a lap
    slam, f, n_frames = _corridor_and_back()
    k = 0
    while slam.mapper.deferred < 30:
        slam.track(k)
        k += 1
    waiting = slam.mapper.deferred_features()
    assert slam.mapper.flush_deferred() > 0 and slam.mapper.deferred == 0
    f.recover_active()
    assert f.incremental.stats.fallbacks >= 1  # the late Zm needed the whole state solved
    starts = f.layout.feature_columns(waiting)[:, 0]
    assert not np.any(f.incremental.window.pos[starts] >= 0)  # none of them came back
    f.complete_estimate()
    assert rel_err(f.x, full_solve(f)) < 1e-8
    slam.track(k)
    assert slam.mapper.deferred > 0  # their next Zm wait again
