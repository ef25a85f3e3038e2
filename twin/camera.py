"""Camera model helpers for the twin's renderer: the OpenCV lens model and the one OpenGL↔OpenCV flip.

Conventions (see ``docs/ARCHITECTURE.md``): camera frames are OpenCV's (x right, y down, z forward),
pixels are OpenCV ``(u, v)`` with the centre of the top-left pixel at (0, 0). The distortion model is
OpenCV's five-term ``(k1, k2, p1, p2, k3)`` model applied to normalised coordinates ``(x/z, y/z)``.

Everything here is plain numpy so that the twin's projection is an implementation independent of
``cv2.projectPoints`` (the tests cross-check the two).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "GL_FROM_CV",
    "gl_pose_from_cv_pose",
    "gl_projection",
    "distort_normalised",
    "undistort_normalised",
    "project_camera_points",
    "pixels_to_normalised",
]

# Flip between an OpenCV camera frame (x right, y down, z forward) and an OpenGL camera frame
# (x right, y up, looking along -z): a rotation by pi about the camera x axis.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])

# Newton on the inverse lens model stops when the re-distorted point is this close (normalised units;
# 1e-12 × f ≈ 4e-10 px for f ≈ 440 px, far below anything a test can see).
UNDISTORT_TOL = 1e-12
UNDISTORT_MAX_ITER = 60


def gl_pose_from_cv_pose(world_from_camera_cv: np.ndarray) -> np.ndarray:
    """The OpenGL camera pose (pyrender's convention) of a camera given with OpenCV axes.

    This is the ONLY place where the OpenCV ↔ OpenGL camera flip happens in the twin.

    Parameters
    ----------
    world_from_camera_cv : (4, 4) float
        Pose of the camera in the world (sensor) frame, camera axes OpenCV's (x right, y down,
        z forward), mm.

    Returns
    -------
    (4, 4) float64
        The same camera with OpenGL axes (x right, y up, z backward), as ``pyrender`` expects.
    """
    T = np.asarray(world_from_camera_cv, dtype=np.float64)
    return T @ GL_FROM_CV


def gl_projection(f_px: tuple[float, float], c_px: tuple[float, float], size_px: tuple[int, int],
                  znear_mm: float, zfar_mm: float) -> np.ndarray:
    """OpenGL clip-from-camera matrix (4, 4) of a pinhole viewport (pyrender's ``IntrinsicsCamera`` formula).

    Parameters
    ----------
    f_px : (fx, fy) focal lengths, px. c_px : (cx, cy) OpenCV principal point, px (centre of the
    top-left pixel at (0, 0)). size_px : (width, height) of the viewport, px.
    znear_mm, zfar_mm : clipping distances.

    Notes
    -----
    GL window coordinates put pixel centres at +0.5, so the GL principal point is ``c_px + 0.5``; with
    the camera pose from :func:`gl_pose_from_cv_pose` an OpenCV point (x, y, z) lands at the OpenCV pixel
    ``(fx x/z + cx, fy y/z + cy)`` counted from the TOP row (the read-back is bottom row first).
    """
    fx, fy = float(f_px[0]), float(f_px[1])
    cx, cy = float(c_px[0]) + 0.5, float(c_px[1]) + 0.5
    w, h = float(size_px[0]), float(size_px[1])
    n, f = float(znear_mm), float(zfar_mm)
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / w
    P[1, 1] = 2.0 * fy / h
    P[0, 2] = 1.0 - 2.0 * cx / w
    P[1, 2] = 2.0 * cy / h - 1.0
    P[3, 2] = -1.0
    P[2, 2] = (f + n) / (n - f)
    P[2, 3] = 2.0 * f * n / (n - f)
    return P


def distort_normalised(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV's lens model to normalised coordinates.

    Parameters
    ----------
    xy : (N, 2) float
        Ideal (pinhole) normalised coordinates ``(x/z, y/z)``.
    dist : (5,) float
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    (N, 2) float64 distorted normalised coordinates (multiply by K to get pixels).
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    k1, k2, p1, p2, k3 = (float(v) for v in np.asarray(dist, dtype=np.float64).reshape(5))
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.column_stack([xd, yd])


def _distort_jacobian(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, ...]:
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)
    dxx = radial + x * dradial_dr2 * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x
    dxy = x * dradial_dr2 * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y
    dyx = y * dradial_dr2 * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y
    dyy = radial + y * dradial_dr2 * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x
    return dxx, dxy, dyx, dyy


def undistort_normalised(xy_distorted: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Invert :func:`distort_normalised` by Newton's method (vectorised).

    Parameters
    ----------
    xy_distorted : (N, 2) float
        Distorted normalised coordinates ``K⁻¹ (u, v, 1)``.
    dist : (5,) float
        ``(k1, k2, p1, p2, k3)``; the model must be monotonic over the points (true for the designs'
        wide-angle barrel model out to the image corners).

    Returns
    -------
    (N, 2) float64 ideal normalised coordinates, re-distorting to the input within ``UNDISTORT_TOL``.

    Raises
    ------
    ValueError
        If Newton does not converge (the lens model folds over inside the requested points).
    """
    target = np.asarray(xy_distorted, dtype=np.float64).reshape(-1, 2)
    dist = np.asarray(dist, dtype=np.float64).reshape(5)
    xy = target.copy()
    for _ in range(UNDISTORT_MAX_ITER):
        res = distort_normalised(xy, dist) - target
        if np.max(np.abs(res), initial=0.0) < UNDISTORT_TOL:
            return xy
        a, b, c, d = _distort_jacobian(xy[:, 0], xy[:, 1], dist)
        det = a * d - b * c
        step_x = (d * res[:, 0] - b * res[:, 1]) / det
        step_y = (-c * res[:, 0] + a * res[:, 1]) / det
        xy[:, 0] -= step_x
        xy[:, 1] -= step_y
    res = distort_normalised(xy, dist) - target
    if np.max(np.abs(res), initial=0.0) < UNDISTORT_TOL * 1e3:
        return xy
    raise ValueError("undistort_normalised: Newton did not converge; the lens model is not invertible "
                     f"over these points (max residual {np.max(np.abs(res)):.3g})")


def project_camera_points(xyz_cam: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Project points given in an OpenCV camera frame to distorted pixels.

    Parameters
    ----------
    xyz_cam : (N, 3) float, camera frame (OpenCV axes), any unit; z must be > 0.
    K : (3, 3) intrinsics, px. dist : (5,) OpenCV distortion.

    Returns
    -------
    (N, 2) float64 pixels ``(u, v)``.
    """
    p = np.asarray(xyz_cam, dtype=np.float64).reshape(-1, 3)
    xy = p[:, :2] / p[:, 2:3]
    xyd = distort_normalised(xy, dist)
    K = np.asarray(K, dtype=np.float64)
    u = K[0, 0] * xyd[:, 0] + K[0, 1] * xyd[:, 1] + K[0, 2]
    v = K[1, 1] * xyd[:, 1] + K[1, 2]
    return np.column_stack([u, v])


def pixels_to_normalised(uv: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Ideal normalised coordinates ``(x/z, y/z)`` of the rays through distorted pixels ``uv`` (N, 2)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    K = np.asarray(K, dtype=np.float64)
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    return undistort_normalised(np.column_stack([xd, yd]), dist)
