"""Stage 7: skin surface from the (refraction-corrected) marker cloud.

The pins hold each marker a distance H + T below the outer skin, along the skin normal (the paper's
assumption: stiff pins stay perpendicular to the skin). So:

1. fit a smooth marker surface z = f(x, y) through the markers (smoothing thin-plate spline);
2. its unit normal at each marker, N = (-f_x, -f_y, 1) / |.|, points out of the skin (+z);
3. the skin point of each marker is P_s = P + (H + T) N;
4. :func:`height_map` refits a surface through the skin points on a regular grid.

Sign note: the paper (Eq. 10) writes P_s = P - (H + T) N with its normal oriented toward the cameras;
here N points out of the skin (+z, toward the object) and markers sit *below* the skin, hence the +.

References
----------
StereoTacTip paper, Sec. "Skin Surface Reconstruction", Eq. (9)-(10).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, QhullError

from pipeline.design import SensorDesign
from pipeline.errors import UserError
from pipeline.geometry.spline import SMOOTHING, ThinPlateSpline
from pipeline.types import HeightMap, MarkerCloud, SkinSurface

__all__ = ["SurfaceError", "skin_surface", "height_map", "fit_surface", "ThinPlateSpline", "SMOOTHING", "MIN_MARKERS",
           "GRID_STEP_MM"]

MIN_MARKERS = 6       # a thin-plate spline with a linear tail needs well over 3 non-collinear points
GRID_STEP_MM = 0.25   # default height-map resolution: ~1/10 of the 2.54 mm marker separation


class SurfaceError(UserError, ValueError):
    """Too few or degenerate markers to fit a surface."""


def fit_surface(xyz_mm: np.ndarray, *, smoothing: float = SMOOTHING, scratch: bool = False) -> ThinPlateSpline:
    """Thin-plate spline z = f(x, y) through points (N, 3) mm; raises SurfaceError if degenerate.
    ``scratch``: see :class:`ThinPlateSpline` (the spline lives only until the next such fit)."""
    xyz = np.asarray(xyz_mm, dtype=np.float64).reshape(-1, 3)
    if len(xyz) < MIN_MARKERS:
        raise SurfaceError(f"surface fit: need at least {MIN_MARKERS} markers, got {len(xyz)}")
    if not np.all(np.isfinite(xyz)):
        raise SurfaceError(f"surface fit: {int((~np.isfinite(xyz)).any(axis=1).sum())} of {len(xyz)} points are not finite")
    try:
        return ThinPlateSpline(xyz[:, :2], xyz[:, 2], smoothing, scratch=scratch)
    except np.linalg.LinAlgError as exc:
        raise SurfaceError(f"surface fit: {len(xyz)} markers are degenerate (collinear or duplicated): {exc}") from None


def _normals(f: ThinPlateSpline) -> np.ndarray:
    """Unit normals (-f_x, -f_y, 1) / |.| at the spline's centres."""
    return f.normals_at_centres()


def skin_surface(cloud: MarkerCloud, design: SensorDesign, *, smoothing: float = SMOOTHING) -> SkinSurface:
    """Skin points from marker positions (paper Eq. 9-10).

    Parameters
    ----------
    cloud : MarkerCloud
        True (refraction-corrected) marker positions, sensor frame, mm.
    design : SensorDesign
        Pin height H and skin thickness T (offset H + T = ``design.marker_depth_mm``).

    Returns
    -------
    SkinSurface
        ``xyz_mm`` = marker + (H + T) N, ``normals`` = N, the unit normals of the fitted marker surface
        at each marker (pointing +z, out of the skin).

    Notes
    -----
    Assumes the pins stay normal to the skin; the twin's physics does not enforce this, so the
    benchmarks measure what the assumption costs. Needs at least :data:`MIN_MARKERS` markers.
    """
    f = fit_surface(cloud.xyz_mm, smoothing=smoothing, scratch=True)   # used here only: reused buffers
    N = _normals(f)
    return SkinSurface(cloud.ids, cloud.xyz_mm + design.marker_depth_mm * N, N)


def height_map(surface_or_points, x_mm: np.ndarray | None = None, y_mm: np.ndarray | None = None, *,
               mask_radius_mm: float | None = None, step_mm: float = GRID_STEP_MM,
               smoothing: float = SMOOTHING) -> HeightMap:
    """Resample a surface through points onto a regular grid.

    Parameters
    ----------
    surface_or_points : SkinSurface, MarkerCloud or (N, 3) array, sensor frame, mm
    x_mm, y_mm : (W,), (H,) increasing grid axes, mm; default: the points' bounding box at ``step_mm``
    mask_radius_mm : float, optional
        Also blank cells farther than this from the sensor axis (e.g. the gel radius).

    Returns
    -------
    HeightMap with NaN outside the convex hull of the points (no extrapolation).
    """
    pts = surface_or_points.xyz_mm if hasattr(surface_or_points, "xyz_mm") else np.asarray(surface_or_points)
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if len(pts) < MIN_MARKERS:
        raise SurfaceError(f"height_map: need at least {MIN_MARKERS} points, got {len(pts)}")
    if x_mm is None:
        x_mm = np.arange(np.floor(pts[:, 0].min() / step_mm), np.ceil(pts[:, 0].max() / step_mm) + 1) * step_mm
    if y_mm is None:
        y_mm = np.arange(np.floor(pts[:, 1].min() / step_mm), np.ceil(pts[:, 1].max() / step_mm) + 1) * step_mm
    x_mm, y_mm = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
    gx, gy = np.meshgrid(x_mm, y_mm)
    q = np.column_stack([gx.ravel(), gy.ravel()])
    try:
        inside = Delaunay(pts[:, :2]).find_simplex(q) >= 0
    except QhullError as exc:
        raise SurfaceError(f"height_map: points are degenerate in x-y: {exc}") from None
    if mask_radius_mm is not None:
        inside &= np.hypot(q[:, 0], q[:, 1]) <= mask_radius_mm
    z = np.full(len(q), np.nan)
    if inside.any():
        z[inside] = fit_surface(pts, smoothing=smoothing)(q[inside])
    return HeightMap(x_mm, y_mm, z.reshape(gy.shape))
