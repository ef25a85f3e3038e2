"""Chessboard stereo calibration on analytically rendered boards (known cameras)."""

import cv2
import numpy as np
import pytest

from pipeline.geometry.calibration import (CalibrationError, board_points_mm, calibrate_stereo, find_board,
                                  rectification)
from pipeline.design import load_design
from pipeline.geometry.triangulation import camera_poses, triangulate
from pipeline.types import MarkerMatches, StereoCalibration
from synth_frames import chessboard_pairs, nominal_calibration, render_chessboard, rot_xyz

# Rendered boards are 2x2 supersampled and noise-free; corner localisation is then ~0.03 px, so the
# paper's 0.12 px RMS is a fair upper bound here; focal lengths within 0.5 %, baseline within 0.05 mm
# (0.4 %) is what 6 views at 38-55 mm pin down.
RMS_TOL_PX = 0.12
FOCAL_REL_TOL = 0.005
BASELINE_TOL_MM = 0.05


@pytest.fixture(scope="module")
def truth():
    return nominal_calibration(load_design("hexagon127"))


@pytest.fixture(scope="module")
def pairs(truth):
    return chessboard_pairs(truth, 6, np.random.default_rng(11))


def test_find_board_locates_corners_at_true_projection(truth):
    T = np.eye(4)
    T[:3, :3] = rot_xyz(10, -15, 5)
    T[:3, 3] = [-12.0, -9.0, 45.0]
    img = render_chessboard(truth.K1, truth.D1, T)
    corners = find_board(img)
    assert corners is not None and corners.shape == (48, 2)
    want, _ = cv2.projectPoints(board_points_mm(), cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], truth.K1, truth.D1)
    err = np.linalg.norm(corners - want.reshape(-1, 2), axis=1)
    assert np.sqrt(np.mean(err**2)) < RMS_TOL_PX
    # same board seen upside down: canonical order still has the first row running toward +u
    T2 = T.copy()
    T2[:3, :3] = T[:3, :3] @ rot_xyz(0, 0, 180)
    T2[:3, 3] = T[:3, 3] + T[:3, :3] @ np.array([28.0, 20.0, 0.0])
    c2 = find_board(render_chessboard(truth.K1, truth.D1, T2))
    assert c2 is not None and c2[7, 0] > c2[0, 0]
    assert find_board(np.full((480, 640), 120, np.uint8)) is None


def test_calibrate_stereo_recovers_cameras(truth, pairs):
    blank = ("blank", np.full((480, 640), 110, np.uint8), np.full((480, 640), 110, np.uint8))
    calib, report = calibrate_stereo(list(pairs) + [blank], sensor_from_left=truth.sensor_from_left)
    assert report.skipped.keys() == {"blank"} and "not found" in report.skipped["blank"]
    assert len(report.used) == len(pairs) and set(report.per_pair_rms_px) == set(report.used)
    assert report.rms_px < RMS_TOL_PX and max(report.per_pair_rms_px.values()) < 2 * RMS_TOL_PX
    for K, K0 in ((calib.K1, truth.K1), (calib.K2, truth.K2)):
        assert abs(K[0, 0] / K0[0, 0] - 1) < FOCAL_REL_TOL and abs(K[1, 1] / K0[1, 1] - 1) < FOCAL_REL_TOL
    assert abs(report.baseline_mm - truth.baseline_mm) < BASELINE_TOL_MM
    ang = np.degrees(np.arccos(np.clip((np.trace(calib.R.T @ truth.R) - 1) / 2, -1, 1)))
    assert ang < 0.2
    # what matters downstream: 3-D points triangulated with the estimate land where they are
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-4, 4, 50), rng.uniform(-4, 4, 50), rng.uniform(-8, 0, 50)])
    px = []
    for pose, K, D in zip(camera_poses(truth), (truth.K1, truth.K2), (truth.D1, truth.D2)):
        cam = np.linalg.inv(pose)
        p, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), cv2.Rodrigues(cam[:3, :3])[0], cam[:3, 3], K, D)
        px.append(p.reshape(-1, 2))
    cloud = triangulate(MarkerMatches(np.arange(50), px[0], px[1]), calib)
    # depth error ~ z^2 / (b f) * disparity error: (30 mm)^2 / (12.5 * 440) * 0.05 px ~ 0.01 mm, plus scale
    assert np.median(np.linalg.norm(cloud.xyz_mm - pts, axis=1)) < 0.1


def test_calibrate_stereo_needs_three_pairs(pairs):
    blank = np.full((480, 640), 110, np.uint8)
    with pytest.raises(CalibrationError, match=r"only 2 usable pair\(s\).*empty1"):
        calibrate_stereo(list(pairs[:2]) + [("empty1", blank, blank)])
    with pytest.raises(CalibrationError, match="differ"):
        calibrate_stereo([("odd", blank, blank[:100])])


def test_rectification_aligns_rows_and_is_cached(truth):
    rect = rectification(truth)
    assert rectification(truth) is rect
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-5, 5, 30), rng.uniform(-5, 5, 30), rng.uniform(-10, 0, 30)])
    rows = []
    for pose, K, D, R, P in zip(camera_poses(truth), (truth.K1, truth.K2), (truth.D1, truth.D2),
                                (rect.R1, rect.R2), (rect.P1, rect.P2)):
        cam = np.linalg.inv(pose)
        p, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), cv2.Rodrigues(cam[:3, :3])[0], cam[:3, 3], K, D)
        r = cv2.undistortPoints(p, K, D, R=R, P=P).reshape(-1, 2)
        rows.append(r[:, 1])
    assert np.max(np.abs(rows[0] - rows[1])) < 1e-3  # epipolar lines are image rows after rectification
    assert rect.maps_left[0].shape == (480, 640)


def test_calibration_yaml_round_trip(tmp_path, truth):
    truth.save_yaml(tmp_path / "c.yaml")
    back = StereoCalibration.load_yaml(tmp_path / "c.yaml")
    assert np.allclose(back.K1, truth.K1) and np.allclose(back.sensor_from_left, truth.sensor_from_left)
    # the OpenCV extras an OpenCV user expects (stereo_calib sample keys): E, F, R1, R2, P1, P2, Q
    fs = cv2.FileStorage(str(tmp_path / "c.yaml"), cv2.FILE_STORAGE_READ)
    E, F, P1, P2, Q = (fs.getNode(k).mat() for k in ("E", "F", "P1", "P2", "Q"))
    fs.release()
    rect = rectification(truth, with_maps=False)
    assert np.allclose(P2, rect.P2) and np.allclose(Q, rect.Q) and np.allclose(P1, rect.P1)
    assert abs(-P2[0, 3] / P2[0, 0] - truth.baseline_mm) < 1e-6       # rectified baseline, mm
    # epipolar constraint on a pair of normalised (undistorted) views of one 3-D point
    X = np.array([1.0, -2.0, 30.0])
    x1 = np.append(X[:2] / X[2], 1.0)
    X2 = truth.R @ X + truth.T
    x2 = np.append(X2[:2] / X2[2], 1.0)
    assert abs(x2 @ E @ x1) < 1e-9
    u1, u2 = truth.K1 @ x1, truth.K2 @ x2
    assert abs(u2 @ F @ u1) / np.linalg.norm(F) < 1e-6


def test_stereo_corner_order_is_consistent_for_boards_turned_near_90_degrees(truth):
    # Rows near vertical in the image are where a per-image orientation rule can pick opposite corner
    # orders in the two views; calibrate_stereo must make each pair consistent (else |T| is off by mm).
    turned = chessboard_pairs(truth, 6, np.random.default_rng(5), in_plane_deg=90.0, in_plane_spread_deg=4.0)
    calib, report = calibrate_stereo(turned, sensor_from_left=truth.sensor_from_left)
    assert len(report.used) >= 4
    assert report.rms_px < RMS_TOL_PX
    assert abs(report.baseline_mm - truth.baseline_mm) < BASELINE_TOL_MM
