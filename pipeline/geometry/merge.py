"""Multi-contact merge: many overlapping taps -> one contiguous, smoothed point map.

Paper, "Experiments III / Data Processing". Each tap gives the skin surface as points in the sensor
frame; the robot's tap pose puts them into one global frame. Neighbouring taps overlap on their
outer parts, where the paper observes a bias (z over-estimated toward the periphery, where the skin
meets the rigid mount), so in the overlaps the lower of each nearest-neighbour pair is kept:

1. overlap: a point whose nearest neighbour IN ANOTHER TAP is closer than T = 0.6 mm (x-y plane);
2. pair each overlap point with that neighbour and keep it only if it is the lower of the two;
3. merge the kept overlap points with the non-overlap points;
4. smooth z with the mollifier phi(rho) = exp(-1 / (1 - rho^2)) / I on the unit disk (0 outside),
   phi_eps(rho) = phi(rho / eps) / eps^2, eps = 0.25 mm, I chosen so that phi integrates to 1.

Two discretisations of step 4 (both normalised, so a constant is left unchanged exactly):

* scattered points (:func:`mollify_points`): z_k <- sum_l w_kl z_l / sum_l w_kl over the points l with
  |p_l - p_k| < eps (x-y), w_kl = phi_eps(|p_l - p_k|). With marker spacings (~1.8 mm) much larger
  than eps this touches only points closer than 0.25 mm, i.e. it averages near-duplicates from
  overlapping taps; a point with no neighbour inside eps keeps its z.
* a regular grid (:func:`mollify_grid`): a discrete kernel K_ij = phi_eps(rho_ij) dx dy / sum(...)
  (weights sum to 1), applied as a NaN-aware normalised convolution. If the grid step is >= eps the
  kernel is the single centre cell (identity).

Frames: points handed to :func:`merge_taps` are in one common frame (mm, z up). Use
:func:`tap_points_to_global` to move sensor-frame points of a downward-facing sensor there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import integrate
from scipy.spatial import cKDTree

from pipeline.types import DataError, HeightMap

__all__ = [
    "OVERLAP_THRESHOLD_MM", "MOLLIFIER_EPS_MM", "MOLLIFIER_I", "mollifier", "mollifier_kernel",
    "tap_points_to_global", "OverlapSelection", "select_overlap", "MergeResult", "merge_taps",
    "mollify_points", "mollify_grid", "grid_points",
]

OVERLAP_THRESHOLD_MM = 0.6   # paper: nearest-neighbour distance below T = 0.6 mm marks an overlap
MOLLIFIER_EPS_MM = 0.25      # paper: mollifier length scale epsilon


def _phi_unnormalised(rho):
    rho = np.asarray(rho, dtype=np.float64)
    out = np.zeros_like(rho)
    inside = rho < 1.0
    out[inside] = np.exp(-1.0 / (1.0 - rho[inside] ** 2))
    return out


# I = 2 pi int_0^1 exp(-1/(1-r^2)) r dr = 0.46651239...; integrated once at import
MOLLIFIER_I = 2.0 * math.pi * integrate.quad(lambda r: math.exp(-1.0 / (1.0 - r * r)) * r, 0.0, 1.0,
                                             epsabs=1e-14, epsrel=1e-12)[0]


def mollifier(rho_mm, eps_mm: float = MOLLIFIER_EPS_MM) -> np.ndarray:
    """phi_eps(rho) = phi(rho / eps) / eps^2 (1/mm^2); integrates to 1 over the plane.

    ``rho_mm`` : array of radial distances (mm), any shape.
    """
    if not eps_mm > 0:
        raise DataError(f"mollifier eps must be > 0 mm, got {eps_mm!r}")
    return _phi_unnormalised(np.asarray(rho_mm, dtype=np.float64) / eps_mm) / (MOLLIFIER_I * eps_mm**2)


def mollifier_kernel(dx_mm: float, dy_mm: float | None = None, eps_mm: float = MOLLIFIER_EPS_MM) -> np.ndarray:
    """Discrete mollifier on a grid of steps (dx, dy) mm: (2a+1, 2b+1) weights summing to 1.

    Row index is y, column index x, centre at the middle. ``phi_eps * dx * dy`` sampled at the
    cell offsets, renormalised (the renormalisation corrects the quadrature error of coarse grids).
    """
    dy_mm = dx_mm if dy_mm is None else dy_mm
    a = int(math.floor(eps_mm / dx_mm))
    b = int(math.floor(eps_mm / dy_mm))
    X, Y = np.meshgrid(np.arange(-a, a + 1) * dx_mm, np.arange(-b, b + 1) * dy_mm)
    k = mollifier(np.hypot(X, Y), eps_mm) * dx_mm * dy_mm
    if k.sum() <= 0:  # eps below the grid step: only the centre
        k = np.zeros_like(k)
        k[b, a] = 1.0
    return k / k.sum()


def tap_points_to_global(points_mm: np.ndarray, tap_origin_mm: Sequence[float], *,
                         facing_down: bool = True) -> np.ndarray:
    """Sensor-frame points of one tap -> the global frame.

    Parameters
    ----------
    points_mm : (N, 3) sensor frame (mm; +z out of the skin toward the object)
    tap_origin_mm : (3,) global position of the sensor-frame origin (centre of the undeformed outer
        skin) at the tap, mm
    facing_down : the sensor looks down on the object (sensor +z = global -z); its x is global x and
        its y is global -y (a 180 deg rotation about x). False: sensor axes = global axes.

    Returns
    -------
    (N, 3) global points, mm, z up.
    """
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    R = np.diag([1.0, -1.0, -1.0]) if facing_down else np.eye(3)
    return p @ R.T + np.asarray(tap_origin_mm, dtype=np.float64).reshape(1, 3)


def _check_taps(taps: Sequence[np.ndarray]) -> list[np.ndarray]:
    out = []
    for i, t in enumerate(taps):
        a = np.asarray(t, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise DataError(f"tap {i}: points must be (N, 3), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise DataError(f"tap {i}: points contain NaN or inf")
        out.append(a)
    return out


@dataclass(frozen=True)
class OverlapSelection:
    """Per point of the concatenated taps (M = sum N_i):

    tap : (M,) tap index; nn_dist_mm : (M,) x-y distance to the nearest point of another tap (inf if
    none); nn_index : (M,) that point's index in the concatenation (-1 if none); overlap : (M,) bool
    ``nn_dist_mm < threshold``; keep : (M,) bool, non-overlap points plus overlap points that are the
    lower of their nearest-neighbour pair.
    """

    points_mm: np.ndarray
    tap: np.ndarray
    nn_dist_mm: np.ndarray
    nn_index: np.ndarray
    overlap: np.ndarray
    keep: np.ndarray


def select_overlap(taps: Sequence[np.ndarray], *, threshold_mm: float = OVERLAP_THRESHOLD_MM) -> OverlapSelection:
    """Find the overlap between taps and choose the lower point of each nearest-neighbour pair.

    Parameters
    ----------
    taps : sequence of (N_i, 3) arrays, common global frame, mm, z up
    threshold_mm : T; a point is in the overlap when its nearest neighbour in ANOTHER tap is closer
        (x-y distance) than T

    Notes
    -----
    Pairing: every overlap point p is paired with its nearest other-tap neighbour q and kept iff
    z_p < z_q, or z_p == z_q and p comes first in the concatenation. For mutual nearest neighbours
    exactly one of the pair survives; a non-mutual chain keeps each point that is lower than its own
    partner. Points of the same tap never pair (a tap's own spacing is not an overlap).
    """
    taps = _check_taps(taps)
    if not threshold_mm > 0:
        raise DataError(f"overlap threshold must be > 0 mm, got {threshold_mm!r}")
    sizes = [len(t) for t in taps]
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    pts = np.vstack(taps) if taps else np.zeros((0, 3))
    tap = np.repeat(np.arange(len(taps)), sizes)
    M = len(pts)
    nn_d = np.full(M, np.inf)
    nn_i = np.full(M, -1, dtype=np.int64)
    trees = [cKDTree(t[:, :2]) if len(t) else None for t in taps]
    lo = [t[:, :2].min(axis=0) if len(t) else None for t in taps]
    hi = [t[:, :2].max(axis=0) if len(t) else None for t in taps]
    for i, ti in enumerate(taps):
        if not len(ti):
            continue
        for j, tj in enumerate(taps):
            if i == j or trees[j] is None:
                continue
            # bounding boxes farther apart than T cannot hold an overlap pair
            if np.any(lo[j] - hi[i] > threshold_mm) or np.any(lo[i] - hi[j] > threshold_mm):
                continue
            d, k = trees[j].query(ti[:, :2], k=1)
            better = d < nn_d[starts[i]:starts[i + 1]]
            idx = np.flatnonzero(better) + starts[i]
            nn_d[idx] = d[better]
            nn_i[idx] = k[better] + starts[j]
    overlap = nn_d < threshold_mm
    keep = ~overlap
    o = np.flatnonzero(overlap)
    if len(o):
        zp, zq = pts[o, 2], pts[nn_i[o], 2]
        keep[o] = (zp < zq) | ((zp == zq) & (o < nn_i[o]))
    return OverlapSelection(pts, tap, nn_d, nn_i, overlap, keep)


@dataclass(frozen=True)
class MergeResult:
    """The merged point map R_new: points_mm (K, 3) global mm (z smoothed when eps > 0), raw_z_mm
    (K,) z before smoothing, tap (K,) source tap, overlap (K,) whether the point came from an
    overlap; selection: the full :class:`OverlapSelection`."""

    points_mm: np.ndarray
    raw_z_mm: np.ndarray
    tap: np.ndarray
    overlap: np.ndarray
    selection: OverlapSelection


def merge_taps(taps: Sequence[np.ndarray], *, threshold_mm: float = OVERLAP_THRESHOLD_MM,
               eps_mm: float | None = MOLLIFIER_EPS_MM) -> MergeResult:
    """Overlap selection, lower-point pairing, merge, then mollifier smoothing (``eps_mm=None``: none).

    ``taps`` : sequence of (N_i, 3) point sets in one global frame (mm, z up), e.g. from
    :func:`tap_points_to_global`.
    """
    sel = select_overlap(taps, threshold_mm=threshold_mm)
    pts = sel.points_mm[sel.keep]
    raw_z = pts[:, 2].copy()
    if eps_mm is not None and len(pts):
        pts = pts.copy()
        pts[:, 2] = mollify_points(pts, eps_mm=eps_mm)
    return MergeResult(pts, raw_z, sel.tap[sel.keep], sel.overlap[sel.keep], sel)


def mollify_points(points_mm: np.ndarray, *, eps_mm: float = MOLLIFIER_EPS_MM) -> np.ndarray:
    """Mollified z of scattered points: normalised phi_eps-weighted mean over x-y neighbours < eps.

    points_mm : (N, 3) mm. Returns (N,) smoothed z (mm). Each point's own weight phi_eps(0) > 0 keeps
    the denominator positive.
    """
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if not len(p):
        return np.zeros(0)
    tree = cKDTree(p[:, :2])
    pairs = tree.query_pairs(eps_mm, output_type="ndarray")
    w0 = float(mollifier(0.0, eps_mm))
    num = w0 * p[:, 2].copy()
    den = np.full(len(p), w0)
    if len(pairs):
        a, b = pairs[:, 0], pairs[:, 1]
        w = mollifier(np.hypot(*(p[a, :2] - p[b, :2]).T), eps_mm)
        np.add.at(num, a, w * p[b, 2])
        np.add.at(den, a, w)
        np.add.at(num, b, w * p[a, 2])
        np.add.at(den, b, w)
    return num / den


def mollify_grid(hm: HeightMap, *, eps_mm: float = MOLLIFIER_EPS_MM) -> HeightMap:
    """Mollify a regular :class:`HeightMap` with the discrete kernel (weights sum to 1).

    NaN cells are no-data: the convolution is normalised by the kernel weight that fell on valid
    cells, so edges are not pulled toward zero; NaN cells stay NaN.
    """
    from scipy.ndimage import convolve

    dx = float(np.mean(np.diff(hm.x_mm))) if len(hm.x_mm) > 1 else 1.0
    dy = float(np.mean(np.diff(hm.y_mm))) if len(hm.y_mm) > 1 else 1.0
    k = mollifier_kernel(dx, dy, eps_mm)
    valid = np.isfinite(hm.z_mm)
    z0 = np.where(valid, hm.z_mm, 0.0)
    num = convolve(z0, k, mode="constant", cval=0.0)
    den = convolve(valid.astype(np.float64), k, mode="constant", cval=0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(valid & (den > 0), num / np.where(den > 0, den, 1.0), np.nan)
    return HeightMap(hm.x_mm, hm.y_mm, z)


def grid_points(points_mm: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, *,
                max_gap_mm: float = 2.0) -> HeightMap:
    """Linear interpolation of scattered z onto the grid x (W,), y (H,) (mm); cells farther than
    ``max_gap_mm`` from every point, or outside the points' convex hull, are NaN."""
    from scipy.interpolate import LinearNDInterpolator

    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    X, Y = np.meshgrid(np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64))
    if len(p) < 3:
        return HeightMap(x_mm, y_mm, np.full(X.shape, np.nan))
    z = LinearNDInterpolator(p[:, :2], p[:, 2])(X, Y)
    d, _ = cKDTree(p[:, :2]).query(np.column_stack([X.ravel(), Y.ravel()]), k=1)
    z[d.reshape(X.shape) > max_gap_mm] = np.nan
    return HeightMap(x_mm, y_mm, z)
