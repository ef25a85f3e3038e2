"""Exact refraction through the sensor's flat optical stack (air → acrylic → gel), per camera.

This is the twin's own implementation, independent of ``pipeline.geometry.refraction`` (which the benchmarks
test against it).

Geometry (sensor frame, mm; see :mod:`pipeline.design`): the interfaces are horizontal planes,
``z = design.acrylic_air_z_mm`` (air below, acrylic above) and ``z = design.gel_acrylic_z_mm`` (acrylic
below, gel above). The gel fills everything above its interface (the skin is opaque, so nothing beyond
it is seen through it). The cameras sit in air below the stack.

The ray from a camera centre ``C`` to a point ``P`` lies in the vertical plane through ``C`` and ``P``.
With the ray parameter ``p = sin θ_air = n_i sin θ_i`` (Snell), its horizontal run through a layer of
thickness ``t_i`` and index ``n_i`` is ``t_i p / sqrt(n_i² − p²)``; the total run must equal the
horizontal distance ``ρ`` from ``C`` to ``P``. In terms of ``q = tan θ_air`` the run ``h(q)`` is increasing
and concave, and ``ρ / Σ t_i`` is a lower bound of the root, so Newton's method started there converges
monotonically (each tangent overshoots nothing) and quadratically.

The *apparent* point of ``P`` for that camera is ``P' = C + s · d_air``, with ``d_air`` the unit ray
direction in air and ``s`` the optical path length ``Σ n_i L_i`` of the true ray. ``P'`` projects to the
same pixel as ``P`` and ``s`` grows monotonically along every ray, so depth order along a pixel's ray is
preserved: a pinhole renderer that draws apparent points draws the refracted scene.

References
----------
StereoTacTip paper, Sec. IV-B (refraction model, Fig. 7): this module is the exact version of the
paper's small-angle model, with the acrylic and the gel kept as separate layers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.design import SensorDesign
from pipeline.errors import UserError
from twin.camera import distort_normalised

__all__ = [
    "OpticsError",
    "FlatStack",
    "RayPaths",
    "solve_paths",
    "apparent_points",
    "refract_direction",
    "trace_forward",
    "project_exact",
    "camera_centre",
]

# Newton stops when the horizontal run matches the target to this (mm): 100x below the 1e-9 mm the exact
# refraction is held to in tests/test_optics.py.
PATH_TOL_MM = 1e-11
PATH_MAX_ITER = 100


class OpticsError(UserError, ValueError):
    """A point or ray handed to the optics cannot be traced (wrong side of the camera, bad shape)."""


@dataclass(frozen=True)
class FlatStack:
    """Horizontal refracting planes above a camera.

    Parameters
    ----------
    interfaces_z_mm : tuple of float, strictly increasing
        z of each interface, sensor frame, mm.
    indices : tuple of float
        Refractive index of each medium, ``len(interfaces_z_mm) + 1`` values; ``indices[0]`` is the
        camera's medium (below the first interface), ``indices[-1]`` fills everything above the last.
    """

    interfaces_z_mm: tuple[float, ...]
    indices: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.indices) != len(self.interfaces_z_mm) + 1:
            raise OpticsError(f"FlatStack: {len(self.interfaces_z_mm)} interfaces need "
                              f"{len(self.interfaces_z_mm) + 1} indices, got {len(self.indices)}")
        if any(b <= a for a, b in zip(self.interfaces_z_mm, self.interfaces_z_mm[1:])):
            raise OpticsError(f"FlatStack: interfaces_z_mm must increase, got {self.interfaces_z_mm}")
        if any(n < 1.0 for n in self.indices):
            raise OpticsError(f"FlatStack: refractive indices must be >= 1, got {self.indices}")

    @classmethod
    def from_design(cls, design: SensorDesign, *, through_stack: bool = True) -> "FlatStack":
        """The design's acrylic + gel stack, or plain air (``through_stack=False``: skin module removed)."""
        if not through_stack:
            return cls((), (1.0,))
        return cls((design.acrylic_air_z_mm, design.gel_acrylic_z_mm),
                   (1.0, design.optics.acrylic_n, design.optics.gel_n))

    @property
    def is_air(self) -> bool:
        return all(n == 1.0 for n in self.indices)


@dataclass(frozen=True)
class RayPaths:
    """Refracted rays from one camera centre to N points.

    ``direction_air`` (N, 3) unit direction of each ray in the camera's medium (sensor frame);
    ``hits_mm`` (N, K, 3) where each ray crosses interface k (NaN if the point lies below it);
    ``optical_path_mm`` (N,) Σ n_i L_i; ``apparent_mm`` (N, 3) = C + optical_path · direction_air;
    ``ray_parameter`` (N,) p = sin θ_air = n_i sin θ_i.
    """

    direction_air: np.ndarray
    hits_mm: np.ndarray
    optical_path_mm: np.ndarray
    apparent_mm: np.ndarray
    ray_parameter: np.ndarray


def _layer_thicknesses(camera_z: float, point_z: np.ndarray, stack: FlatStack) -> np.ndarray:
    """(N, L) vertical extent of each medium between the camera and each point, mm."""
    bounds = np.array([camera_z, *stack.interfaces_z_mm, np.inf])
    lo = np.maximum(bounds[:-1], camera_z)[None, :]
    hi = np.minimum(bounds[1:][None, :], point_z[:, None])
    return np.clip(hi - lo, 0.0, None)


def solve_paths(camera_xyz_mm: np.ndarray, points_mm: np.ndarray, stack: FlatStack, *,
                with_hits: bool = True, q0: np.ndarray | None = None) -> RayPaths:
    """Solve Snell's law exactly for the ray from a camera centre to each point (vectorised).

    Parameters
    ----------
    camera_xyz_mm : (3,) float
        Camera centre, sensor frame, mm; must lie below the first interface.
    points_mm : (N, 3) float
        Points above the camera (z > camera z), sensor frame, mm.
    stack : FlatStack
    with_hits : bool
        False skips the interface crossing points (``hits_mm`` then has shape (N, 0, 3)).
    q0 : (N,) float, optional
        Warm start for ``tan θ_air`` (e.g. the previous frame's ``tan(asin(ray_parameter))``).

    Returns
    -------
    RayPaths
        Horizontal runs match to within ``PATH_TOL_MM``.

    Raises
    ------
    OpticsError
        If a point is not above the camera or the camera is not below the stack.
    """
    C = np.asarray(camera_xyz_mm, dtype=np.float64).reshape(3)
    P = np.asarray(points_mm, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise OpticsError(f"points_mm: expected shape (N, 3), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise OpticsError("points_mm: contains NaN or inf")
    if stack.interfaces_z_mm and C[2] >= stack.interfaces_z_mm[0]:
        raise OpticsError(f"camera at z = {C[2]:.3f} mm is not below the stack (first interface at "
                          f"z = {stack.interfaces_z_mm[0]:.3f} mm)")
    dz = P[:, 2] - C[2]
    if np.any(dz <= 0):
        bad = int(np.argmax(dz <= 0))
        raise OpticsError(f"points_mm[{bad}] = {P[bad].round(3).tolist()} is not above the camera "
                          f"(z must exceed {C[2]:.3f} mm)")
    n = np.asarray(stack.indices, dtype=np.float64)
    t = _layer_thicknesses(C[2], P[:, 2], stack)                      # (N, L)
    dxy = P[:, :2] - C[:2]
    rho = np.hypot(dxy[:, 0], dxy[:, 1])
    e = np.zeros_like(dxy)
    nz = rho > 0
    e[nz] = dxy[nz] / rho[nz, None]
    e[~nz, 0] = 1.0

    # Newton on q = tan(theta_air), started at the lower bound rho / sum(t) (see module notes) or at a
    # caller's warm start (any start converges: h is increasing and concave, so one step from the right
    # lands left of the root and the iteration is monotone from there).
    q = rho / t.sum(axis=1) if q0 is None else np.asarray(q0, dtype=np.float64).reshape(len(P)).copy()
    layers = [(t[:, i], float(n[i]) ** 2) for i in range(len(n)) if np.any(t[:, i] > 0)]
    for _ in range(PATH_MAX_ITER):
        one_q2 = 1.0 + q * q
        p = q / np.sqrt(one_q2)
        p2 = p * p
        h = np.zeros_like(q)
        dh_dp = np.zeros_like(q)
        for ti, ni2 in layers:
            inv = 1.0 / np.sqrt(ni2 - p2)
            h += ti * p * inv
            dh_dp += ti * ni2 * (inv * inv * inv)
        res = h - rho
        if np.max(np.abs(res), initial=0.0) < PATH_TOL_MM:
            break
        q -= res * (one_q2 * np.sqrt(one_q2)) / dh_dp        # dp/dq = (1 + q^2)^(-3/2)
    p = q / np.sqrt(1.0 + q * q)
    cos_air = 1.0 / np.sqrt(1.0 + q * q)
    d_air = np.column_stack([e * p[:, None], cos_air])

    sin_i = p[:, None] / n[None, :]
    cos_i = np.sqrt(1.0 - sin_i * sin_i)
    opl = np.sum(n[None, :] * t / cos_i, axis=1)
    K = len(stack.interfaces_z_mm)
    hits = np.full((len(P), K, 3), np.nan) if with_hits else np.empty((len(P), 0, 3))
    if with_hits:
        cum = np.cumsum(t * sin_i / cos_i, axis=1)                  # horizontal run per layer, summed
        for k, zk in enumerate(stack.interfaces_z_mm):
            reach = P[:, 2] > zk
            hits[reach, k, :2] = C[:2] + e[reach] * cum[reach, k, None]
            hits[reach, k, 2] = zk
    apparent = C[None, :] + opl[:, None] * d_air
    return RayPaths(direction_air=d_air, hits_mm=hits, optical_path_mm=opl, apparent_mm=apparent,
                    ray_parameter=p)


def apparent_points(points_mm: np.ndarray, camera_xyz_mm: np.ndarray, stack: FlatStack) -> np.ndarray:
    """Apparent positions (N, 3) mm of ``points_mm`` seen from ``camera_xyz_mm`` (see module notes)."""
    if stack.is_air:
        return np.asarray(points_mm, dtype=np.float64).copy()
    return solve_paths(camera_xyz_mm, points_mm, stack, with_hits=False).apparent_mm


def refract_direction(d: np.ndarray, n_from: float, n_to: float) -> np.ndarray:
    """Vector Snell's law at a horizontal interface (normal ±z): refracted unit directions (N, 3).

    The tangential component of ``n · d`` is conserved; the vertical component keeps its sign. Total
    internal reflection gives NaN rows.
    """
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    tang = d[:, :2] * (n_from / n_to)
    s2 = np.sum(tang**2, axis=1)
    with np.errstate(invalid="ignore"):
        dz = np.sign(d[:, 2]) * np.sqrt(1.0 - s2)
    out = np.column_stack([tang, dz])
    out[s2 > 1.0] = np.nan
    return out


def trace_forward(origin_mm: np.ndarray, directions: np.ndarray, stack: FlatStack,
                  stop_z_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Trace rays upward from a camera centre through the stack to the plane ``z = stop_z_mm``.

    Parameters
    ----------
    origin_mm : (3,) camera centre (below the stack). directions : (N, 3) directions in air, d_z > 0.
    stack : FlatStack. stop_z_mm : float, above the camera.

    Returns
    -------
    points : (N, 3) where each ray meets ``z = stop_z_mm``, mm.
    direction : (N, 3) unit direction of each ray in the medium containing that plane.
    """
    o = np.asarray(origin_mm, dtype=np.float64).reshape(3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(d[:, 2] <= 0):
        raise OpticsError("trace_forward: directions must point upward (d_z > 0)")
    pts = np.broadcast_to(o, d.shape).copy()
    for k, zk in enumerate(stack.interfaces_z_mm):
        if zk >= stop_z_mm:
            break
        pts = pts + d * ((zk - pts[:, 2]) / d[:, 2])[:, None]
        d = refract_direction(d, stack.indices[k], stack.indices[k + 1])
    pts = pts + d * ((stop_z_mm - pts[:, 2]) / d[:, 2])[:, None]
    return pts, d


def camera_centre(design: SensorDesign, side: str) -> np.ndarray:
    """Centre (3,) mm of camera ``side`` ("left" | "right") in the sensor frame."""
    return _camera_pose(design, side)[:3, 3].copy()


def _camera_pose(design: SensorDesign, side: str) -> np.ndarray:
    if side not in ("left", "right"):
        raise OpticsError(f"side: expected 'left' or 'right', got {side!r}")
    return design.camera_poses()[side]


def project_exact(points_mm: np.ndarray, design: SensorDesign, side: str, *,
                  through_stack: bool = True) -> np.ndarray:
    """Where points appear in the distorted image of camera ``side``: exact Snell + the lens model.

    Parameters
    ----------
    points_mm : (N, 3) float
        Points in the sensor frame, mm, above the camera. Points inside the gel are seen through acrylic
        and gel, points inside the acrylic through acrylic only, points below it through air only.
    design : SensorDesign
        Supplies the stack, the nominal camera poses (``camera_poses()``) and the intrinsics/distortion.
    side : "left" | "right"
    through_stack : bool
        False for the skin-less calibration set-up (whole skin module removed: air everywhere).

    Returns
    -------
    (N, 2) float64 pixel coordinates (u, v) in that camera's 640x480 image (may lie outside it).
    """
    pose = _camera_pose(design, side)
    cam = getattr(design.cameras, side)
    stack = FlatStack.from_design(design, through_stack=through_stack)
    P = np.asarray(points_mm, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise OpticsError(f"points_mm: expected shape (N, 3), got {P.shape}")
    C = pose[:3, 3]
    if stack.is_air:
        d = P - C
    else:
        d = solve_paths(C, P, stack).direction_air
    d_cam = d @ pose[:3, :3]                    # R^T d for each row: direction in camera axes
    if np.any(d_cam[:, 2] <= 0):
        raise OpticsError(f"project_exact: some points are behind camera {side!r}")
    xy = d_cam[:, :2] / d_cam[:, 2:3]
    xyd = distort_normalised(xy, cam.D)
    K = cam.K
    return np.column_stack([K[0, 0] * xyd[:, 0] + K[0, 1] * xyd[:, 1] + K[0, 2], K[1, 1] * xyd[:, 1] + K[1, 2]])
