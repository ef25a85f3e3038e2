"""Stage 6: refraction (depth) correction for markers seen through the acrylic + gel stack.

The optical stack is flat (sensor frame, planes z = const)::

    camera (air, n = 1) | z = design.acrylic_air_z_mm | acrylic (n_a, thickness A)
                        | z = design.gel_acrylic_z_mm | gel (n_g) with the markers

Light from a marker bends away from the normal at each interface, so straight-ray triangulation
(:mod:`pipeline.geometry.triangulation`) places markers too close to the cameras, and a depth change dz
appears as roughly dz / n_g.

Two corrections:

* :func:`correct_exact` — back-project both pixels to rays in air, refract them with the vector
  form of Snell's law at both planes, and intersect the refracted rays in the gel (closest point of
  approach). Exact for a flat stack with known indices and calibrated cameras.
* :func:`correct_linear` — the paper's linear model (Eq. 8): depth displacement from an undeformed
  reference scaled by the effective index n (fitted by
  :func:`pipeline.geometry.index_fit.fit_refractive_index`).

Measuring the indices from a press (``calibrate-refraction``) is :mod:`pipeline.geometry.index_fit`.

References
----------
StereoTacTip paper, Sec. "Depth Correction Model", Eq. (3)-(8) and the error term E of Fig. 7.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np

from pipeline.design import SensorDesign
from pipeline.errors import UserError
from pipeline.geometry.triangulation import camera_poses, matched_rays
from pipeline.types import MarkerCloud, MarkerMatches, StereoCalibration

__all__ = ["RefractionError", "snell", "refract_stack_rays", "correct_exact", "correct_linear",
           "project_through_stack"]

N_AIR = 1.0  # the paper's n_air = 1.00027 changes depths by < 0.03 %; the design's indices are relative to air
_BISECT_ITERS = 64  # halves the ray-parameter bracket [0, 1) to 2^-64: far below double precision of the result


class RefractionError(UserError, ValueError):
    """Refraction input is unusable (points outside the gel, too few calibration samples, ...)."""


def snell(d: np.ndarray, normal: np.ndarray, eta: float) -> np.ndarray:
    """Refract unit directions at a surface, vector form of Snell's law.

    Parameters
    ----------
    d : (N, 3) unit incident directions
    normal : (3,) unit surface normal pointing back toward the incident side (-z for rays going +z)
    eta : n_incident / n_transmitted

    Returns
    -------
    (N, 3) unit transmitted directions; NaN rows for total internal reflection.
    """
    cos_i = -d @ normal
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    with np.errstate(invalid="ignore"):
        t = eta * d + (eta * cos_i - np.sqrt(k))[:, None] * normal
    t[k < 0] = np.nan
    return t


def _indices(design: SensorDesign, n_gel: float | None, n_acrylic: float | None) -> tuple[float, float]:
    return (design.optics.acrylic_n if n_acrylic is None else float(n_acrylic),
            design.optics.gel_n if n_gel is None else float(n_gel))


def refract_stack_rays(origins: np.ndarray, dirs: np.ndarray, design: SensorDesign, *,
                       n_gel: float | None = None, n_acrylic: float | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Carry rays from the cameras (in air) through the acrylic into the gel.

    Parameters
    ----------
    origins : (N, 3) ray origins below the acrylic (camera centres), sensor frame, mm
    dirs : (N, 3) unit directions with positive z (toward the skin)
    design : SensorDesign
        Gives the interface planes and the indices (overridable with ``n_gel`` / ``n_acrylic``).

    Returns
    -------
    points : (N, 3) where each ray enters the gel (on z = design.gel_acrylic_z_mm), mm
    dirs_gel : (N, 3) unit directions inside the gel
    Rows of rays that never reach the stack (dz <= 0) are NaN.
    """
    n_a, n_g = _indices(design, n_gel, n_acrylic)
    up = np.array([0.0, 0.0, -1.0])  # normal facing the incoming rays
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        s1 = (design.acrylic_air_z_mm - o[:, 2]) / d[:, 2]
        p1 = o + s1[:, None] * d
        d1 = snell(d, up, N_AIR / n_a)
        s2 = (design.gel_acrylic_z_mm - p1[:, 2]) / d1[:, 2]
        p2 = p1 + s2[:, None] * d1
        d2 = snell(d1, up, n_a / n_g)
    bad = ~(d[:, 2] > 0) | ~(s1 >= 0)
    p2[bad] = np.nan
    d2[bad] = np.nan
    return p2, d2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _refract_row(o, d, z_air, z_gel, eta_a, eta_g):
    """One ray of :func:`refract_stack_rays`, the same operations in the same order (each numpy
    expression there rounds once per operation, as here; Snell's law is taken with the normal
    (0, 0, -1), whose products ``-d . n`` and ``m n`` are exact). Returns the gel entry point and
    direction, NaN where :func:`refract_stack_rays` gives NaN."""
    nan = np.nan
    s1 = (z_air - o[2]) / d[2]
    p1x, p1y, p1z = o[0] + s1 * d[0], o[1] + s1 * d[1], o[2] + s1 * d[2]
    # air -> acrylic
    c = d[2]                                             # -d . (0, 0, -1)
    k = 1.0 - eta_a * eta_a * (1.0 - c * c)
    m = eta_a * c - math.sqrt(k) if k >= 0 else nan
    t0, t1, t2 = eta_a * d[0] + m * 0.0, eta_a * d[1] + m * 0.0, eta_a * d[2] + m * -1.0
    if k < 0:
        t0 = t1 = t2 = nan
    s2 = (z_gel - p1z) / t2
    p2x, p2y, p2z = p1x + s2 * t0, p1y + s2 * t1, p1z + s2 * t2
    # acrylic -> gel
    c = t2
    k = 1.0 - eta_g * eta_g * (1.0 - c * c)
    m = eta_g * c - math.sqrt(k) if k >= 0 else nan
    g0, g1, g2 = eta_g * t0 + m * 0.0, eta_g * t1 + m * 0.0, eta_g * t2 + m * -1.0
    if k < 0:
        g0 = g1 = g2 = nan
    if not (d[2] > 0) or not (s1 >= 0):
        p2x = p2y = p2z = g0 = g1 = g2 = nan
    return p2x, p2y, p2z, g0, g1, g2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _stack_midpoints(o1, d1, o2, d2, z_air, z_gel, eta_a, eta_g, xyz, gap):
    """:func:`refract_stack_rays` of both rays of every marker and :func:`closest_points` of the
    refracted pairs, in one pass with no (N, 3) temporaries: the same operations in the same order,
    so the same numbers (bit for bit with numpy 2.4's einsum order on x86-64; tests/test_refraction.py
    holds them to 1e-12 mm wherever numpy sums the dot products in another order)."""
    for i in range(len(o1)):
        ax, ay, az, ux, uy, uz = _refract_row(o1[i], d1[i], z_air, z_gel, eta_a, eta_g)
        bx, by, bz, vx, vy, vz = _refract_row(o2[i], d2[i], z_air, z_gel, eta_a, eta_g)
        wx, wy, wz = ax - bx, ay - by, az - bz
        # the dot products summed as numpy's einsum sums three products (x + z first, then y)
        b = (ux * vx + uz * vz) + uy * vy
        dd = (ux * wx + uz * wz) + uy * wy
        e = (vx * wx + vz * wz) + vy * wy
        denom = 1.0 - b * b
        s = (b * e - dd) / denom
        t = (e - b * dd) / denom
        q1x, q1y, q1z = ax + s * ux, ay + s * uy, az + s * uz
        q2x, q2y, q2z = bx + t * vx, by + t * vy, bz + t * vz
        if denom < 1e-12:
            xyz[i, 0] = xyz[i, 1] = xyz[i, 2] = gap[i] = np.nan
            continue
        xyz[i, 0], xyz[i, 1], xyz[i, 2] = 0.5 * (q1x + q2x), 0.5 * (q1y + q2y), 0.5 * (q1z + q2z)
        rx, ry, rz = q1x - q2x, q1y - q2y, q1z - q2z
        gap[i] = math.sqrt(rx * rx + ry * ry + rz * rz)


def correct_exact(matches: MarkerMatches, calib: StereoCalibration, design: SensorDesign, *,
                  n_gel: float | None = None, n_acrylic: float | None = None,
                  return_gap: bool = False, rays: tuple[np.ndarray, ...] | None = None
                  ) -> MarkerCloud | tuple[MarkerCloud, np.ndarray]:
    """True marker positions from matched pixels by exact ray tracing through the flat stack.

    Parameters
    ----------
    matches : MarkerMatches
        Distorted pixels of each marker in both views.
    calib : StereoCalibration
        Cameras; ``sensor_from_left`` places them relative to the stack.
    design : SensorDesign
        Interface planes and refractive indices (``n_gel`` / ``n_acrylic`` override the indices).
    rays : optional
        :func:`pipeline.geometry.triangulation.matched_rays` of ``matches`` if already computed.

    Returns
    -------
    MarkerCloud
        Closest-approach midpoints of the two refracted rays in the gel, sensor frame, mm. Markers
        whose rays do not reach the gel are dropped.
    gap : (N,) float64, only with ``return_gap``
        Closest-approach distance of the two refracted rays of each kept marker (mm): ~0 for a
        correct left/right pair (pixel noise), large for two different markers (see
        :data:`pipeline.runner.STEREO_GATE_MM`).

    Notes
    -----
    Exact for a flat stack: on points projected by :func:`project_through_stack` the error is at the
    level of the undistortion's numerical precision (< 1e-6 mm, tests/test_refraction.py). Errors in
    ``sensor_from_left`` (the chessboard cannot measure it) shift the stack relative to the cameras and
    are not corrected.
    """
    if len(matches) == 0:
        empty = MarkerCloud(np.empty(0, np.int64), np.empty((0, 3)))
        return (empty, np.empty(0)) if return_gap else empty
    o1, d1, o2, d2 = (np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3)
                      for a in (matched_rays(matches, calib) if rays is None else rays))
    n_a, n_g = _indices(design, n_gel, n_acrylic)
    # refract_stack_rays of both rays and closest_points of the pair, fused (same numbers)
    xyz, gap = np.empty((len(o1), 3)), np.empty(len(o1))
    _stack_midpoints(o1, d1, o2, d2, float(design.acrylic_air_z_mm), float(design.gel_acrylic_z_mm), N_AIR / n_a,
                     n_a / n_g, xyz, gap)
    ok = np.all(np.isfinite(xyz), axis=1)
    cloud = MarkerCloud(matches.ids[ok], xyz[ok])
    return (cloud, gap[ok]) if return_gap else cloud


def correct_linear(cloud: MarkerCloud, reference: MarkerCloud, n_gel: float, design: SensorDesign) -> MarkerCloud:
    """The paper's linear depth correction (Eq. 8) relative to an undeformed reference frame.

    Implements, per marker id i present in both clouds::

        z_c[i] = z_rest[i] + n_gel * (z'[i] - z'_ref[i]),    x_c = x'[i],  y_c = y'[i]

    where z' is the apparent (triangulated) depth, z'_ref the apparent depth of the same marker in the
    undeformed reference, and z_rest the design's true rest depth (``design.rest_markers_mm()[i, 2]``).

    Why this form: Eq. (3)-(8) show |P_t1 P_t2| ≈ n_gel |P'_t1 P'_t2| for a marker moving from rest
    P_t1 to P_t2 — only depth *changes* are scaled by n; the absolute apparent depth is not (the paper
    notes absolute positions are unreliable and calibrates on relative positions). The paper's Eq. (8)
    writes z_c = z' + n_gel z with z the apparent change; anchoring the change at the known rest depth
    instead of the apparent one removes the constant apparent-depth offset of the stack (several mm
    here). x and y are left at their apparent values, as in the paper (refraction "primarily impacts
    the Z-axis direction").

    Parameters
    ----------
    cloud, reference : MarkerCloud
        Apparent positions (sensor frame, mm) of the current and the undeformed frame.
    n_gel : float
        Effective refractive index (the paper fits 1.51 for acrylic + gel).
    design : SensorDesign
        Supplies the rest depths by canonical id.

    Returns
    -------
    MarkerCloud of the ids present in both clouds (others are dropped).

    Notes
    -----
    The error grows with the incidence angle (paper's error term E, Fig. 7): ~1 % of the displacement
    at 10° and more for off-axis markers of wide patterns (tests/test_refraction.py measures it).
    """
    if not n_gel >= 1.0:
        raise RefractionError(f"correct_linear: n_gel must be >= 1, got {n_gel}")
    rest = design.rest_markers_mm()
    if len(cloud.ids) and (cloud.ids.min() < 0 or cloud.ids.max() >= len(rest)):
        raise RefractionError(f"correct_linear: marker ids outside 0..{len(rest) - 1} of design {design.name!r}")
    ref_index = {int(i): k for k, i in enumerate(reference.ids)}
    keep = np.array([int(i) in ref_index for i in cloud.ids], dtype=bool)
    ids = cloud.ids[keep]
    xyz = cloud.xyz_mm[keep].copy()
    ref_z = reference.xyz_mm[[ref_index[int(i)] for i in ids], 2] if len(ids) else np.empty(0)
    xyz[:, 2] = rest[ids, 2] + n_gel * (xyz[:, 2] - ref_z)
    return MarkerCloud(ids, xyz)


def _solve_ray_parameter(rho: np.ndarray, h: list[np.ndarray], n: list[float]) -> np.ndarray:
    """Solve sum_i h_i p / sqrt(n_i^2 - p^2) = rho for the ray parameter p = n sin(theta) in [0, n_min).

    The left side is increasing in p, so bisection on [0, n_min) converges unconditionally.
    """
    lo = np.zeros_like(rho)
    hi = np.full_like(rho, min(n))
    for _ in range(_BISECT_ITERS):
        mid = 0.5 * (lo + hi)
        f = sum(hi_ * mid / np.sqrt(ni * ni - mid * mid) for hi_, ni in zip(h, n)) - rho
        pos = f > 0
        hi = np.where(pos, mid, hi)
        lo = np.where(pos, lo, mid)
    return 0.5 * (lo + hi)


def _air_points(points: np.ndarray, centre: np.ndarray, design: SensorDesign, n_a: float, n_g: float) -> np.ndarray:
    """For each point, where its refracted path to ``centre`` crosses the acrylic/air plane, (N, 3)."""
    h_air = design.acrylic_air_z_mm - centre[2]
    if not h_air > 0:
        raise RefractionError(f"camera centre z = {centre[2]:.3f} mm is not below the acrylic "
                              f"(z = {design.acrylic_air_z_mm:.3f} mm)")
    h_acr = np.full(len(points), design.optics.acrylic_thickness_mm)
    h_gel = points[:, 2] - design.gel_acrylic_z_mm
    dxy = points[:, :2] - centre[:2]
    rho = np.hypot(dxy[:, 0], dxy[:, 1])
    p = _solve_ray_parameter(rho, [np.full(len(points), h_air), h_acr, h_gel], [N_AIR, n_a, n_g])
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(rho[:, None] > 0, dxy / rho[:, None], 0.0)
    r_air = h_air * p / np.sqrt(N_AIR * N_AIR - p * p)
    return np.column_stack([centre[0] + r_air * u[:, 0], centre[1] + r_air * u[:, 1],
                            np.full(len(points), design.acrylic_air_z_mm)])


def project_through_stack(points_mm: np.ndarray, calib: StereoCalibration, design: SensorDesign, *,
                          n_gel: float | None = None, n_acrylic: float | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Project 3-D points in the gel into both cameras along their refracted paths.

    For each camera and point the refracted path lies in the vertical plane through the camera centre
    and the point (the interfaces are planes z = const). Snell's invariant p = n sin(theta) is shared by
    all segments; p solves sum_i h_i tan(theta_i) = horizontal distance (1-D root find). The air segment
    is then projected with ``cv2.projectPoints`` (with lens distortion).

    Parameters
    ----------
    points_mm : (N, 3) float64
        Points in the gel (z > design.gel_acrylic_z_mm), sensor frame, mm.
    calib : StereoCalibration
    design : SensorDesign

    Returns
    -------
    left_px, right_px : (N, 2) float64 distorted pixels (u, v) in each half image.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(pts)):
        raise RefractionError("project_through_stack: points contain NaN or inf")
    if np.any(pts[:, 2] <= design.gel_acrylic_z_mm):
        worst = float(pts[:, 2].min())
        raise RefractionError(f"project_through_stack: points must lie in the gel (z > {design.gel_acrylic_z_mm:.3f} "
                              f"mm); lowest z = {worst:.3f} mm")
    n_a, n_g = _indices(design, n_gel, n_acrylic)
    out = []
    for pose, K, D in zip(camera_poses(calib), (calib.K1, calib.K2), (calib.D1, calib.D2)):
        if len(pts) == 0:
            out.append(np.empty((0, 2)))
            continue
        q = _air_points(pts, pose[:3, 3], design, n_a, n_g)
        cam_from_sensor = np.linalg.inv(pose)
        rvec, _ = cv2.Rodrigues(cam_from_sensor[:3, :3])
        px, _ = cv2.projectPoints(q.reshape(-1, 1, 3), rvec, cam_from_sensor[:3, 3], K, D)
        out.append(px.reshape(-1, 2))
    return out[0], out[1]
