"""The five-point relative pose on real wide-baseline pairs agrees with the ground truth
within its own covariance, and narrow forward pairs keep their direction (ground truth
used for scoring only).

strecha-castle-p30 starts with a 24 m, 46° step between frames 0 and 1. On its 69 ``Ωp``
correspondences a wrong essential matrix (rotation 15° off) has 62 inliers at 1 px, the
right one 68; at ``ransac_confidence`` 0.999 OpenCV's USAC stopped at the wrong one (its
iteration count follows the best inlier ratio so far, 90%), and the whole run ended at an
ATE of 0.82 m (COLMAP 0.17 m).
"""

from __future__ import annotations


import numpy as np
import pytest

from eifslam.geometry.rotations import quat_log, quat_multiply, quat_conjugate, quat_to_rotmat, rotmat_to_quat
from eifslam.io.trajectory import read_tum
from eifslam.system.config import SlamConfig
from eifslam.system.slam import Slam

CHI2_3_999 = 16.27  # 99.9% quantile of chi-square with 3 degrees of freedom


@pytest.mark.data
@pytest.mark.parametrize("i, j, contrast, seed", [(0, 1, 0.04, 0), (1, 2, 0.04, 0), (0, 2, 0.04, 0), (0, 1, 0.02, 2),
                                                  (0, 1, 0.01, 0)])
def test_wide_baseline_relative_rotation_is_consistent_with_its_covariance(i, j, contrast, seed, shared_dataset,
                                                                         monkeypatch):
    # SIFT's contrast threshold changes the keypoints: at 0.01 (and 0.02 with seed 2) the
    # first pair's Ωp correspondences made USAC stop at the facade's twin pose (14 deg off,
    # 67 of 73 inliers against the true pose's 73), and the Gauss-Newton refinement of the
    # homography's pose stayed at its start
    from eifslam.frontend.config import FrontEndConfig
    from eifslam.io import open_source

    castle = shared_dataset("strecha-castle-p30")
    monkeypatch.setattr(FrontEndConfig, "sift_contrast_threshold", contrast)  # a tuning constant, varied here
    seq = open_source(castle)
    gt = read_tum(castle / "groundtruth.tum")
    slam = Slam(seq.camera, SlamConfig().replace(frontend={"seed": seed}))
    fe = slam.frontend
    for k in sorted({i, j}):
        fe.add_frame(seq.load(k), k)
    r = fe.relative_pose(i, j)
    assert r.ok, r.reason
    m = r.measurement
    # true R_ij = R_wi^T R_wj; the error convention of RelativePose: R_true = R_ij Exp(dtheta)
    R_true = quat_to_rotmat(gt.quats_wxyz[i]).T @ quat_to_rotmat(gt.quats_wxyz[j])
    dtheta = quat_log(quat_multiply(quat_conjugate(m.q_ij), rotmat_to_quat(R_true)))
    chi2 = float(dtheta @ np.linalg.solve(m.cov[:3, :3], dtheta))
    assert chi2 < CHI2_3_999, f"rotation {np.degrees(np.linalg.norm(dtheta)):.2f} deg off, chi2 {chi2:.1f}"
    assert np.degrees(np.linalg.norm(dtheta)) < 2.0


@pytest.mark.data
@pytest.mark.parametrize("i, j", [(0, 1), (10, 11)])
def test_a_narrow_forward_pair_keeps_its_direction(i, j, shared_dataset):
    # with ORB, kitti-seq1's narrow forward pairs (0.7-0.8 deg of parallax) have
    # homography decompositions 84 deg off the true direction with more inliers at 1 px than
    # the essential matrix's pose (the pair's near-static points fit them); trying them on
    # every pair and taking the most inliers ended the run at 4.7 m ATE. Only wide pairs try
    # them (relative_pose._PLANE_PARALLAX_DEG).
    from eifslam.io import open_source

    kitti = shared_dataset("kitti-seq1")
    seq = open_source(kitti)
    gt = read_tum(kitti / "groundtruth.tum")
    fe = Slam(seq.camera, SlamConfig().replace(frontend={"detector": "orb"})).frontend
    for k in (i, j):
        fe.add_frame(seq.load(k), k)
    r = fe.relative_pose(i, j)
    assert r.ok, r.reason
    R_i = quat_to_rotmat(gt.quats_wxyz[i])
    t_true = R_i.T @ (gt.positions[j] - gt.positions[i])
    cos = float(r.measurement.t_ij @ t_true / np.linalg.norm(t_true))
    assert np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) < 10.0
