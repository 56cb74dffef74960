"""The per-track observation store against a plain reference (dictionary of lists)."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.system import observations
from eifslam.system.observations import TrackObservations


@pytest.mark.parametrize("snapshot_rows", [1, 97, observations.SNAPSHOT_ROWS])
def test_histories_covisibility_forgetting_and_a_round_trip_match_a_plain_reference(monkeypatch, snapshot_rows):
    # snapshots after every row, now and then, and never: sorted slices, walks and both
    monkeypatch.setattr(observations, "SNAPSHOT_ROWS", snapshot_rows)
    rng = np.random.default_rng(0)
    obs, ref = TrackObservations(), {}

    def check(store: TrackObservations) -> None:
        query = np.array([5, 399, 17, 1000, 3, 17], np.int64)  # unknown and repeated ids too
        owner, rows = store.rows_of(query)
        for n, t in enumerate(query.tolist()):
            mine = rows[owner == n]
            want = ref.get(t, [])
            assert store.frames(mine).tolist() == [f for f, _ in want]
            np.testing.assert_array_equal(store.pixels(mine), np.array([u for _, u in want]).reshape(-1, 2))
        some = np.arange(0, 400, 3)
        want: dict[int, int] = {}
        for t in some.tolist():
            for f, _ in ref.get(t, []):
                want[f] = want.get(f, 0) + 1
        assert store.covisible(some) == want
        assert len(store) == sum(len(h) for h in ref.values())

    for frame in range(60):
        tracks = rng.choice(400, int(rng.integers(0, 80)), replace=False)
        uv = rng.normal(size=(len(tracks), 2))
        obs.add(frame, tracks, uv)
        for t, u in zip(tracks.tolist(), uv):
            ref.setdefault(t, []).append((frame, u))
        if frame % 7 == 3:  # a loop's observations: only tracks not yet seen by this frame
            extra = rng.choice(400, 30, replace=False)
            eu = rng.normal(size=(30, 2))
            added = obs.add(frame, extra, eu, only_new=True)
            for t, u, a in zip(extra.tolist(), eu, added):
                assert a == all(f != frame for f, _ in ref.get(t, []))
                if a:
                    ref.setdefault(t, []).append((frame, u))
        if frame % 11 == 5:
            gone = rng.choice(400, 40, replace=False)
            obs.forget(frame, gone)
            for t in gone.tolist():
                ref[t] = [(f, u) for f, u in ref.get(t, []) if f != frame]
        if frame % 13 == 0:
            check(obs)

    check(obs)
    check(TrackObservations.from_arrays(*obs.arrays()))
