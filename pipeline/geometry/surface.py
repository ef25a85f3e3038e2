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

import math
import threading

import numba
import numpy as np
import scipy.linalg
from scipy.spatial import Delaunay, QhullError

from pipeline.design import SensorDesign
from pipeline.errors import UserError
from pipeline.types import HeightMap, MarkerCloud, SkinSurface

__all__ = ["SurfaceError", "skin_surface", "height_map", "fit_surface", "ThinPlateSpline", "SMOOTHING", "MIN_MARKERS",
           "GRID_STEP_MM"]

# Thin-plate-spline smoothing (added to the kernel diagonal as scipy's RBFInterpolator does; mm^2 of z): 1e-3 leaves exact
# data interpolated to ~1 um yet keeps the normals stable under ~0.01 mm triangulation noise.
SMOOTHING = 1e-3
_GETRF, _GETRS = scipy.linalg.get_lapack_funcs(("getrf", "getrs"), (np.empty((2, 2)),))   # float64: dgetrf, dgetrs
# A frame's spline system is solved by iterative refinement on the factorisation of an earlier frame's system
# of the same size (:meth:`_Scratch.refined`), and factorised afresh only where that does not reach a residual
# |b - A x| <= REFINE_RTOL (|A| |x| + |b|) (infinity norms) within REFINE_STEPS corrections. Measured on the
# latency benchmark's circular217_dome press sequence (0-3 mm in 20 frames, and the 3 -> 0 mm jump): each
# correction gains 1-1.5 decades; the direct solve's own residual is ~5e-20 on this scale, 1e-15 is reached
# in 5-6 corrections, and the skin points then differ from the direct solve's by ~1e-10 mm (1e-17: 7-8
# corrections, ~1e-11 mm). A correction costs two triangular solves and a product (~0.02 ms for 217 markers)
# against ~0.3 ms for the factorisation; the press sequence is factorised again every ~10 frames.
REFINE_RTOL = 1e-15
REFINE_STEPS = 10
MIN_MARKERS = 6       # a thin-plate spline with a linear tail needs well over 3 non-collinear points
GRID_STEP_MM = 0.25   # default height-map resolution: ~1/10 of the 2.54 mm marker separation


class SurfaceError(UserError, ValueError):
    """Too few or degenerate markers to fit a surface."""


@numba.njit(cache=True, nogil=True)
def _tps_system(xy, tail, smoothing, lhs, log_r2):
    """Fill the (N + 3)^2 spline system ``[[K + s I, P], [P^T, 0]]`` (K_ij = r^2 log r, P = ``tail``)
    and ``log_r2`` (N, N) = log(r_ij^2), 0 on the diagonal; one logarithm per pair. Returns the
    system's infinity norm (largest absolute row sum)."""
    n = len(xy)
    rows = np.zeros(n + 3)                                     # absolute row sums
    for i in range(n):
        lhs[i, i] = smoothing
        log_r2[i, i] = 0.0
        rows[i] += abs(smoothing)
        for j in range(i + 1, n):
            dx, dy = xy[i, 0] - xy[j, 0], xy[i, 1] - xy[j, 1]
            r2 = dx * dx + dy * dy
            lg = math.log(r2) if r2 > 0 else 0.0
            k = 0.5 * r2 * lg                                  # r**2 log r = r2 log(r2) / 2
            lhs[i, j] = k
            lhs[j, i] = k
            log_r2[i, j] = lg
            log_r2[j, i] = lg
            rows[i] += abs(k)
            rows[j] += abs(k)
        for c in range(3):
            lhs[i, n + c] = tail[i, c]
            lhs[n + c, i] = tail[i, c]
            rows[i] += abs(tail[i, c])
            rows[n + c] += abs(tail[i, c])
    for a in range(3):
        for b in range(3):
            lhs[n + a, n + b] = 0.0
    return rows.max()


@numba.njit(cache=True, nogil=True)
def _tps_gradient_at_centres(xy, log_r2, w):
    """Kernel part of the spline gradient at its own centres: sum_j w_j (x_i - x_j)(log r_ij^2 + 1)."""
    n = len(xy)
    out = np.zeros((n, 2))
    for i in range(n):
        gx = 0.0
        gy = 0.0
        for j in range(n):
            g = (log_r2[i, j] + 1.0) * w[j]
            gx += g * (xy[i, 0] - xy[j, 0])
            gy += g * (xy[i, 1] - xy[j, 1])
        out[i, 0], out[i, 1] = gx, gy
    return out


class _Scratch:
    """Per-thread buffers for the spline system and its pairwise logarithms, reused frame after frame.

    The system of a 217-marker sensor is ~390 kB and its logarithms as much again: fresh arrays of
    that size come from the kernel page by page on every frame, and where page faults are slow (2
    shared cores) that cost the skin stage of circular217_dome 1.66 ms against 0.99 ms with the
    buffers kept (one sensor per process, a frame after any other job). Kept per marker count (a
    stream sees a few), at most :data:`_ENTRIES` of them."""

    _ENTRIES = 8
    _local = threading.local()

    @classmethod
    def get(cls, name: str, shape: tuple[int, int]) -> np.ndarray:
        bufs = getattr(cls._local, "bufs", None)
        if bufs is None:
            bufs = cls._local.bufs = {}
        key = (name, shape)
        buf = bufs.get(key)
        if buf is None:
            if len(bufs) >= 2 * cls._ENTRIES:
                bufs.clear()
            buf = bufs[key] = np.empty(shape)
        return buf

    @classmethod
    def system(cls, m: int) -> np.ndarray:
        """An (m, m) buffer for this frame's system: not the one holding the kept factorisation."""
        kept = getattr(cls._local, "factor", None)
        name = "lhs1" if kept is not None and kept[0] is cls.get("lhs0", (m, m)) else "lhs0"
        return cls.get(name, (m, m))

    @classmethod
    def keep_factor(cls, system: np.ndarray, lu: np.ndarray, piv: np.ndarray) -> None:
        """Keep a fresh factorisation (``lu`` overwrote ``system``) for the next frames' refinement."""
        cls._local.factor = (system, lu, piv)

    @classmethod
    def refined(cls, lhs: np.ndarray, rhs: np.ndarray, norm: float) -> np.ndarray | None:
        """Solve ``lhs x = rhs`` by iterative refinement on the kept factorisation of an earlier
        frame's system of the same size (a sensor's markers move little between frames, so that
        factorisation is a close preconditioner): at most :data:`REFINE_STEPS` corrections until the
        residual is at the level of a direct solve's (:data:`REFINE_RTOL`). None where there is no
        such factorisation or it does not get there: the caller factorises this system afresh."""
        kept = getattr(cls._local, "factor", None)
        if kept is None or kept[1].shape != lhs.shape:
            return None
        _, lu, piv = kept
        x, info = _GETRS(lu, piv, rhs)
        b_norm = float(np.abs(rhs).max())
        last = math.inf
        for _ in range(REFINE_STEPS):
            if info != 0 or not np.all(np.isfinite(x)):
                return None
            r = rhs - lhs @ x
            res = float(np.abs(r).max())
            if res <= REFINE_RTOL * (norm * float(np.abs(x).max()) + b_norm):
                return x
            if res >= last:       # not contracting: this system is too far from the kept one
                return None
            last = res
            dx, info = _GETRS(lu, piv, r)
            x = x + dx
        return None


class ThinPlateSpline:
    """Smoothing thin-plate spline z = f(x, y) with a linear tail, and its analytic gradient.

    The function scipy's ``RBFInterpolator(kernel="thin_plate_spline", degree=1, smoothing=s)`` fits
    (kernel ``phi(r) = r**2 log r``; ``s`` added to the kernel matrix's diagonal; the tail's coordinates
    shifted and scaled to [-1, 1] for conditioning; tests/test_surface.py compares the two), solved
    directly: at the pipeline's sizes (<= a few hundred markers) scipy's general machinery costs more
    than the fit, and the normals needed four extra evaluations per marker for finite differences.
    ``gradient`` is exact, and at the centres it reuses the fit's pairwise logarithms. The system and
    the gradient at the centres are compiled loops (one logarithm per pair, no (N, N) temporaries).
    """

    _CHUNK = 4096  # query points evaluated at a time (bounds the (chunk, N) blocks)

    def __init__(self, xy: np.ndarray, z: np.ndarray, smoothing: float = SMOOTHING, *, scratch: bool = False) -> None:
        """``scratch``: build the system in this thread's reused buffers (:class:`_Scratch`); the
        spline is then valid only until the next ``scratch`` fit on the same thread (for a caller
        that evaluates it at once and drops it, as :func:`skin_surface` does)."""
        xy = np.ascontiguousarray(xy, dtype=np.float64)
        n = len(xy)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        self._shift = 0.5 * (hi + lo)
        self._scale = np.where(hi > lo, 0.5 * (hi - lo), 1.0)
        self.centres = xy
        tail = self._tail(xy)
        if np.linalg.matrix_rank(tail) < 3:
            raise np.linalg.LinAlgError("the points are collinear: the linear tail is not determined")
        if scratch:
            lhs = _Scratch.system(n + 3)
            self._log_r2 = _Scratch.get("log_r2", (n, n))
        else:
            lhs = np.empty((n + 3, n + 3))
            self._log_r2 = np.empty((n, n))
        norm = _tps_system(xy, tail, float(smoothing), lhs, self._log_r2)
        rhs = np.concatenate([np.asarray(z, dtype=np.float64), np.zeros(3)])
        sol = _Scratch.refined(lhs, rhs, norm) if scratch else None
        if sol is None:
            # symmetric system: its transpose is the Fortran-ordered array LAPACK wants, factorised in place
            # (LAPACK's getrf/getrs called directly: what scipy.linalg.lu_factor / lu_solve call, without
            # their per-call checks and lookups)
            lu, piv, info = _GETRF(lhs.T, overwrite_a=True)
            if info > 0:
                raise np.linalg.LinAlgError(f"Diagonal number {info} is exactly zero. Singular matrix.")
            sol, info = _GETRS(lu, piv, rhs, overwrite_b=True)
            if info != 0:
                raise np.linalg.LinAlgError(f"the spline system could not be solved (LAPACK info {info})")
            if not np.all(np.isfinite(sol)):
                raise np.linalg.LinAlgError("the spline system is singular (duplicated points?)")
            if scratch:
                _Scratch.keep_factor(lhs, lu, piv)
        self._w, self._a = sol[:n], sol[n:]

    def _tail(self, q: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones(len(q)), (q - self._shift) / self._scale])

    def _pairwise(self, q: np.ndarray):
        """dx, dy, r**2 and log(r**2) (0 where r = 0) from the centres to the query points (M, N)."""
        dx = q[:, 0, None] - self.centres[None, :, 0]
        dy = q[:, 1, None] - self.centres[None, :, 1]
        r2 = dx * dx + dy * dy
        return dx, dy, r2, np.log(np.where(r2 > 0, r2, 1.0))

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """f at query points (M, 2)."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, 2)
        out = np.empty(len(q))
        for k in range(0, len(q), self._CHUNK):
            c = q[k:k + self._CHUNK]
            _, _, r2, lg = self._pairwise(c)
            out[k:k + self._CHUNK] = (0.5 * r2 * lg) @ self._w + self._tail(c) @ self._a   # r**2 log r
        return out

    def gradient(self, q: np.ndarray | None = None) -> np.ndarray:
        """(df/dx, df/dy) at query points (M, 2), default the centres: grad phi = (x - c)(2 log r + 1),
        which vanishes at r = 0 with x - c."""
        if q is None:
            return _tps_gradient_at_centres(self.centres, self._log_r2, self._w) + self._a[1:] / self._scale
        q = np.asarray(q, dtype=np.float64).reshape(-1, 2)
        out = np.empty((len(q), 2))
        for k in range(0, len(q), self._CHUNK):
            dx, dy, _, lg = self._pairwise(q[k:k + self._CHUNK])
            g = lg + 1.0
            out[k:k + len(dx), 0] = (g * dx) @ self._w
            out[k:k + len(dx), 1] = (g * dy) @ self._w
        return out + self._a[1:] / self._scale


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
    g = f.gradient()
    N = np.column_stack([-g, np.ones(len(g))])
    return N / np.linalg.norm(N, axis=1, keepdims=True)


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
