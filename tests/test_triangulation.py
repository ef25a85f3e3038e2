"""Triangulation against analytic points (straight rays, no refraction) and cv2.triangulatePoints."""

import cv2
import numpy as np
import pytest

from pipeline.design import load_design
from pipeline.io.synthetic import nominal_calibration
from pipeline.geometry.triangulation import UNDISTORT_CRITERIA, TriangulationError, camera_poses, triangulate, undistort_normalized
from pipeline.types import MarkerMatches

# Exact pixels: undistortion converges to ~1e-10 (UNDISTORT_CRITERIA) of normalised coordinates, i.e.
# ~1e-9 mm at 30 mm range; 1e-6 mm leaves ample margin while catching any formula or frame error.
EXACT_TOL_MM = 1e-6


def _project(points, calib):
    out = []
    for pose, K, D in zip(camera_poses(calib), (calib.K1, calib.K2), (calib.D1, calib.D2)):
        cam = np.linalg.inv(pose)
        rvec, _ = cv2.Rodrigues(cam[:3, :3])
        px, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, cam[:3, 3], K, D)
        out.append(px.reshape(-1, 2))
    return out


def _points(rng, n=200, calib=None):
    # a box in front of the cameras (at z = -30 mm), 5-35 mm away, kept where both images see it
    pts = np.column_stack([rng.uniform(-8, 8, 3 * n), rng.uniform(-8, 8, 3 * n), rng.uniform(-25, 5, 3 * n)])
    calib = calib or nominal_calibration(load_design("hexagon127"))
    left, right = _project(pts, calib)
    inside = np.all((left >= 0) & (left < [640, 480]) & (right >= 0) & (right < [640, 480]), axis=1)
    return pts[inside][:n]


@pytest.mark.parametrize("design_name", ["hexagon127", "circular217_dome"])
@pytest.mark.parametrize("method", ["general", "disparity"])
def test_triangulate_analytic_points(design_name, method):
    design = load_design(design_name)
    calib = nominal_calibration(design)
    pts = _points(np.random.default_rng(1), calib=calib)
    left, right = _project(pts, calib)
    cloud = triangulate(MarkerMatches(np.arange(len(pts)), left, right), calib, method=method)
    assert np.array_equal(cloud.ids, np.arange(len(pts)))
    assert np.max(np.abs(cloud.xyz_mm - pts)) < EXACT_TOL_MM


def test_general_matches_cv2_triangulate_points_with_noise():
    calib = nominal_calibration(load_design("hexagon127"))
    rng = np.random.default_rng(2)
    pts = _points(rng)
    left, right = _project(pts, calib)
    left = left + rng.normal(0, 0.2, left.shape)
    right = right + rng.normal(0, 0.2, right.shape)
    ours = triangulate(MarkerMatches(np.arange(len(pts)), left, right), calib).xyz_mm
    nl = cv2.undistortPoints(left.reshape(-1, 1, 2), calib.K1, calib.D1).reshape(-1, 2)
    nr = cv2.undistortPoints(right.reshape(-1, 1, 2), calib.K2, calib.D2).reshape(-1, 2)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([calib.R, calib.T.reshape(3, 1)])
    X = cv2.triangulatePoints(P1, P2, nl.T, nr.T)
    X = (X[:3] / X[3]).T
    theirs = X @ calib.sensor_from_left[:3, :3].T + calib.sensor_from_left[:3, 3]
    # Midpoint and DLT are different estimators: with noise they differ by a fraction of the error
    # the noise itself causes (both are first-order unbiased), and agree exactly without noise.
    diff = np.linalg.norm(ours - theirs, axis=1)
    err = np.linalg.norm(ours - pts, axis=1)
    err_dlt = np.linalg.norm(theirs - pts, axis=1)
    print(f"median |midpoint - DLT| {np.median(diff):.4f} mm, median error {np.median(err):.4f} mm")
    assert 0.005 < np.median(err) < 0.2  # noise really was applied and stays at the expected scale
    assert np.median(diff) < 0.25 * np.median(err)
    assert abs(np.median(err) - np.median(err_dlt)) < 0.1 * np.median(err)


def test_unknown_method_and_empty_input():
    calib = nominal_calibration(load_design("hexagon127"))
    m = MarkerMatches(np.empty(0, np.int64), np.empty((0, 2)), np.empty((0, 2)))
    assert triangulate(m, calib).xyz_mm.shape == (0, 3)
    assert triangulate(m, calib, method="disparity").xyz_mm.shape == (0, 3)
    with pytest.raises(TriangulationError, match="unknown method"):
        triangulate(m, calib, method="magic")


def test_parallel_rays_are_dropped_not_nan():
    calib = nominal_calibration(load_design("hexagon127"))
    pts = _points(np.random.default_rng(3), 5)
    left, right = _project(pts, calib)
    # marker 4: the right pixel is replaced by the direction parallel to the left ray (point at infinity)
    ray_dir = (np.linalg.inv(calib.K1) @ np.array([*cv2.undistortPoints(left[4:5].reshape(1, 1, 2), calib.K1,
                                                                         calib.D1, P=calib.K1).ravel(), 1.0]))
    d_sensor = calib.sensor_from_left[:3, :3] @ ray_dir
    inf_pt = camera_poses(calib)[1][:3, 3] + 1e9 * d_sensor
    right[4] = _project(inf_pt.reshape(1, 3), calib)[1][0]
    for method in ("general", "disparity"):
        cloud = triangulate(MarkerMatches(np.arange(5), left, right), calib, method=method)
        assert np.all(np.isfinite(cloud.xyz_mm))
        assert cloud.ids.tolist() == [0, 1, 2, 3], (method, cloud.ids)   # marker 4 dropped, the rest kept
        assert np.max(np.abs(cloud.xyz_mm - pts[:4])) < EXACT_TOL_MM


@pytest.mark.parametrize("dist", [None, (-0.5, 0.3, 0.001, -0.002, -0.1), (0.3, 0.1, 0.002, 0.001, 0.05)])
def test_newton_undistortion_is_opencvs_and_inverts_the_lens(dist):
    """undistort_normalized against cv2.undistortPoints (UNDISTORT_CRITERIA): over the image of the
    twin's lens the two agree to 1e-10 (measured 1.1e-12). On a grid reaching 200 px beyond the image,
    with the twin's and two stronger lenses, every point agrees to 1e-7 wherever OpenCV itself
    converged (its reprojection within 1e-6 px; measured <= 1.1e-8), and every point reprojects
    through cv2.projectPoints within 1e-6 px unless OpenCV's does not either (the points Newton
    hands back to OpenCV, where the model folds over)."""
    calib = nominal_calibration(load_design("hexagon127"))
    K = calib.K1
    D = calib.D1 if dist is None else np.array(dist)
    u, v = np.meshgrid(np.linspace(-200, 839, 53), np.linspace(-200, 679, 45))
    px = np.column_stack([u.ravel(), v.ravel()])
    ref = cv2.undistortPoints(px.reshape(-1, 1, 2), K, D, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
    new = undistort_normalized(px, K, D)

    def reproj_err(xy):
        p3 = np.column_stack([xy, np.ones(len(xy))])
        return np.linalg.norm(cv2.projectPoints(p3, np.zeros(3), np.zeros(3), K, D)[0].reshape(-1, 2) - px, axis=1)

    cv_ok = reproj_err(ref) < 1e-6
    assert np.abs(new - ref)[cv_ok].max() < 1e-7
    assert np.all((reproj_err(new) < 1e-6) | ~cv_ok)
    if dist is None:
        inside = (px[:, 0] >= 0) & (px[:, 0] <= 639) & (px[:, 1] >= 0) & (px[:, 1] <= 479)
        assert np.abs(new - ref)[inside].max() < 1e-10


def test_compiled_midpoints_are_closest_points():
    """The triangulation's compiled pass gives closest_points' midpoints: NaN for the same
    (near-parallel) pairs, the same points elsewhere (identical with numpy's einsum order on x86-64;
    1e-12 mm allowed for a numpy that sums a dot product's three products in another order)."""
    from pipeline.geometry.triangulation import _midpoints, closest_points

    rng = np.random.default_rng(5)
    for trial in range(40):
        n = int(rng.integers(1, 300))
        o1 = rng.normal(0, 5, (n, 3))
        o2 = o1 + rng.normal(0, 3, (n, 3))
        d1, d2 = rng.normal(0, 1, (2, n, 3))
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
        d2[:3] = d1[:3]                                            # parallel pairs
        with np.errstate(divide="ignore", invalid="ignore"):
            want, _ = closest_points(o1, d1, o2, d2)
        got = np.empty((n, 3))
        _midpoints(o1, d1, o2, d2, got)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        ok = ~np.isnan(want)
        np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-12)
