"""Stage 5: stereo triangulation of matched markers (apparent, i.e. refracted, positions).

Two methods, both returning :class:`~pipeline.types.MarkerCloud` in the sensor frame (mm):

* ``"general"`` — undistort each pixel to a viewing ray (:func:`undistort_normalized`), place the rays
  with the full stereo extrinsics (R, T) and take the midpoint of their closest approach. Works for
  any relative pose (the StereoTacTip cameras are toed in by ~9°).
* ``"disparity"`` — the paper's Eq. (2)-(3) on rectified coordinates: z = b f / d,
  x = b (u_l - c_x) / d, y = b (v_l - c_y) / d in the rectified left camera frame, then rotated back
  to the left camera and on to the sensor frame.

The positions are *apparent*: the rays are straight lines in air, so markers seen through the
acrylic + gel stack come out shallower than they are. :mod:`pipeline.geometry.refraction` corrects that.

References
----------
StereoTacTip paper, Sec. "3D Marker Position", Eq. (1)-(3).
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

from pipeline.errors import UserError
from pipeline.types import MarkerCloud, MarkerMatches, StereoCalibration

__all__ = ["triangulate", "camera_poses", "pixels_to_rays", "matched_rays", "closest_points", "TriangulationError",
           "UNDISTORT_CRITERIA", "undistort_normalized"]

# cv2.undistortPoints iterates a fixed-point inversion of the lens model; the default 5 iterations
# leave ~1e-3 px at the corners of a k1 = -0.28 wide-angle lens, 40 iterations reach ~1e-10.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)

METHODS = ("general", "disparity")


class TriangulationError(UserError, ValueError):
    """Triangulation input is unusable (unknown method, rays that do not converge)."""


def camera_poses(calib: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-from-camera poses of both cameras, each (4, 4) float64, mm.

    OpenCV's stereo convention is X_right = R X_left + T, so right_from_left = [R | T] and
    sensor_from_right = sensor_from_left @ inv(right_from_left).

    Worked out once per calibration (its arrays are read-only) and kept on it: the stereo check, the
    cross-view completion and triangulation ask for them several times a frame. Returned read-only.
    """
    hit = calib.__dict__.get("_camera_poses")
    if hit is None:
        right_from_left = np.eye(4)
        right_from_left[:3, :3] = calib.R
        right_from_left[:3, 3] = calib.T
        hit = (calib.sensor_from_left.copy(), calib.sensor_from_left @ np.linalg.inv(right_from_left))
        for a in hit:
            a.setflags(write=False)
        calib.__dict__["_camera_poses"] = hit     # a frozen dataclass: cached beside its fields
    return hit


@numba.njit(cache=True, nogil=True)
def _undistort_newton(px, fx, fy, cx, cy, k1, k2, p1, p2, k3, out):
    """Normalised undistorted coordinates of distorted pixels by Newton's method on the OpenCV lens
    model (k1, k2, p1, p2, k3), from the pixel's own normalised position. Returns a mask of the points
    that did not converge to a step below 1e-15 within 20 iterations, met a singular Jacobian, or
    converged where the model folds over."""
    failed = np.zeros(len(px), np.bool_)
    for i in range(len(px)):
        xd, yd = (px[i, 0] - cx) / fx, (px[i, 1] - cy) / fy
        x, y = xd, yd
        ok = False
        for _ in range(20):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dr = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)              # d radial / d r2
            fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
            fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
            jxx = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
            jxy = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
            jyx = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
            jyy = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
            det = jxx * jyy - jxy * jyx
            if det == 0.0 or not np.isfinite(det):
                break
            sx = (jyy * fx_ - jxy * fy_) / det
            sy = (jxx * fy_ - jyx * fx_) / det
            x -= sx
            y -= sy
            if abs(sx) + abs(sy) < 1e-15:
                # a root where the model folds over (radial factor or Jacobian not positive) is not
                # the lens's: leave those to OpenCV, like the points Newton does not settle
                ok = radial > 0.0 and det > 0.0
                break
        out[i, 0], out[i, 1] = x, y
        failed[i] = not ok
    return failed


def undistort_normalized(px: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Normalised undistorted image coordinates (N, 2) of distorted pixels (N, 2): what
    ``cv2.undistortPoints(px, K, D)`` returns with :data:`UNDISTORT_CRITERIA`, by Newton's method
    (quadratic convergence: a few iterations instead of OpenCV's up to 40 fixed-point ones; the two
    agree to ~1e-12, tests/test_triangulation.py). Points where Newton does not converge, or converges
    outside the lens model's monotonic range, are handed to OpenCV, so there the result is OpenCV's.
    Skew in ``K`` is ignored, as OpenCV does.
    """
    px = np.ascontiguousarray(px, dtype=np.float64).reshape(-1, 2)
    out = np.empty_like(px)
    if len(px) == 0:
        return out
    d = np.asarray(D, dtype=np.float64).reshape(-1)
    failed = _undistort_newton(px, K[0, 0], K[1, 1], K[0, 2], K[1, 2], d[0], d[1], d[2], d[3], d[4], out)
    if failed.any():
        out[failed] = cv2.undistortPoints(px[failed].reshape(-1, 1, 2), K, D,
                                          criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
    return out


def pixels_to_rays(px: np.ndarray, K: np.ndarray, D: np.ndarray, sensor_from_cam: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Back-project distorted pixels to unit viewing rays in the sensor frame.

    Parameters
    ----------
    px : (N, 2) float64, (u, v) pixels of one camera image
    K, D : (3, 3) intrinsics and (5,) distortion of that camera
    sensor_from_cam : (4, 4) pose of the camera in the sensor frame, mm

    Returns
    -------
    origins : (N, 3) camera centre repeated, sensor frame, mm
    dirs : (N, 3) unit ray directions, sensor frame
    """
    px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
    if len(px) == 0:
        return np.empty((0, 3)), np.empty((0, 3))
    xy = undistort_normalized(px, K, D)
    d_cam = np.column_stack([xy, np.ones(len(xy))])
    d = d_cam @ sensor_from_cam[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(sensor_from_cam[:3, 3], d.shape).copy()
    return o, d


def closest_points(o1: np.ndarray, d1: np.ndarray, o2: np.ndarray, d2: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Midpoints of closest approach of ray pairs and the gap between the rays, (N, 3) and (N,) mm.

    Rays are o + s d with unit d. Near-parallel rays (no depth information) give NaN.
    """
    w = o1 - o2
    b = np.einsum("ij,ij->i", d1, d2)
    d = np.einsum("ij,ij->i", d1, w)
    e = np.einsum("ij,ij->i", d2, w)
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - d) / denom
        t = (e - b * d) / denom
        p1 = o1 + s[:, None] * d1
        p2 = o2 + t[:, None] * d2
        mid = 0.5 * (p1 + p2)
        gap = np.linalg.norm(p1 - p2, axis=1)
    bad = denom < 1e-12
    mid[bad] = np.nan
    gap[bad] = np.nan
    return mid, gap


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _midpoints(o1, d1, o2, d2, mid):
    """:func:`closest_points`'s midpoints of (N, 3) rays into ``mid``, in one pass with no
    temporaries: the same operations in the same order (the dot products summed as numpy's einsum
    sums three products, x + z first, then y), so the same numbers; tests/test_triangulation.py."""
    for i in range(len(o1)):
        wx, wy, wz = o1[i, 0] - o2[i, 0], o1[i, 1] - o2[i, 1], o1[i, 2] - o2[i, 2]
        ux, uy, uz = d1[i, 0], d1[i, 1], d1[i, 2]
        vx, vy, vz = d2[i, 0], d2[i, 1], d2[i, 2]
        b = (ux * vx + uz * vz) + uy * vy
        d = (ux * wx + uz * wz) + uy * wy
        e = (vx * wx + vz * wz) + vy * wy
        denom = 1.0 - b * b
        if denom < 1e-12:
            mid[i, 0] = mid[i, 1] = mid[i, 2] = np.nan
            continue
        s = (b * e - d) / denom
        t = (e - b * d) / denom
        mid[i, 0] = 0.5 * ((o1[i, 0] + s * ux) + (o2[i, 0] + t * vx))
        mid[i, 1] = 0.5 * ((o1[i, 1] + s * uy) + (o2[i, 1] + t * vy))
        mid[i, 2] = 0.5 * ((o1[i, 2] + s * uz) + (o2[i, 2] + t * vz))


def matched_rays(matches: MarkerMatches, calib: StereoCalibration) -> tuple[np.ndarray, ...]:
    """Viewing rays of every matched marker in both cameras, sensor frame: ``(o1, d1, o2, d2)``,
    each (N, 3) (origins mm, unit directions), left then right (:func:`pixels_to_rays`). Computed
    once per frame, they serve both :func:`triangulate` and the exact refraction correction."""
    sfl, sfr = camera_poses(calib)
    o1, d1 = pixels_to_rays(matches.left_px, calib.K1, calib.D1, sfl)
    o2, d2 = pixels_to_rays(matches.right_px, calib.K2, calib.D2, sfr)
    return o1, d1, o2, d2


def _general(matches: MarkerMatches, calib: StereoCalibration, rays=None) -> np.ndarray:
    o1, d1, o2, d2 = (np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3)
                      for a in (matched_rays(matches, calib) if rays is None else rays))
    mid = np.empty((len(o1), 3))
    _midpoints(o1, d1, o2, d2, mid)      # closest_points' midpoints, compiled
    return mid


def _disparity(matches: MarkerMatches, calib: StereoCalibration) -> np.ndarray:
    from pipeline.geometry.calibration import rectification

    rect = rectification(calib, with_maps=False)
    ul = cv2.undistortPoints(matches.left_px.reshape(-1, 1, 2), calib.K1, calib.D1, R=rect.R1, P=rect.P1,
                             criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
    ur = cv2.undistortPoints(matches.right_px.reshape(-1, 1, 2), calib.K2, calib.D2, R=rect.R2, P=rect.P2,
                             criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
    f = rect.P1[0, 0]
    cx_l, cy = rect.P1[0, 2], rect.P1[1, 2]
    cx_r = rect.P2[0, 2]
    b = -rect.P2[0, 3] / rect.P2[0, 0]  # P2[0, 3] = -f b for a right camera at +x of the rectified left
    # Eq. (2): the paper's d is measured between principal points; with CALIB_ZERO_DISPARITY cx_l = cx_r.
    d = (ul[:, 0] - cx_l) - (ur[:, 0] - cx_r)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = b * f / d
        x = b * (ul[:, 0] - cx_l) / d
        y = b * (ul[:, 1] - cy) / d * (f / rect.P1[1, 1])
    p_rect = np.column_stack([x, y, z])
    p_rect[~(d > 0)] = np.nan  # zero or negative disparity: point at or behind infinity
    p_left = p_rect @ rect.R1  # rectified = R1 @ left  =>  left = R1^T @ rectified
    return p_left @ calib.sensor_from_left[:3, :3].T + calib.sensor_from_left[:3, 3]


def triangulate(matches: MarkerMatches, calib: StereoCalibration, *, method: str = "general",
                rays: tuple[np.ndarray, ...] | None = None) -> MarkerCloud:
    """Triangulate matched markers to apparent 3-D positions in the sensor frame.

    Parameters
    ----------
    matches : MarkerMatches
        ``left_px`` / ``right_px`` (N, 2) distorted pixels in each half image.
    calib : StereoCalibration
        Intrinsics, distortion, left→right (R, T) and ``sensor_from_left``.
    method : {"general", "disparity"}
        Ray midpoint with the full extrinsics, or the paper's rectified-disparity formulas.
    rays : optional
        :func:`matched_rays` of ``matches`` if already computed ("general" only).

    Returns
    -------
    MarkerCloud
        ``ids`` as in ``matches``; ``xyz_mm`` (N, 3) apparent positions (straight rays, no refraction),
        sensor frame, mm. Markers whose rays are parallel or whose disparity is not positive are dropped
        (their ids are simply absent).

    Notes
    -----
    ``"disparity"`` needs points inside the rectified field; both methods agree to ~1e-9 mm on
    analytic points (tests/test_triangulation.py).
    """
    if method not in METHODS:
        raise TriangulationError(f"triangulate: unknown method {method!r}; choose one of {METHODS}")
    if len(matches) == 0:
        return MarkerCloud(np.empty(0, np.int64), np.empty((0, 3)))
    if rays is not None and method != "general":
        raise TriangulationError("triangulate: precomputed rays serve the 'general' method only")
    xyz = _general(matches, calib, rays) if method == "general" else _disparity(matches, calib)
    ok = np.all(np.isfinite(xyz), axis=1)
    return MarkerCloud(matches.ids[ok], xyz[ok])
