"""Front end on images: config, bad input, tracks, the Ωp/Ωm split, degenerate input,
relocalisation, a few real frames of kitti-seq1 against ground truth, and the windowed
first match on 7-Scenes."""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from eifslam.geometry.camera import PinholeCamera
from eifslam.errors import ConfigError, EstimatorError, ImageError
from eifslam.frontend import FrontEnd, FrontEndConfig, Reason
from eifslam.geometry.rotations import quat_to_rotmat, quat_xyzw_to_wxyz, rotvec_exp

CAM = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
# a small front end, quick on these synthetic images: 1000 features, previous frame only.
SMALL = FrontEndConfig(max_features=1000, match_window=1, map_fraction=0.3)


def _texture(rng: np.random.Generator, w: int = 1400, h: int = 1100) -> np.ndarray:
    """A blob texture with structure at several scales (many keypoints for any detector)."""
    img = np.zeros((h, w), np.float32)
    for cell, amp in ((8, 0.5), (24, 0.35), (64, 0.25)):
        small = rng.random((h // cell + 2, w // cell + 2)).astype(np.float32)
        img += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)[:h, :w]
    img = (img - img.min()) / (img.max() - img.min())
    return (255 * img).astype(np.uint8)


def _rotated_view(tex: np.ndarray, yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """The camera CAM looking at the texture as a plane at infinity, rotated: an exact
    pure-rotation homography, so any epipolar geometry fits and parallax is zero."""
    Kt = np.array([[500.0, 0, tex.shape[1] / 2], [0, 500.0, tex.shape[0] / 2], [0, 0, 1]])
    R = rotvec_exp(np.radians([pitch_deg, yaw_deg, 0.0]))
    H = Kt @ R @ np.linalg.inv(CAM.K)  # camera pixel -> texture pixel
    return cv2.warpPerspective(tex, H, (CAM.width, CAM.height), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)


@pytest.fixture(scope="module")
def texture():
    return _texture(np.random.default_rng(0))


def test_config_rejects_bad_values_naming_the_key():
    with pytest.raises(ConfigError, match="detector"):
        FrontEndConfig(detector="harris")
    with pytest.raises(ConfigError, match="map_fraction"):
        FrontEndConfig(map_fraction=1.5)
    with pytest.raises(ConfigError, match="sigma_px"):
        FrontEndConfig(sigma_px=0.0)
    with pytest.raises(ConfigError, match="frontend.match_window"):
        FrontEndConfig(match_window=0)
    with pytest.raises(ConfigError, match="bogus"):
        FrontEndConfig.from_dict({"bogus": 1})
    assert FrontEndConfig.from_dict({"detector": "orb"}).detector == "orb"


def test_akaze_detects_or_is_a_config_error():
    """AKAZE comes with the contrib wheel the package depends on; an OpenCV without it
    gives a one-line ConfigError naming the detector and the package that has it."""
    from eifslam.frontend.features import akaze_factory

    if akaze_factory() is None:
        with pytest.raises(ConfigError, match="akaze.*opencv-contrib"):
            FrontEnd(CAM, FrontEndConfig(detector="akaze"))
        return
    img = (np.random.default_rng(0).random((CAM.height, CAM.width)) * 255).astype(np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 2.0)
    f = FrontEnd(CAM, FrontEndConfig(detector="akaze", max_features=200)).detect(img)
    assert 0 < len(f) <= 200 and f.descriptors.dtype == np.uint8


def test_surf_is_not_offered():
    with pytest.raises(ConfigError, match="detector"):
        FrontEndConfig(detector="surf")


def test_bad_images_raise_image_error():
    fe = FrontEnd(CAM, SMALL)
    with pytest.raises(ImageError, match="None"):
        fe.add_frame(None, 0)
    with pytest.raises(ImageError, match="dtype"):
        fe.add_frame(np.zeros((480, 640), np.int32), 0)
    with pytest.raises(ImageError, match="shape"):
        fe.add_frame(np.zeros((480, 640, 2), np.uint8), 0)
    with pytest.raises(ImageError, match="camera"):
        fe.add_frame(np.zeros((240, 320), np.uint8), 0)
    with pytest.raises(ImageError, match="numpy"):
        fe.add_frame([[0, 1]], 0)
    with pytest.raises(EstimatorError):
        fe.frame(0)


def test_black_image_is_a_value(texture):
    fe = FrontEnd(CAM, SMALL)
    r0 = fe.add_frame(_rotated_view(texture, 0.0), 0)
    r1 = fe.add_frame(np.zeros((480, 640, 3), np.uint8), 1)
    assert r0.ok and r0.n_features > 500
    assert not r1.ok and r1.reason == Reason.NO_FEATURES and r1.n_features == 0
    f = fe.frame(1)
    assert f.uv.shape == (0, 2) and f.track_ids.dtype == np.int64 and f.colors.shape == (0, 3)
    rp = fe.relative_pose(0, 1)
    assert not rp.ok and rp.reason == Reason.TOO_FEW_COMMON and rp.measurement is None
    r2 = fe.add_frame(np.full((480, 640), 0.5, np.float32), 2)  # textureless, float input
    assert not r2.ok and r2.reason == Reason.NO_FEATURES
    with pytest.raises(EstimatorError):
        fe.add_frame(_rotated_view(texture, 0.0), 2)  # id already used


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_tracks_and_split_over_a_sequence(texture, detector):
    cfg = FrontEndConfig(detector=detector, match_window=2, map_fraction=0.3)
    fe = FrontEnd(CAM, cfg)
    for k in range(6):
        image = _rotated_view(texture, 1.5 * k, 0.5 * k)
        if k == 3:  # a lost frame: tracks resume from frame 2 through the match window
            image = np.zeros_like(image)
        res = fe.add_frame(image, k)
        assert res.ok == (k != 3)
        assert set(res.timings_ms) == {"detect", "match"}
    flags: dict[int, bool] = {}
    for k in range(6):
        f = fe.frame(k)
        assert len(np.unique(f.track_ids)) == len(f.track_ids)  # one keypoint per track
        for t, m in zip(f.track_ids.tolist(), f.in_map.tolist()):
            assert flags.setdefault(t, m) == m  # a track never changes set
        ids_m, uv_m = fe.map_observations(k)
        assert np.all(np.isin(ids_m, f.track_ids[f.in_map])) and len(ids_m) == f.in_map.sum()
    omega_m = {t for t, m in flags.items() if m}
    omega_p = {t for t, m in flags.items() if not m}
    assert not omega_m & omega_p
    frac = len(omega_m) / len(flags)
    assert 0.25 < frac < 0.35
    # tracks recovered across the black frame; matches are geometrically consistent
    ids, u2, u4 = fe.common_tracks(2, 4)
    assert len(ids) > 100
    ids_p, _, _ = fe.common_tracks(2, 4, in_map=False)
    ids_m, _, _ = fe.common_tracks(2, 4, in_map=True)
    assert len(ids_p) + len(ids_m) == len(ids) and len(ids_m) > 0.15 * len(ids)
    H, _ = cv2.findHomography(u2, u4, 0)
    pred = cv2.perspectiveTransform(u2.reshape(-1, 1, 2), H).reshape(-1, 2)
    # no gross outliers in tracks (ORB keypoints of coarse pyramid levels are off by ~2 px)
    assert np.percentile(np.linalg.norm(pred - u4, axis=1), 99) < 5.0
    # pure rotation: a value, with the reason
    rp = fe.relative_pose(0, 1)
    assert not rp.ok and rp.reason == Reason.NO_PARALLAX and 0 <= rp.parallax_deg < 0.3
    assert fe.map_observations(0, min_track_length=2)[0].size < fe.map_observations(0)[0].size


@pytest.mark.parametrize("config", [SMALL, FrontEndConfig()], ids=["small", "defaults"])
def test_repeated_frame_has_no_parallax(texture, config):
    """The same view twice (a camera standing still): the five-point RANSAC has no model
    (every translation fits), so the matches are checked by a homography instead and the
    pair is a value, no parallax. Before, the frame kept no match at the defaults (and
    with the small front end once the gain normalisation changed its keypoints)."""
    fe = FrontEnd(CAM, config)
    img = _rotated_view(texture, 2.0)
    fe.add_frame(img, 0)
    res = fe.add_frame(img.copy(), 1)
    assert res.ok and res.n_matches > 300
    rp = fe.relative_pose(0, 1)
    assert not rp.ok and rp.reason == Reason.NO_PARALLAX
    assert fe.relative_pose(1, 1).reason == Reason.SAME_FRAME


def test_relocalise_restores_identity(texture):
    fe = FrontEnd(CAM, SMALL)
    fe.add_frame(_rotated_view(texture, 0.0), 0)
    other = _texture(np.random.default_rng(1))
    fe.add_frame(_rotated_view(other, 0.0), 1)  # another place: tracking lost
    res = fe.add_frame(_rotated_view(texture, 1.0), 2)
    assert not res.ok and res.reason == Reason.TOO_FEW_MATCHES
    assert len(fe.common_tracks(0, 2)[0]) == 0
    found = fe.relocalise(2, [1, 0])
    assert found[0] == (1, 0) and found[1][0] == 0 and found[1][1] > 300
    ids, _, _ = fe.common_tracks(0, 2)
    assert len(ids) > 0.8 * found[1][1]
    assert np.all(ids < len(fe.frame(0).track_ids))  # the older (frame 0) identities won
    for k in range(3):
        t = fe.frame(k).track_ids
        assert len(np.unique(t)) == len(t)
    fe.forget(0)
    assert fe.relocalise(2, [0]) == [(0, 0)]
    assert len(fe.frame(0).uv) > 0


def _load_kitti(d, n):
    import yaml

    c = yaml.safe_load((d / "camera.yaml").read_text())
    cam = PinholeCamera(c["fx"], c["fy"], c["cx"], c["cy"], c["width"], c["height"], tuple(c["distortion"]))
    files = sorted((d / "images").iterdir())[:n]
    gt = np.loadtxt(d / "groundtruth.tum")[:n]
    return cam, [cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files], gt


@pytest.mark.data
def test_kitti_relative_poses_against_ground_truth(shared_dataset):
    cam, images, gt = _load_kitti(shared_dataset("kitti-seq1/images").parent, 4)
    fe = FrontEnd(cam)
    rot_err, dir_err = [], []
    for k, img in enumerate(images):
        assert fe.add_frame(img, k).ok
        if k == 0:
            continue
        rp = fe.relative_pose(k - 1, k)
        assert rp.ok, rp.reason
        m = rp.measurement
        assert (m.i, m.j) == (k - 1, k) and rp.n_inliers > 100
        Ri = quat_to_rotmat(quat_xyzw_to_wxyz(gt[k - 1, 4:]))
        Rj = quat_to_rotmat(quat_xyzw_to_wxyz(gt[k, 4:]))
        t = Ri.T @ (gt[k, 1:4] - gt[k - 1, 1:4])
        dR = quat_to_rotmat(m.q_ij).T @ (Ri.T @ Rj)
        rot_err.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        dir_err.append(np.degrees(np.arccos(np.clip(m.t_ij @ t / np.linalg.norm(t), -1, 1))))
        sd = np.sqrt(np.diag(m.cov))
        assert np.all(sd > 0) and np.degrees(sd[:3]).max() < 0.5
    assert 0.0 < np.median(rot_err) < 0.3
    assert 0.0 < np.median(dir_err) < 2.0


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_reobserve_finds_lost_map_tracks_where_predicted_only(texture, detector):
    """Frame 2 shows frame 0's view again but tracking (window 1) only sees frame 1, an
    unrelated view: every keypoint starts a new track. The guided search (radius 5 px)
    gives most map tracks their old ids back, on their own keypoints, when predicted where
    they are or 4.2 px off. Predicted 5.7 px off, the track's own keypoint is just outside
    the window: SIFT finds almost none, ORB mostly the same corners detected at another
    pyramid level (a few pixels from the track's own); predicted 40 px off, almost none."""
    def run(offset_px: float) -> tuple[int, int, np.ndarray]:
        """Tracks found, map tracks of frame 0, and the distances of the found keypoints to
        the tracks' own."""
        fe = FrontEnd(CAM, FrontEndConfig(detector=detector, match_window=1, max_features=1500))
        a = _rotated_view(texture, 0.0)
        fe.add_frame(a, 0)
        fe.add_frame(_rotated_view(_texture(np.random.default_rng(1)), 0.0), 1)  # another scene
        fe.add_frame(a.copy(), 2)
        ids0, uv0 = fe.map_observations(0)
        assert not np.isin(ids0, fe.frame(2).track_ids).any()  # lost by tracking
        found = fe.reobserve(2, ids0, uv0 + offset_px, radius_px=5.0)
        ids2, uv2 = fe.map_observations(2)
        back = np.isin(ids2, ids0)
        assert back.sum() == found
        where = {t: u for t, u in zip(ids0.tolist(), uv0)}
        return found, len(ids0), np.array([np.linalg.norm(where[t] - u) for t, u in zip(ids2[back].tolist(),
                                                                                        uv2[back])])

    for offset in (0.0, 3.0):
        found, n, dist = run(offset)
        assert 0.6 * n <= found <= n and np.median(dist) < 0.5
    found, n, dist = run(4.0)
    if detector == "sift":
        assert found <= 0.02 * n
    else:
        assert found <= 0.3 * n and np.median(dist) < 3.0
    assert run(40.0)[0] <= 0.02 * n


def _blob_image(sigma: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian blobs of ``sigma`` px at random sub-pixel centres ``(N, 2)`` on a grid
    (``CAM``'s size, uint8), each drawn within 5 sigma of its centre."""
    rng = np.random.default_rng(seed)
    img = np.full((CAM.height, CAM.width), 40.0)
    step = int(8 * sigma) + 10
    centres = np.array([(x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5))
                        for y in range(step, CAM.height - step, step) for x in range(step, CAM.width - step, step)])
    r = int(5 * sigma) + 2
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    for x, y in centres:
        xi, yi = int(x), int(y)
        img[yi - r : yi + r + 1, xi - r : xi + r + 1] += 180.0 * np.exp(
            -((xx + xi - x) ** 2 + (yy + yi - y) ** 2) / (2.0 * sigma**2))
    return np.clip(img, 0, 255).astype(np.uint8), centres


def test_sift_keypoints_of_rendered_blobs_against_their_centres():
    """Gaussian blobs at known sub-pixel centres (sigma 1.5-6 px, so that the doubled
    first octave and the next two find them): OpenCV's upscaling of the first octave
    shifts every SIFT keypoint by about a quarter pixel right and down (a bias common to
    every frame, which a relative pose does not see)."""
    from scipy.spatial import cKDTree

    from eifslam.frontend.features import detect_features, make_detector

    cfg = FrontEndConfig(max_features=2000)
    offsets = []
    for sigma in (1.5, 3.0, 6.0):
        img, centres = _blob_image(sigma)
        f = detect_features(img, CAM, cfg, make_detector(cfg))
        d, i = cKDTree(f.uv_raw).query(centres)
        found = d < 1.0
        assert found.mean() > 0.5, f"sigma {sigma}: {found.sum()} of {len(centres)} blobs found"
        offsets.append(f.uv_raw[i[found]] - centres[found])
    mean = np.concatenate(offsets).mean(axis=0)
    assert np.all((mean > 0.15) & (mean < 0.35)), mean


@pytest.mark.data
def test_windowed_first_match_finds_what_the_whole_frame_search_finds(shared_dataset):
    """On 20 frames of 7-Scenes (30 Hz, hand-held), SIFT: once the motion's prediction has
    held, each frame's first match is searched only in the windows (at most the first
    three frames search the whole image) and finds between nine tenths and one and a half
    times the epipolar inliers a whole-frame search finds on the same pair (the ratio test
    inside a window is not confused by look-alikes elsewhere), nearly all of those among
    them."""
    from eifslam.frontend import matching
    from eifslam.io import open_source

    seq = open_source(shared_dataset("7scenes-redkitchen-a"))
    cfg = FrontEndConfig()
    fe = FrontEnd(seq.camera, cfg)
    whole = []
    search = matching.DescriptorMatcher.match

    def counted(self, d1, d2, free1=None, *args, **kwargs):
        if free1 is None:
            whole.append(len(d1))
        return search(self, d1, d2, free1, *args, **kwargs)

    feats = [fe.match_ahead(fe.detect(seq.load(k))) for k in range(3)]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(matching.DescriptorMatcher, "match", counted)
        feats += [fe.match_ahead(fe.detect(seq.load(k))) for k in range(3, 20)]
    assert len(whole) == 0  # after three frames, windows only
    assert all(np.isfinite(f.motion.radius_px) and f.motion.radius_px < 20.0 for f in feats[3:])
    for prev, f in zip(feats[3:], feats[4:]):
        a = f.ahead
        got = set(zip(a.idx_new[a.inliers].tolist(), a.idx_previous[a.inliers].tolist()))
        i1, i2 = fe.matcher.match(f.descriptors, prev.descriptors, index1=f.index, index2=prev.index)
        _, inl = matching.essential_ransac(prev.uv[i2], f.uv[i1], seq.camera.K, cfg.ransac_threshold_px,
                                           cfg.ransac_confidence, cfg.ransac_method)
        ref = set(zip(i1[inl].tolist(), i2[inl].tolist()))
        assert 1.5 * len(ref) >= len(got) >= 0.9 * len(ref) > 300, (len(got), len(ref))
        assert len(got & ref) >= 0.85 * len(ref), (len(got & ref), len(ref))


def test_a_released_frame_keeps_what_reobservation_needs_only(texture):
    """A frame released (placed between keyframes) keeps its descriptors while in the match
    window and then only those of its keypoints that are a track's last observation: the
    guided search finds as many tracks again as when the frame kept everything, and a
    front end loaded from its saved state keeps those rows that still are."""
    def run(release: bool) -> tuple[FrontEnd, int]:
        fe = FrontEnd(CAM, FrontEndConfig(match_window=1, max_features=1500))
        a = _rotated_view(texture, 0.0)
        fe.add_frame(a, 0)
        if release:
            fe.release(0)
            assert fe.descriptors(0) is not None  # still in the match window
        fe.add_frame(_rotated_view(_texture(np.random.default_rng(1)), 0.0), 1)  # another scene
        fe.add_frame(a.copy(), 2)
        if release:
            assert fe.descriptors(0) is None
        ids0, uv0 = fe.map_observations(0)
        return fe, fe.reobserve(2, ids0, uv0, radius_px=5.0)

    kept, found_kept = run(False)
    released, found_released = run(True)
    assert found_released == found_kept > 100
    gone = released._frames[0].feats.descriptors
    assert gone.size == 0 and gone.base is None  # not a view that keeps the frame's descriptors alive
    back = FrontEnd(CAM, FrontEndConfig(match_window=1, max_features=1500))
    back.load_state_dict(released.state_dict())
    assert back.descriptors(0) is None and set(back._last_desc) == set(released._last_desc)
    rows, d = released._last_desc[0]  # kept when forgotten: every row still a track's last observation
    rows_b, d_b = back._last_desc[0]  # loaded: those that still are (some were found again in frame 2)
    assert 0 < len(rows_b) <= len(rows) and np.isin(rows_b, rows).all()
    assert np.array_equal(d_b, d[np.searchsorted(rows, rows_b)])


def test_forgotten_frames_keep_only_the_track_ends_that_are_still_ends(texture, monkeypatch):
    """Each forget prunes the oldest forgotten frames' descriptors to the rows that are still
    some track's last observation: re-observation finds the same tracks as with nothing
    pruned, and the ends it moved to a later frame are dropped from the older one."""
    others = [_rotated_view(_texture(np.random.default_rng(s)), 0.0) for s in (1, 2, 3, 4)]

    def run(prune: bool) -> tuple[FrontEnd, int]:
        fe = FrontEnd(CAM, FrontEndConfig(match_window=1, max_features=1500))
        if not prune:
            monkeypatch.setattr(fe, "_prune_last_desc", lambda n: None)
        views = [_rotated_view(texture, float(a)) for a in range(4)] + [others[0], _rotated_view(texture, 3.0)]
        for k, img in enumerate(views):
            fe.add_frame(img, k)
            fe.release(k)
        ids3, uv3 = fe.map_observations(3)  # tracks since frame 0, lost in the other scene
        found = fe.reobserve(5, ids3, uv3, radius_px=5.0)  # their ends move from frame 3 to 5
        for k, img in enumerate(others[1:], start=6):
            fe.add_frame(img, k)
            fe.release(k)
        return fe, found

    pruned, found = run(True)
    unpruned, found_unpruned = run(False)
    assert found == found_unpruned > 100
    total = sum(len(r) for r, _ in pruned._last_desc.values())
    assert total < sum(len(r) for r, _ in unpruned._last_desc.values())
    for f, (rows, d) in pruned._last_desc.items():
        assert np.isin(pruned._last_rows(f), rows).all() and len(rows) == len(d)
    pruned._prune_last_desc(len(pruned._last_desc))  # every entry once more: exactly the ends
    for f, (rows, d) in pruned._last_desc.items():
        assert np.array_equal(rows, pruned._last_rows(f))
