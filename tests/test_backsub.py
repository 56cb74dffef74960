"""Back-substitution with merged feature conditionals (estimation/backsub.py) against the
one-by-one back-substitution and the full solve, through re-activations that undo and
split conditionals inside merged chunks."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.estimation import backsub
from eifslam.estimation.filter import InformationFilter
from test_incremental import _old_image_again, full_solve, rel_err, run_slam, scene


def one_by_one(conds, x: np.ndarray) -> np.ndarray:
    for c in reversed(conds):
        if c is not None:
            c.apply(x)
    return x


def test_merged_chunks_equal_one_by_one_and_follow_undone_conditionals(monkeypatch):
    monkeypatch.setattr(backsub, "CHUNK", 8)  # several complete chunks in a short run
    sc, m = scene(40, 7)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    merged_uses, diffs = [], []
    real_apply = backsub._Merged.apply  # noqa: SLF001

    def counting(self, x):
        merged_uses.append(len(self.conds))
        return real_apply(self, x)

    monkeypatch.setattr(backsub._Merged, "apply", counting)  # noqa: SLF001

    def check(k, filt):
        inc = filt.incremental
        if k in (20, 30):  # undo (and split) conditionals of complete, already merged chunks
            _old_image_again(filt, m, k - 12)
            filt.recover_active()
        a = filt.x.copy()
        inc.full_solution(a)
        b = one_by_one(inc.conditionals.slots, filt.x.copy())
        diffs.append(float(np.max(np.abs(a - b))) / max(1.0, float(np.abs(b).max())))

    run_slam(sc, m, f, on_frame=check)
    st = f.incremental.stats
    assert st.reactivations >= 2 and st.rebuilds == 1
    assert len(merged_uses) > 20 and max(merged_uses) > 1
    assert max(diffs) < 1e-13
    assert rel_err(f.x, full_solve(f)) < 1e-8
    assert rel_err(f.x, np.linalg.solve(f.information_matrix().toarray(), f.information_vector())) < 1e-8


def test_a_chunk_is_merged_once_and_again_only_when_its_conditionals_change(monkeypatch):
    monkeypatch.setattr(backsub, "CHUNK", 4)
    sc, m = scene(30, 3)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    inc = f.incremental
    built = []
    real_of = backsub._Merged.of  # noqa: SLF001
    monkeypatch.setattr(backsub._Merged, "of", staticmethod(lambda conds: built.append(len(conds)) or real_of(conds)))  # noqa: SLF001
    inc.conditionals.backsub.clear()
    x1 = inc.full_solution(f.x.copy())
    n_first = len(built)
    assert n_first > 2
    x2 = inc.full_solution(f.x.copy())
    assert len(built) == n_first and np.array_equal(x1, x2)  # cached: nothing merged again
    slot = next(s for s, c in enumerate(inc.conditionals.slots) if c is not None and c.Dinv is not None)
    assert inc.reactivate(np.array([inc.conditionals[slot].idx[0]]))
    inc.window.solve()
    x3 = inc.full_solution(f.x.copy())
    assert n_first < len(built) <= n_first + 1  # the changed chunk alone
    assert rel_err(x3, full_solve(f)) < 1e-8


def test_recent_solution_is_exact_for_the_recent_states_and_leaves_the_older_ones():
    sc, m = scene(40, 7)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    inc = f.incremental
    exact = f.x.copy()
    inc.full_solution(exact)
    assert rel_err(exact, full_solve(f)) < 1e-8
    slots = 10
    stale = np.full(f.dim, 123.0)  # marks what a recent back substitution must not touch
    got = inc.recent_solution(stale.copy(), slots)
    recent = np.zeros(f.dim, bool)
    for c in inc.conditionals.slots[-slots:]:
        if c is not None:
            recent[c.idx] = True
    active = np.zeros(f.dim, bool)
    active[inc.window.pidx] = active[inc.window.fidx] = True
    assert recent.sum() > 0 and (~(recent | active)).sum() > 0
    np.testing.assert_allclose(got[recent | active], exact[recent | active], rtol=1e-9, atol=1e-9)
    assert np.all(got[~(recent | active)] == 123.0)


@pytest.mark.parametrize("recovery", ["incremental", "full"])
def test_local_map_is_the_features_measured_in_the_last_steps(recovery):
    """``local_map`` (from the recovery's bookkeeping) holds exactly the features that
    ``recent_features`` marks among all of them, in state order, at their estimates; with
    the full recovery, every feature."""
    sc, m = scene(40, 7)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery=recovery, window=1))
    ids, X = f.features()
    ids = np.asarray(ids, np.int64)
    for steps in (1, 3, 10, 1000):
        got, Xg = f.local_map(steps)
        want = ids[f.recent_features(ids, steps)]
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(Xg, f.x[f.layout.feature_columns(want)].reshape(-1, 3))
        if recovery == "full":
            np.testing.assert_array_equal(got, ids)
    if recovery == "incremental":
        assert 0 < len(f.local_map(1)[0]) < len(f.local_map(1000)[0]) == len(ids)


def test_recent_solution_reads_of_a_rebuild_only_the_recently_measured_states():
    """A sparse rebuild's conditional holds every state that was old at the rebuild: a
    recent back substitution recovers exactly those of them measured in the last
    ``slots / 2`` steps and leaves the rest as they are."""
    from eifslam.estimation.smoothing import smooth

    sc, m = scene(20, 5)
    f = run_slam(sc, m, InformationFilter(sc.camera, recovery="incremental", window=1))
    inc = f.incremental
    inc.undoable_rebuild_pose_entries = 0  # the rebuild is one sparse factorisation
    inc.rebuild_horizon = 1  # of everything but the states just measured
    smooth(f, max_passes=1)  # I replaced: the next step rebuilds
    _old_image_again(f, m, 12)  # an old frame measured again: its states join the window
    f.recover_active()
    rebuilt = [c for c in inc.conditionals.slots if c is not None and c.factor is not None]
    assert len(rebuilt) == 1 and len(rebuilt[0].cidx)  # conditioned on the window
    exact = f.x.copy()
    inc.full_solution(exact)
    assert rel_err(exact, full_solve(f)) < 1e-8
    slots = 8
    got = inc.recent_solution(np.full(f.dim, 123.0), slots)
    last = inc._last[inc._map.start]  # noqa: SLF001  the step each entry was last measured
    in_rebuild = np.zeros(f.dim, bool)
    in_rebuild[rebuilt[0].idx] = True
    wanted = in_rebuild & (last > inc.stats.steps - slots // 2)
    assert wanted.sum() > 0 and (in_rebuild & ~wanted).sum() > 0
    np.testing.assert_allclose(got[wanted], exact[wanted], rtol=1e-9, atol=1e-9)
    assert np.all(got[in_rebuild & ~wanted] == 123.0)
