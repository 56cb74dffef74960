"""The covisibility counts (system/covisibility.py) against counting each track's frame set."""

import numpy as np
import pytest

from eifslam.system.covisibility import Covisibility


def _reference(frames: dict[int, set[int]], ids) -> dict[int, int]:
    seen = [f for t in np.asarray(ids, np.int64).reshape(-1).tolist() for f in frames.get(t, ())]
    f, n = np.unique(np.array(seen, np.int64), return_counts=True)
    return dict(zip(f.tolist(), n.tolist()))


@pytest.mark.parametrize("merge_every", [1, 7, 10_000])
def test_counts_equal_the_frame_sets_whatever_is_merged(merge_every):
    rng = np.random.default_rng(0)
    cv = Covisibility(merge_every=merge_every)
    frames: dict[int, set[int]] = {}
    for step in range(400):  # pairs arrive in any frame order, some twice
        t, k = int(rng.integers(0, 60)), int(rng.integers(0, 40))
        added = cv.add(t, k)
        assert added == (k not in frames.get(t, set()))
        frames.setdefault(t, set()).add(k)
        if step % 37 == 0:
            ids = rng.integers(-2, 70, size=int(rng.integers(0, 30)))  # unknown, negative and repeated ids
            assert cv.count(ids) == _reference(frames, ids)
    for t in range(60):
        assert cv.frames_of(t) == frames.get(t, set())
    ids = np.arange(-1, 65).reshape(2, -1)
    got = cv.count(ids)
    assert got == _reference(frames, ids) and list(got) == sorted(got)


def test_nothing_recorded_counts_nothing():
    assert Covisibility().count([0, 3, 5]) == {}
    assert Covisibility().count([]) == {}
