"""Descriptor matching: float descriptors are matched exactly (the brute-force ratio test
and cross check) and, above ``EXACT_ROWS``, by FLANN; a frame's index built once and reused
gives the matches the plain matcher gives; rows that are not free are never matched; binary
descriptors are searched exactly; a seeded index is the same whenever it is built; the
guided search finds a descriptor near its prediction only, with the ratio test inside its
window."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from eifslam.frontend import matching
from eifslam.frontend.matching import (MAX_RADIUS_PX, MIN_RADIUS_PX, DescriptorIndex, DescriptorMatcher,
                                      ImageMotion, guided_search, image_motion, lone_candidate_bound, row_distances,
                                      windowed_match)


def _pair(rng, n=600, shared=400, dim=128, noise=0.05, binary=False):
    """Two descriptor sets: ``shared`` rows of ``d1`` are noisy copies of rows of ``d2``
    (in a shuffled order), the others unrelated. Returns d1, d2 and the true partner in
    ``d2`` of each row of ``d1`` (-1 when none)."""
    if binary:
        d2 = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        d1 = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    else:
        d2 = rng.random((n, dim)).astype(np.float32)
        d1 = rng.random((n, dim)).astype(np.float32)
    truth = np.full(n, -1, np.int64)
    src = rng.permutation(n)[:shared]
    dst = rng.permutation(n)[:shared]
    if binary:  # flip a few bits
        flips = rng.random((shared, 32 * 8)) < noise
        d1[dst] = np.packbits(np.unpackbits(d2[src], axis=1) ^ flips, axis=1)
    else:
        d1[dst] = d2[src] + rng.normal(0, noise, (shared, dim)).astype(np.float32)
    truth[dst] = src
    return d1, d2, truth


@pytest.fixture(params=["exact", "flann"])
def search(request, monkeypatch):
    """Both searches of float descriptors: exact, and FLANN (``EXACT_ROWS`` 0)."""
    if request.param == "flann":
        monkeypatch.setattr(matching, "EXACT_ROWS", 0)
    return request.param


def _recall(i1, i2, truth):
    return np.mean(truth[i1] == i2) if len(i1) else 0.0, np.sum(truth[i1] == i2) / np.sum(truth >= 0)


@pytest.mark.parametrize("binary", [False, True])
def test_prebuilt_indices_give_the_plain_matches(binary, search):
    rng = np.random.default_rng(4)
    d1, d2, truth = _pair(rng, binary=binary)
    m = DescriptorMatcher(0.8, True)
    a1, a2 = m.match(d1, d2)
    b1, b2 = m.match(d1, d2, index1=m.index(d1), index2=m.index(d2))
    for i1, i2 in ((a1, a2), (b1, b2)):
        precision, recall = _recall(i1, i2, truth)
        assert 0.97 <= precision <= 1.0 and 0.9 <= recall <= 1.0
        assert len(np.unique(i1)) == len(i1) and len(np.unique(i2)) == len(i2)
    same = len(set(zip(a1, a2)) & set(zip(b1, b2))) / len(set(zip(a1, a2)) | set(zip(b1, b2)))
    assert 0.97 <= same <= 1.0


@pytest.mark.parametrize("with_index", [False, True])
def test_rows_that_are_not_free_are_never_matched(with_index, search):
    rng = np.random.default_rng(5)
    d1, d2, truth = _pair(rng)
    free1 = rng.random(len(d1)) < 0.6
    free2 = rng.random(len(d2)) < 0.6
    m = DescriptorMatcher(0.8, True)
    idx = (m.index(d1), m.index(d2)) if with_index else (None, None)
    i1, i2 = m.match(d1, d2, free1, free2, *idx)
    assert free1[i1].all() and free2[i2].all()
    # the true pairs of two free rows are found (the others are not available)
    possible = free1 & (truth >= 0) & free2[np.maximum(truth, 0)]
    found = np.isin(np.flatnonzero(possible), i1[truth[i1] == i2])
    assert 0.9 <= found.mean() <= 1.0
    assert np.mean(truth[i1] == i2) >= 0.97


def test_free_rows_from_a_full_index_are_the_subset_matches(monkeypatch):
    """The nearest free rows taken from a FLANN search of all rows (prebuilt indices) give
    the matches of a search of the free rows alone, and the exact matches, also where the
    taken rows are the nearer ones (here every taken row of d2 has a near copy in d1)."""
    rng = np.random.default_rng(8)
    d1, d2, truth = _pair(rng, n=800, shared=600, noise=0.08)
    taken2 = np.zeros(len(d2), bool)
    taken2[truth[truth >= 0][:300]] = True  # half of the true partners are taken already
    free1 = rng.random(len(d1)) < 0.8  # rows of d1 whose partner is taken stay free: their nearest is taken
    m = DescriptorMatcher(0.8, True)
    exact = set(zip(*m.match(d1, d2, free1, ~taken2)))
    monkeypatch.setattr(matching, "EXACT_ROWS", 0)
    a = m.match(d1, d2, free1, ~taken2)
    b = m.match(d1, d2, free1, ~taken2, m.index(d1), m.index(d2))
    pa, pb = set(zip(*a)), set(zip(*b))
    assert len(pa) > 200
    assert 0.95 <= len(pa & pb) / len(pa | pb) <= 1.0
    assert 0.95 <= len(pb & exact) / len(pb | exact) <= 1.0


@pytest.mark.parametrize("mutual", [False, True])
def test_exact_matches_are_the_brute_force_ratio_test_and_cross_check(mutual):
    """The exact search of float descriptors gives what OpenCV's brute-force matcher gives
    on the free rows: Lowe's ratio test on the two nearest and, with ``mutual``, the
    nearest of the other side's row."""
    rng = np.random.default_rng(9)
    d1, d2, _ = _pair(rng, n=700, shared=450, noise=0.1)
    free1, free2 = rng.random(len(d1)) < 0.7, rng.random(len(d2)) < 0.8
    r1, r2 = np.flatnonzero(free1), np.flatnonzero(free2)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = bf.knnMatch(d1[r1], d2[r2], k=2)
    back = [m[0].trainIdx for m in bf.knnMatch(d2[r2], d1[r1], k=1)]
    ref = set()
    for i, (a, b) in enumerate(fwd):
        if a.distance < 0.8 * b.distance and (not mutual or back[a.trainIdx] == i):
            ref.add((int(r1[i]), int(r2[a.trainIdx])))
    if not mutual:  # a row of d2 claimed by several rows of d1 goes to the first of them
        first = {}
        for i, j in sorted(ref):
            first.setdefault(j, i)
        ref = {(i, j) for j, i in first.items()}
    got = DescriptorMatcher(0.8, mutual).match(d1, d2, free1, free2)
    assert len(ref) > 250
    assert set(zip(*got)) == ref


def test_binary_search_is_the_brute_force_matcher():
    rng = np.random.default_rng(6)
    d1, d2, _ = _pair(rng, n=300, shared=150, binary=True)
    idx, dist = DescriptorIndex(d2).knn(d1, 2)
    ref = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d1, d2, k=2)
    np.testing.assert_array_equal(dist, [[m.distance for m in r] for r in ref])
    # equal distances may come in either order: the nearest distance is what must agree
    assert np.mean(idx[:, 0] == [r[0].trainIdx for r in ref]) > 0.95
    # AKAZE's 61-byte descriptors: the same Hamming distances as OpenCV's
    a1, a2 = rng.integers(0, 256, (200, 61), dtype=np.uint8), rng.integers(0, 256, (300, 61), dtype=np.uint8)
    _, ad = DescriptorIndex(a2).knn(a1, 2)
    ref_d, _ = cv2.batchDistance(a1, a2, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2)
    np.testing.assert_array_equal(ad, ref_d)
    # fewer rows than asked for: -1 and inf
    few, fd = DescriptorIndex(d2[:1]).knn(d1[:3], 2)
    assert (few[:, 1] == -1).all() and np.isinf(fd[:, 1]).all() and (few[:, 0] == 0).all()


def test_a_seeded_index_is_the_same_whenever_it_is_built(monkeypatch):
    monkeypatch.setattr(matching, "EXACT_ROWS", 0)
    rng = np.random.default_rng(7)
    d1, d2, _ = _pair(rng, n=2000, shared=1000, noise=0.3)
    out = []
    for seed in (3, 3, 4):
        cv2.setRNGSeed(seed)
        index = DescriptorIndex(d2, trees=4, checks=8)  # few checks: the trees matter
        assert index.prebuilt
        index.build()
        out.append(index.knn(d1, 2)[0])
    assert np.array_equal(out[0], out[1])
    assert not np.array_equal(out[0], out[2])  # (the trees do depend on the generator)




@pytest.mark.parametrize("binary", [False, True])
def test_row_distances_are_l2_or_hamming(binary):
    rng = np.random.default_rng(5)
    a, b, _ = _pair(rng, n=50, shared=20, binary=binary)
    norm = cv2.NORM_HAMMING if binary else cv2.NORM_L2
    ref = [cv2.norm(x, y, norm) for x, y in zip(a, b)]
    np.testing.assert_allclose(row_distances(a, b), ref, rtol=1e-5)


def _guided_scene(binary: bool):
    """Keypoints on a 20 px grid with unrelated descriptors (binary ones of 512 bits, whose
    unrelated distances vary little), and queries that are noisy copies of the first 30
    keypoints' descriptors."""
    rng = np.random.default_rng(11)
    xs, ys = np.meshgrid(np.arange(10.0, 630.0, 20.0), np.arange(10.0, 470.0, 20.0))
    uv = np.stack([xs.ravel(), ys.ravel()], 1)
    if binary:
        t = rng.integers(0, 256, (len(uv), 64), dtype=np.uint8)
        q = t[:30].copy()
    else:
        q, t, _ = _pair(rng, n=len(uv), shared=0)
        q = q[:30].copy()
    if binary:
        flips = rng.random((30, t.shape[1] * 8)) < 0.05
        q[:] = np.packbits(np.unpackbits(t[:30], axis=1) ^ flips, axis=1)
    else:
        q[:] = t[:30] + rng.normal(0.0, 0.02, (30, t.shape[1])).astype(np.float32)
    return q, t, uv


@pytest.mark.parametrize("binary", [False, True])
def test_guided_search_finds_a_descriptor_near_its_prediction_only(binary):
    """Predicted 4 px off, each query finds its own keypoint (alone in the window of 12 px,
    and nearer than the bound); predicted 26 or 30 px off, its own keypoint is outside the
    window and the dissimilar keypoints inside are refused: one alone by the bound, two
    by the ratio test."""
    q, t, uv = _guided_scene(binary)
    lone = 0.8 * np.median(row_distances(t[:30], t[30:60]))  # the ratio of unrelated distances
    rows, kp, dist = guided_search(q, uv[:30] + [4.0, 0.0], t, uv, 12.0, 0.8, lone)
    np.testing.assert_array_equal(rows, np.arange(30))
    np.testing.assert_array_equal(kp, np.arange(30))
    np.testing.assert_allclose(dist, row_distances(q, t[:30]))
    for off in (26.0, 30.0):
        assert len(guided_search(q, uv[:30] + [off, 0.0], t, uv, 12.0, 0.8, lone)[0]) == 0


@pytest.mark.parametrize("binary", [False, True])
def test_guided_search_lone_candidates_and_ambiguous_windows(binary):
    """A keypoint alone in its window is taken when nearer than the bound, refused when not;
    two keypoints of the same descriptor in one window fail the ratio test."""
    q, t, uv = _guided_scene(binary)
    d_true = row_distances(q[:5], t[:5])
    rows, kp, _ = guided_search(q[:5], uv[:5] + [0.0, 3.0], t, uv, 5.0, 0.8, 2.0 * d_true.max())
    np.testing.assert_array_equal(kp, np.arange(5))
    assert len(guided_search(q[:5], uv[:5] + [0.0, 3.0], t, uv, 5.0, 0.8, 0.5 * d_true.min())[0]) == 0
    t2 = t.copy()
    t2[1] = t2[0]  # keypoint 1 (20 px to the right) looks like keypoint 0
    rows, _, _ = guided_search(q[:1], uv[:1] + [10.0, 0.0], t2, uv, 12.0, 0.8, 1e9)
    assert len(rows) == 0
    rows, kp, _ = guided_search(q[:1], uv[:1] + [-2.0, 0.0], t2, uv, 12.0, 0.8, 1e9)  # 1 outside
    assert kp.tolist() == [0]


def test_lone_candidate_bound_is_the_ratio_of_a_typical_second_nearest():
    assert lone_candidate_bound(np.zeros((3, 128), np.float32), 0.8) == pytest.approx(240.0)
    assert lone_candidate_bound(np.zeros((3, 32), np.uint8), 0.8) == pytest.approx(0.8 * 44.0)


def _moving_keypoints(rng, n=400, flow=(14.0, -6.0)):
    """An old frame of ``n`` keypoints with unrelated float descriptors of SIFT's norm
    (512, so that the lone-candidate bound applies as to SIFT's), and a new frame
    where 300 of them moved by ``flow`` (1 px noise; descriptors noisy copies, rows
    shuffled) and 100 unrelated keypoints appeared. Returns the old and new descriptors
    and pixels and the true old row of each new row (-1 for none)."""
    uv_old = rng.uniform([0, 0], [640, 480], (n, 2))
    _, d_old, _ = _pair(rng, n=n, shared=0)
    src = rng.permutation(n)[:300]
    d_new = np.concatenate([d_old[src] + rng.normal(0, 0.02, (300, d_old.shape[1])).astype(np.float32),
                            rng.random((100, d_old.shape[1])).astype(np.float32)])
    uv_new = np.concatenate([uv_old[src] + flow + rng.normal(0, 1.0, (300, 2)),
                             rng.uniform([0, 0], [640, 480], (100, 2))])
    truth = np.concatenate([src, np.full(100, -1)])

    def sift_norm(d):
        return (512.0 * d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    return sift_norm(d_old), uv_old, sift_norm(d_new), uv_new, truth


def test_windowed_match_finds_the_keypoints_where_the_motion_predicts_them():
    """Predicted by their motion, the moved keypoints are found again, every match right;
    predicted where they were (the motion 15 px off) with an 8 px window, almost none is
    (a window without the right keypoint holds only unrelated ones, refused); rows that are
    not free are never matched."""
    rng = np.random.default_rng(5)
    d_old, uv_old, d_new, uv_new, truth = _moving_keypoints(rng)
    ia, ib = windowed_match(d_new, uv_new, d_old, uv_old + [14.0, -6.0], 8.0, 0.8)
    assert np.all(truth[ia] == ib) and len(ia) >= 0.95 * 300
    assert np.all(np.diff(ia) > 0) and len(np.unique(ib)) == len(ib)
    ia, ib = windowed_match(d_new, uv_new, d_old, uv_old, 8.0, 0.8)
    assert len(ia) <= 3
    free_new, free_old = rng.random(len(d_new)) < 0.5, rng.random(len(d_old)) < 0.5
    ia, ib = windowed_match(d_new, uv_new, d_old, uv_old + [14.0, -6.0], 8.0, 0.8, free_new, free_old)
    assert np.all(free_new[ia]) and np.all(free_old[ib]) and np.all(truth[ia] == ib)
    both = free_new & (truth >= 0) & free_old[np.maximum(truth, 0)]
    assert len(ia) >= 0.95 * both.sum()


def test_windowed_match_keeps_mutual_nearest_neighbours_only():
    """Two new keypoints near one old keypoint, both passing their own tests: the old one
    goes to the nearer descriptor; and a new keypoint whose nearest old keypoint prefers
    another new keypoint (which failed its ratio test) is not matched."""
    d_old = np.eye(4, 16, dtype=np.float32) * 10.0
    uv_old = np.array([[100.0, 100.0], [300.0, 300.0], [500.0, 100.0], [600.0, 400.0]])
    d_new = np.stack([d_old[0] + 0.1, d_old[0] + 0.5]).astype(np.float32)
    d_new[1, 5] += 0.5
    uv_new = np.array([[101.0, 100.0], [99.0, 101.0]])
    ia, ib = windowed_match(d_new, uv_new, d_old, uv_old, 5.0, 0.8)
    assert ia.tolist() == [0] and ib.tolist() == [0]
    # new 0 is nearest to old 0 but ambiguous (old 4 alike, in its window): old 0 is then
    # the nearest of new 1 too, which it prefers less
    d_old2 = np.concatenate([d_old, d_old[:1] + 0.05]).astype(np.float32)
    uv_old2 = np.concatenate([uv_old, [[103.0, 100.0]]])
    uv_new2 = np.array([[101.0, 100.0], [96.0, 100.0]])
    ia, ib = windowed_match(d_new, uv_new2, d_old2, uv_old2, 5.0, 0.8)
    assert 1 not in ia.tolist()


def test_image_motion_is_the_matches_displacement_and_its_prediction_error():
    """Matched keypoints move by their own displacement, the others by their matched
    neighbours' median. The radius is the 99% quantile of how far the matches landed from
    the previous prediction, at least its lower bound, and infinite (no window) without a
    prediction or when it missed by more than the upper bound. The reference is the matches
    of the last whole-frame search. No motion from fewer than five matches."""
    rng = np.random.default_rng(2)
    uv_prev = rng.uniform([0, 0], [640, 480], (200, 2))
    rows = np.arange(150)
    uv = uv_prev.copy()
    uv[rows] += [10.0, 3.0]
    uv[150:] = rng.uniform([0, 0], [640, 480], (50, 2))
    m0 = image_motion(uv, uv_prev, rows, rows, None, whole_frame=True)
    np.testing.assert_allclose(m0.flow, np.tile([10.0, 3.0], (200, 1)))
    assert m0.radius_px == np.inf and m0.reference == 150
    err = np.abs(rng.normal(0.0, 6.0, 150))  # how far the previous prediction was off, along x
    predicted = np.tile([10.0, 3.0], (200, 1))
    predicted[rows, 0] -= err
    previous = ImageMotion(predicted, 30.0, 400)
    m1 = image_motion(uv, uv_prev, rows, rows, previous, whole_frame=True)
    assert m1.radius_px == pytest.approx(np.clip(np.quantile(err, 0.99), MIN_RADIUS_PX, MAX_RADIUS_PX))
    assert m1.reference == 150
    m2 = image_motion(uv, uv_prev, rows, rows, previous, whole_frame=False)
    assert (m2.radius_px, m2.reference) == (m1.radius_px, 400)
    np.testing.assert_allclose(m2.flow, m0.flow)
    still = ImageMotion(np.tile([10.0, 3.0], (200, 1)), 20.0, 150)
    assert image_motion(uv, uv_prev, rows, rows, still, whole_frame=True).radius_px == MIN_RADIUS_PX
    jolt = ImageMotion(np.tile([10.0 + 1.5 * MAX_RADIUS_PX, 3.0], (200, 1)), 20.0, 150)
    assert image_motion(uv, uv_prev, rows, rows, jolt, whole_frame=True).radius_px == np.inf
    assert image_motion(uv, uv_prev, rows[:4], rows[:4], None, whole_frame=True) is None
