"""Loaders on the shared evaluation data sets (data tests: tests/conftest.py)."""

from __future__ import annotations


import numpy as np
import pytest

from eifslam.io import open_source
from eifslam.io.cameras import load_camera
from eifslam.io.kitti import read_kitti_poses
from eifslam.io.strecha import open_strecha
from eifslam.io.trajectory import read_tum


EXPECTED = {
    # name: (frames, width, height, fx, image channels)
    "kitti-seq1": (51, 1226, 370, 707.0912, 1),
    "7scenes-redkitchen-a": (500, 640, 480, 525.0, 3),
    "middlebury-templering": (31, 640, 480, 1520.4, 3),
    "strecha-fountain-p11": (11, 768, 512, 689.87, 3),
}


@pytest.mark.data
@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_folder_loader_on_shared(name, shared_dataset):
    root = shared_dataset(name)
    n, w, h, fx, channels = EXPECTED[name]
    seq = open_source(root)
    assert seq.kind == "folder"
    assert len(seq) == n
    assert (seq.camera.width, seq.camera.height) == (w, h)
    assert seq.camera.fx == pytest.approx(fx)
    assert not seq.camera.has_distortion
    for i in (0, n - 1):
        img = seq.load(i)
        assert img.shape[:2] == (h, w)
        assert (img.ndim == 2) == (channels == 1)
    gt = seq.ground_truth()
    assert len(gt) == n  # every frame has ground truth
    np.testing.assert_allclose(gt.timestamps, seq.timestamps)
    ref = read_tum(root / "groundtruth.tum")
    np.testing.assert_allclose(gt.positions, ref.positions)


@pytest.mark.data
def test_kitti_original_files_agree(shared_dataset):
    root = shared_dataset("kitti-seq1")
    T = read_kitti_poses(root / "poses.txt")
    ref = read_tum(root / "groundtruth.tum")
    np.testing.assert_allclose(T[:, :3, 3], ref.positions, atol=1e-6)
    np.testing.assert_allclose(T[:, :3, :3], ref.rotations, atol=1e-6)
    cam = load_camera(root / "calib.txt", image_size=(1226, 370))
    assert cam == load_camera(root / "camera.yaml")


@pytest.mark.data
def test_strecha_original_files_agree(shared_dataset):
    root = shared_dataset("strecha-fountain-p11")
    seq = open_strecha(root)  # .camera files in gt_cameras/
    ref = read_tum(root / "groundtruth.tum")
    gt = seq.ground_truth()
    np.testing.assert_allclose(gt.positions, ref.positions, atol=1e-9)
    np.testing.assert_allclose(gt.rotations, ref.rotations, atol=1e-6)
    assert seq.camera.K == pytest.approx(load_camera(root / "camera.yaml").K)
