"""The pipelined front end: ``FrontEnd.detect`` / ``add_features``, the
runner's prefetching worker thread, and the cheaper-detection settings.

The pipelined run must give the sequential run's results exactly (detection depends on
the image only; everything else runs in frame order), so the comparisons here are exact.
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from eifslam.errors import ConfigError, EstimatorError, ImageError
from eifslam.frontend import FrontEnd, FrontEndConfig
from eifslam.frontend.features import Features
from eifslam.frontend.matching import essential_ransac
from eifslam.geometry.camera import PinholeCamera
from eifslam.system.config import SlamConfig
from eifslam.system.runner import FramePrefetcher, run_sequence



class _Frames:
    """The minimal sequence ``run_sequence`` needs, over images held in memory."""

    def __init__(self, camera: PinholeCamera, images: list, timestamps) -> None:
        self.camera = camera
        self.images = images
        self.frames = [SimpleNamespace(timestamp=float(t)) for t in timestamps]
        self.loaded: list[int] = []
        self.threads: set[str] = set()

    def __len__(self) -> int:
        return len(self.images)

    def load(self, k: int):
        self.loaded.append(k)
        self.threads.add(threading.current_thread().name)
        img = self.images[k]
        if isinstance(img, Exception):
            raise img
        return img


@pytest.fixture(scope="module")
def scene_frames() -> _Frames:
    """Ten frames of the rendered built-in scene at 320x240 (BGR, as imread gives)."""
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54, width=320, height=240)
    n = 10
    return _Frames(scene.camera, [render_frame(scene, k) for k in range(n)], scene.timestamps[:n])


def _trajectory(run) -> tuple:
    return run.slam.trajectory()


def _same_runs(a, b) -> None:
    assert [r.state for r in a.slam.results] == [r.state for r in b.slam.results]
    assert [r.reason for r in a.slam.results] == [r.reason for r in b.slam.results]
    ta, Pa, Qa = _trajectory(a)
    tb, Pb, Qb = _trajectory(b)
    np.testing.assert_array_equal(ta, tb)
    np.testing.assert_array_equal(Pa, Pb)  # identical, not merely close
    np.testing.assert_array_equal(Qa, Qb)
    ia, Xa, _ = a.slam.map()
    ib, Xb, _ = b.slam.map()
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_array_equal(Xa, Xb)


# -- FrontEnd.detect / add_features ---------------------------------------------------
def _features_equal(f: Features, g: Features) -> None:
    for name in ("uv", "uv_raw", "descriptors", "scale_px", "response", "sign", "colors"):
        np.testing.assert_array_equal(getattr(f, name), getattr(g, name), err_msg=name)


def test_detect_is_pure_and_thread_safe(scene_frames):
    fe = FrontEnd(scene_frames.camera, FrontEndConfig())
    images = scene_frames.images[:4]
    ref = [fe.detect(im) for im in images]
    assert all(len(f) > 100 for f in ref) and all(f.detect_ms > 0 for f in ref)
    # the same images detected by four threads at once, through the same front end
    out: dict[tuple[int, int], Features] = {}
    errors: list[BaseException] = []

    def work(t: int) -> None:
        try:
            for r in range(3):
                for k, im in enumerate(images):
                    out[(t, r * len(images) + k)] = fe.detect(im)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(t,)) for t in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors
    assert len(out) == 4 * 3 * len(images)
    for (t, i), f in out.items():
        _features_equal(f, ref[i % len(images)])
    assert fe.frame_ids == []  # detection stored nothing


def test_add_frame_equals_detect_then_add_features(scene_frames):
    # one front end after the other: each seeds OpenCV's random generator (RANSAC's draws)
    # when made, so two front ends interleaved in one thread would not be comparable
    cam, ims = scene_frames.camera, scene_frames.images[:5]
    a = FrontEnd(cam, FrontEndConfig())
    res_a = [a.add_frame(im, k) for k, im in enumerate(ims)]
    b = FrontEnd(cam, FrontEndConfig())
    res_b = [b.add_features(b.detect(im), k) if k % 2 else b.add_frame(b.detect(im), k) for k, im in enumerate(ims)]
    for ra, rb in zip(res_a, res_b):
        assert (ra.ok, ra.reason, ra.n_features, ra.n_matches, ra.n_new_tracks) == \
               (rb.ok, rb.reason, rb.n_features, rb.n_matches, rb.n_new_tracks)
        assert set(rb.timings_ms) == {"detect", "match"} and rb.timings_ms["detect"] > 0
    assert res_a[-1].n_matches > 50
    for k in range(5):
        fa, fb = a.frame(k), b.frame(k)
        np.testing.assert_array_equal(fa.track_ids, fb.track_ids)
        np.testing.assert_array_equal(fa.in_map, fb.in_map)
    ra, rb = a.relative_pose(0, 4), b.relative_pose(0, 4)
    assert ra.ok and rb.ok
    np.testing.assert_array_equal(ra.measurement.q_ij, rb.measurement.q_ij)
    np.testing.assert_array_equal(ra.measurement.t_ij, rb.measurement.t_ij)


def test_add_features_rejects_bad_input(scene_frames):
    fe = FrontEnd(scene_frames.camera, FrontEndConfig())
    f = fe.detect(scene_frames.images[0])
    fe.add_features(f, 0)
    with pytest.raises(EstimatorError, match="already added"):
        fe.add_features(f, 0)
    with pytest.raises(EstimatorError, match="takes Features"):
        fe.add_features(scene_frames.images[1], 1)
    with pytest.raises(ImageError):
        fe.detect(np.zeros((10, 10), np.uint8))
    assert fe.frame_ids == [0]


def test_pickled_front_end_detects_again(scene_frames):
    import pickle

    fe = FrontEnd(scene_frames.camera, FrontEndConfig())
    fe.add_frame(scene_frames.images[0], 0)
    fe2 = pickle.loads(pickle.dumps(fe))
    _features_equal(fe2.detect(scene_frames.images[1]), fe.detect(scene_frames.images[1]))
    assert fe2.add_frame(scene_frames.images[1], 1).n_matches == fe.add_frame(scene_frames.images[1], 1).n_matches


# -- the runner ---------------------------------------------------------------------------
def test_pipelined_run_is_the_sequential_run_on_the_rendered_scene(scene_frames):
    cfg = SlamConfig()
    seq_run = run_sequence(scene_frames, cfg, quiet=True, prefetch=0)
    scene_frames.threads.clear()
    pipe_run = run_sequence(scene_frames, cfg, quiet=True, prefetch=2)
    assert scene_frames.threads == {"eifslam-prefetch"}  # decoding left the main thread, in one thread
    assert seq_run.stopped is None and pipe_run.stopped is None
    assert sum(r.position is not None for r in pipe_run.slam.results) >= 8
    _same_runs(seq_run, pipe_run)
    assert all("wait" in r.timings_ms and "detect" in r.timings_ms for r in pipe_run.slam.results)
    assert all("load" in r.timings_ms for r in seq_run.slam.results)
    # the default is pipelined, and the default run is the same run again
    assert cfg.runtime.prefetch == 2
    _same_runs(seq_run, run_sequence(scene_frames, cfg, quiet=True))


@pytest.mark.data
def test_pipelined_run_is_the_sequential_run_on_kitti(shared_dataset):
    from eifslam.io import open_source

    seq = open_source(shared_dataset("kitti-seq1"))
    cfg = SlamConfig()
    a = run_sequence(seq, cfg, max_frames=6, quiet=True, prefetch=0)
    b = run_sequence(seq, cfg, max_frames=6, quiet=True, prefetch=3)
    assert sum(r.position is not None for r in b.slam.results) >= 5
    _same_runs(a, b)


def test_bad_frames_are_handled_as_in_the_sequential_loop(scene_frames):
    ims = list(scene_frames.images[:6])
    ims[2] = ImageError("frame 2: corrupt file")  # decoding fails: skipped, the run goes on
    seq = _Frames(scene_frames.camera, ims, range(6))
    a = run_sequence(seq, SlamConfig(), quiet=True, prefetch=0)
    b = run_sequence(seq, SlamConfig(), quiet=True, prefetch=2)
    assert a.stopped is None and b.stopped is None
    assert a.slam.n_frames == b.slam.n_frames == 5
    _same_runs(a, b)
    ims[4] = np.zeros((7, 7), np.uint8)  # decodes, but the front end refuses it: the run stops
    seq = _Frames(scene_frames.camera, ims, range(6))
    a = run_sequence(seq, SlamConfig(), quiet=True, prefetch=0)
    b = run_sequence(seq, SlamConfig(), quiet=True, prefetch=2)
    assert a.stopped == b.stopped and a.stopped.startswith("stopped at a failing frame")
    assert a.slam.n_frames == b.slam.n_frames == 3


def test_ctrl_c_stops_cleanly_and_keeps_the_estimate(scene_frames, monkeypatch):
    from eifslam.system import slam as slam_module

    real_track = slam_module.Slam.track

    def track(self, image, timestamp=None):
        if self.n_frames == 5:
            raise KeyboardInterrupt
        return real_track(self, image, timestamp)

    monkeypatch.setattr(slam_module.Slam, "track", track)
    before = {t for t in threading.enumerate() if t.name.startswith("eifslam-")}
    run = run_sequence(scene_frames, SlamConfig(), quiet=True, prefetch=2)
    assert run.stopped == "interrupted"
    assert run.slam.n_frames == 5 and sum(r.position is not None for r in run.slam.results) >= 4
    assert len(run.slam.trajectory()[0]) >= 4
    left = {t for t in threading.enumerate() if t.name.startswith("eifslam-")} - before
    assert not any(t.is_alive() for t in left)  # the workers did not outlive the run
    assert max(scene_frames.loaded[-3:]) <= 5 + 2 + 2 + 1  # stopped a few frames ahead (queue + detections)


def test_an_internal_error_stops_the_run_and_keeps_the_estimate(scene_frames, monkeypatch):
    """A bug or a numerical failure no check foresaw (not an ``EifslamError``) ends the run
    as a failing frame does: what was estimated is kept, the reason is recorded."""
    from eifslam.system import slam as slam_module

    real_track = slam_module.Slam.track

    def track(self, image, timestamp=None):
        if self.n_frames == 5:
            raise np.linalg.LinAlgError("1-th leading minor of the array is not positive definite")
        return real_track(self, image, timestamp)

    monkeypatch.setattr(slam_module.Slam, "track", track)
    run = run_sequence(scene_frames, SlamConfig(), quiet=True, prefetch=2)
    assert run.stopped == ("stopped at a failing frame by an internal error: LinAlgError: 1-th leading minor "
                           "of the array is not positive definite")
    assert run.slam.n_frames == 5 and len(run.slam.trajectory()[0]) >= 4


def test_prefetcher_stops_when_closed_on_a_full_queue():
    seq = _Frames(PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100), [np.zeros((4, 4))] * 1000, range(1000))
    pre = FramePrefetcher(seq, 1000, detect=lambda im: im.sum(), depth=2)
    it = iter(pre)
    assert next(it)[0] == 0
    pre.close(timeout=5.0)
    assert not pre.alive
    assert len(seq.loaded) < 10


def test_prefetcher_detects_in_parallel_and_hands_frames_on_in_order():
    """Several detection threads finish out of order (here the even frames take longer);
    the consumer still gets every frame in order, ``ahead`` runs in frame order in one
    thread, and the first frame is detected before any other starts."""
    import time as _time

    n = 12
    seq = _Frames(PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100), list(range(n)), range(n))
    events, lock = [], threading.Lock()  # (frame, +1 start / -1 end) in the order they happen

    def detect(k):
        with lock:
            events.append((k, 1))
        _time.sleep(0.02 if k % 2 == 0 else 0.001)
        with lock:
            events.append((k, -1))
        return 10 * k

    seen_ahead, ahead_threads = [], set()

    def ahead(item):
        seen_ahead.append(item)
        ahead_threads.add(threading.current_thread().name)
        return item + 1

    pre = FramePrefetcher(seq, n, detect=detect, depth=2, ahead=ahead, workers=3)
    got = [(k, item) for k, item, _ in pre]
    pre.close()
    assert got == [(k, 10 * k + 1) for k in range(n)]
    assert seen_ahead == [10 * k for k in range(n)] and ahead_threads == {"eifslam-prefetch"}
    assert seq.loaded == list(range(n)) and seq.threads == {"eifslam-prefetch"}  # decoded in order, in one thread
    assert events[:2] == [(0, 1), (0, -1)]  # the first frame alone
    running = np.cumsum([e for _, e in events])
    assert running.max() >= 2  # then detections overlap
    assert not pre.alive


def test_prefetcher_hands_on_worker_errors():
    class Boom(Exception):
        pass

    seq = _Frames(PinholeCamera(100.0, 100.0, 50.0, 50.0, 100, 100), [1, 2, Boom("decoder broke"), 4], range(4))
    pre = FramePrefetcher(seq, 4, detect=lambda im: -im, depth=1)
    got = []
    with pytest.raises(Boom, match="decoder broke"):
        for k, item, _ in pre:
            got.append((k, item))
    assert got == [(0, -1), (1, -2)]
    pre.close()
    assert not pre.alive


# -- cheaper-detection settings ----------------------------------------------------------
def test_runtime_settings_are_validated():
    for bad in (dict(prefetch=-1), dict(prefetch=1.5), dict(blas_threads=0), dict(opencv_threads="many")):
        with pytest.raises(ConfigError, match="runtime." + next(iter(bad))):
            SlamConfig.from_dict({"runtime": bad})
    c = SlamConfig.from_dict({"runtime": {"prefetch": 0, "blas_threads": None, "opencv_threads": 3}})
    assert c.runtime.prefetch == 0 and c.runtime.blas_threads is None and c.runtime.opencv_threads == 3


def test_the_run_holds_blas_to_its_setting_and_gives_it_back(scene_frames):
    """``runtime.blas_threads`` (1 by default) holds the BLAS library's threads during
    ``run_sequence`` (checked from inside the run) and restores them after; ``None``
    leaves them alone; anything else is refused."""
    from threadpoolctl import threadpool_info

    def blas_threads() -> set[int]:
        return {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}

    if not blas_threads():
        pytest.skip("no BLAS library found by threadpoolctl")
    before = blas_threads()
    seen: list[set[int]] = []
    run_sequence(scene_frames, SlamConfig(), max_frames=3, quiet=True, on_frame=lambda r: seen.append(blas_threads()))
    assert seen and all(s == {1} for s in seen)
    assert blas_threads() == before
    seen.clear()
    run_sequence(scene_frames, SlamConfig.from_dict({"runtime": {"blas_threads": None}}), max_frames=2, quiet=True,
                 on_frame=lambda r: seen.append(blas_threads()))
    assert seen and all(s == before for s in seen)
    for bad in (0, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="blas_threads"):
            SlamConfig.from_dict({"runtime": {"blas_threads": bad}})


def test_the_run_holds_opencv_to_its_thread_setting_and_gives_it_back(scene_frames):
    """``runtime.opencv_threads: auto`` gives OpenCV one thread while SIFT frames are
    detected in the prefetch worker (the tracking thread's search of float descriptors
    leaves OpenCV nothing to share), and
    leaves OpenCV's setting alone for ORB's parallel Hamming search and without a worker;
    an integer is applied as it is; OpenCV's setting is restored after the run."""
    from eifslam.system.runner import opencv_thread_count

    def cfg(**kw) -> SlamConfig:
        fe = {k: kw.pop(k) for k in ("detector",) if k in kw}
        return SlamConfig.from_dict({"frontend": fe, "runtime": kw})

    assert opencv_thread_count(cfg(), prefetch=2) == 1
    assert opencv_thread_count(cfg(), prefetch=0) is None
    assert opencv_thread_count(cfg(detector="orb"), prefetch=2) is None
    assert opencv_thread_count(cfg(opencv_threads=3, detector="orb"), prefetch=2) == 3
    assert opencv_thread_count(cfg(opencv_threads=None), prefetch=2) is None
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        seen: list[int] = []
        run_sequence(scene_frames, SlamConfig(), max_frames=2, quiet=True,
                     on_frame=lambda r: seen.append(cv2.getNumThreads()))
        assert seen == [1, 1] and cv2.getNumThreads() == 2
        seen.clear()
        run_sequence(scene_frames, cfg(opencv_threads=None), max_frames=2, quiet=True,
                     on_frame=lambda r: seen.append(cv2.getNumThreads()))
        assert seen == [2, 2]
    finally:
        cv2.setNumThreads(before)
    for bad in (0, 1.5, True, "all"):
        with pytest.raises(ConfigError, match="opencv_threads"):
            cfg(opencv_threads=bad)


@pytest.mark.parametrize("detector", ["orb", "sift"])
def test_matches_made_ahead_give_the_front_ends_own_results(scene_frames, detector):
    """Features from ``match_ahead`` carry the matches with the previous detected frame
    (the first pair searched in the whole frame, exactly; then, for SIFT, near where the
    previous frame's motion predicts),
    which ``add_features`` uses in place of its own first search, with the same tracks;
    matches made against another frame or another motion than the front end's previous
    one (a frame skipped, and the frame after it) are ignored."""
    cam, ims = scene_frames.camera, scene_frames.images[:6]
    cfg = FrontEndConfig(detector=detector)
    a = FrontEnd(cam, cfg)
    res_a = [a.add_frame(im, k) for k, im in enumerate(ims) if k != 3]
    b = FrontEnd(cam, cfg)
    ahead = [b.match_ahead(b.detect(im)) for im in ims]
    assert ahead[0].ahead is None and all(f.ahead is not None and len(f.ahead.idx_new) > 20 for f in ahead[1:])
    predicted = cfg.detector.float_descriptors  # binary descriptors are searched in the whole frame
    assert all((f.motion is not None) == predicted and f.ahead.motion_previous is p.motion
               for f, p in zip(ahead[2:], ahead[1:]))
    res_b = [b.add_features(f, k) for k, f in enumerate(ahead) if k != 3]  # frame 4's were made against 3
    used = ["match_ahead" in r.timings_ms for r in res_b]
    assert used == [False, True, True, False, not predicted]  # frame 5's with frame 4's motion from 3
    for ra, rb in zip(res_a, res_b):
        assert (ra.ok, ra.n_matches, ra.n_new_tracks) == (rb.ok, rb.n_matches, rb.n_new_tracks)
    for k in (0, 1, 2, 4, 5):
        np.testing.assert_array_equal(a.frame(k).track_ids, b.frame(k).track_ids)
    assert res_a[-1].n_matches > 50
    # their epipolar RANSAC, made in the worker too: what the tracking thread would get
    # on those matches, whatever its random generator holds
    for f, prev in zip(ahead[1:], ahead[:-1]):
        inl = f.ahead.inliers
        assert inl is not None and inl.dtype == bool and inl.shape == f.ahead.idx_new.shape and inl.sum() > 20
        cv2.setRNGSeed(12345)
        _, again = essential_ransac(prev.uv[f.ahead.idx_previous], f.uv[f.ahead.idx_new], cam.K,
                                    cfg.ransac_threshold_px, cfg.ransac_confidence, cfg.ransac_method)
        np.testing.assert_array_equal(again, inl)
    assert all((f.index is not None) == cfg.detector.float_descriptors for f in ahead)


def test_a_loaded_front_end_goes_on_as_the_uninterrupted_one(scene_frames):
    """A front end saved after six frames and loaded again searches the next frames where
    the saved motion predicts them, with the matches made ahead from the first frame on,
    and gives the tracks of the uninterrupted one."""
    cam, ims = scene_frames.camera, scene_frames.images
    cfg = FrontEndConfig(seed=0)
    a = FrontEnd(cam, cfg)
    res_a = [a.add_features(a.match_ahead(a.detect(im)), k) for k, im in enumerate(ims)]
    b = FrontEnd(cam, cfg)
    for k, im in enumerate(ims[:6]):
        b.add_features(b.match_ahead(b.detect(im)), k)
    c = FrontEnd(cam, cfg)
    c.load_state_dict(b.state_dict())
    ahead = [c.match_ahead(c.detect(im)) for im in ims[6:]]
    assert all(f.ahead is not None and f.ahead.motion_previous is not None for f in ahead)
    res_c = [c.add_features(f, k) for k, f in enumerate(ahead, start=6)]
    assert all("match_ahead" in r.timings_ms for r in res_c)
    assert [r.n_matches for r in res_c] == [r.n_matches for r in res_a[6:]]
    for k in range(6, len(ims)):
        np.testing.assert_array_equal(a.frame(k).track_ids, c.frame(k).track_ids)
