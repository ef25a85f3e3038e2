"""Rejection of what is not a marker (glare, the bright rim, debris) and the handling of touching markers."""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from pipeline.vision.detection.candidates import ELONGATION, MEASURE_SIGMA, RADIUS_PER_SIGMA, SIGMA
from pipeline.vision.detection.crowding import flanked, ring_spread, split_centroids
from pipeline.vision.detection.numpy_order import median
from pipeline.vision.detection.params import DetectionParams
from pipeline.vision.detection.peaks import suppress
from pipeline.vision.detection.scale_space import scale_below_lowest
from pipeline.vision.nearest import nearest_other_distances
from pipeline.vision.detection.photometry import Measurements, group_offsets, refine_and_measure

#: Floor (on the [0, 1] scale) of the contrast that scales the isolation limits, so that a candidate
#: without contrast gets a tiny positive limit rather than zero or a negative one.
_CONTRAST_FLOOR = 1e-6
#: Markers that must pass the strict tests before the image's typical marker (median scale, marker
#: field) is trusted; with fewer, a median says nothing and only the strict tests apply.
MIN_TYPICAL_MARKERS = 5
#: A blob whose core is more than ``_MAX_GLARE_CORE_SATURATION`` saturated is LED glare, unless the
#: median accepted marker has at least ``_CLIPPED_CORE_SATURATION`` of its core saturated (the
#: exposure clips every marker: saturation then says nothing).
_CLIPPED_CORE_SATURATION = 0.5
_MAX_GLARE_CORE_SATURATION = 0.3
#: A pin squeezed between touching neighbours on opposite sides reads elongated: their light fills
#: the dark on both flanks, which flattens its response along the row (measured 5.4 and 6.3 for pins
#: at 5 mm of press in a 217-pin dome). Such a candidate is a marker up to this multiple of
#: ``max_elongation`` when peers lighting its ring (as :func:`pipeline.vision.detection.crowding.ring_spread` reckons them) lie on
#: opposite sides of it (:func:`pipeline.vision.detection.crowding.flanked`).
_SQUEEZED_ELONGATION_FACTOR = 2.0


def _inside_hull(xy: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(N,) bool: ``xy`` inside the marker field: the convex hull of ``ref`` grown by half the median
    nearest-neighbour spacing of ``ref`` away from its centroid (an outer-ring marker that failed the
    strict tests sits on the hull's edge, not inside it). False everywhere for < 3 points or a
    degenerate hull."""
    from scipy.spatial import ConvexHull, QhullError

    if len(ref) < 3:
        return np.zeros(len(xy), bool)
    spacing = float(np.median(nearest_other_distances(np.ascontiguousarray(ref, np.float64))))
    c = ref.mean(axis=0)
    r = np.maximum(np.hypot(*(ref - c).T), 1e-9)[:, None]
    grown = c + (ref - c) * (1.0 + 0.5 * spacing / r)
    try:
        eq = ConvexHull(grown).equations           # outward normals n and offsets: inside where n.x + b <= 0
    except QhullError:
        return np.zeros(len(xy), bool)
    return np.all(xy @ eq[:, :2].T + eq[:, 2] <= 0.0, axis=1)


def _ring_background(grey: np.ndarray, xy: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Median of the background ring (as the photometry's: ``RING_IN r + RING_GAP_PX .. RING_IN r + RING_WIDTH_PX`` px about the
    rounded centre) per centre, on the [0, 1] scale; NaN where the ring is wholly outside the image."""
    out = np.full(len(xy), np.nan)
    defaults = DetectionParams()
    grey = np.ascontiguousarray(grey)
    for r in np.unique(radius):                     # the measuring scales: a few radii a view
        sel = np.flatnonzero(radius == r)
        dx, dy = group_offsets(float(r), defaults)[:2]
        out[sel] = _ring_medians(grey, np.ascontiguousarray(xy[sel], np.float64), dx, dy)
    return out


@numba.njit(cache=True, nogil=True)
def _ring_medians(grey, xy, dx, dy):
    h, w = grey.shape
    out = np.full(len(xy), np.nan)
    vals = np.empty(len(dx))
    for i in range(len(xy)):
        cx, cy = int(np.rint(xy[i, 0])), int(np.rint(xy[i, 1]))
        m = 0
        for k in range(len(dx)):
            x, y = cx + dx[k], cy + dy[k]
            if 0 <= x < w and 0 <= y < h:
                vals[m] = grey[y, x]
                m += 1
        if m > 0:
            out[i] = median(vals[:m]) / 255.0
    return out



def separate_debris(grey: np.ndarray, cand_all: np.ndarray, cand: np.ndarray, measured: Measurements,
                    params: DetectionParams) -> tuple[np.ndarray, np.ndarray, Measurements]:
    """Candidates with the debris (specks far smaller than the typical marker) suppressed apart from the
    markers, so that a speck on a marker cannot shadow it, and re-measured.

    The typical marker is the median scale of the candidates in ``cand`` (suppressed, measured as
    ``measured``) that pass the strict tests; debris is every candidate of ``cand_all`` (unsuppressed)
    below 1/``params.debris_size_ratio`` of it. Debris is still measured, as a blob that may light a
    neighbour's ring (see :func:`pipeline.vision.detection.crowding.ring_spread`), and is never kept. Returns the candidates (markers
    first), the (N,) debris mask and their measurements; unchanged, with no debris, when fewer than
    :data:`MIN_TYPICAL_MARKERS` pass the strict tests.
    """
    typical = ((measured.contrast >= params.min_contrast) & (cand[:, ELONGATION] <= params.max_elongation)
               & (measured.sat <= params.max_saturated_fraction)
               & (measured.sectors.max(axis=1) <= params.isolation * np.maximum(measured.contrast, _CONTRAST_FLOOR)))
    if typical.sum() < MIN_TYPICAL_MARKERS:
        return cand, np.zeros(len(cand), bool), measured
    small_all = cand_all[:, SIGMA] < float(np.median(cand[typical, SIGMA])) / params.debris_size_ratio
    parts = [suppress(cand_all[~small_all], params.min_separation_px),
             suppress(cand_all[small_all], params.min_separation_px)]
    cand = np.concatenate(parts)
    debris = np.arange(len(cand)) >= len(parts[0])
    return cand, debris, refine_and_measure(grey, cand, params)


#: Typical neighbours (nearest first) whose median scale is a candidate's local reference size.
LOCAL_SIZE_NEIGHBOURS = 6


def _local_scale(cand: np.ndarray, typical: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Median scale of the :data:`LOCAL_SIZE_NEIGHBOURS` typical candidates nearest each of ``which``
    (the candidate itself excluded): the size a marker there should have. A strongly pressed skin
    moves markers towards and away from the cameras by millimetres, so markers in a valley of the
    press look uniformly smaller than the image's median (down to the narrowed scale space's lowest
    scale, where their scale is not refined); a speck is small against its neighbours too."""
    ref = np.flatnonzero(typical)
    out = np.full(int(which.sum()), np.inf)
    if len(ref) < LOCAL_SIZE_NEIGHBOURS + 1:
        return out
    xy = cand[:, :2]
    _, j = cKDTree(xy[ref]).query(xy[which], k=LOCAL_SIZE_NEIGHBOURS + 1)
    return _local_medians(ref, j, np.flatnonzero(which), np.ascontiguousarray(cand[:, SIGMA]), LOCAL_SIZE_NEIGHBOURS)


@numba.njit(cache=True, nogil=True)
def _local_medians(ref, j, idx, sigma, k):
    """Per row of ``j`` (indices into ``ref``, nearest first): the median scale of the first ``k`` that are not
    the candidate ``idx[r]`` itself."""
    out = np.empty(len(idx))
    vals = np.empty(k)
    for r in range(len(idx)):
        m = 0
        for c in range(j.shape[1]):
            nb = ref[j[r, c]]
            if nb != idx[r] and m < k:
                vals[m] = sigma[nb]
                m += 1
        out[r] = median(vals[:m])
    return out


def screen(grey: np.ndarray, cand: np.ndarray, measured: Measurements, debris: np.ndarray,
           params: DetectionParams) -> tuple[np.ndarray, np.ndarray]:
    """Which candidates are markers, and their centres with touching neighbours' light excluded.

    Contrast always; with ``params.rejections``: elongation, ring saturation and isolation, then,
    against the typical marker of this image (once :data:`MIN_TYPICAL_MARKERS` pass the strict tests),
    size, touching neighbours (:func:`pipeline.vision.detection.crowding.ring_spread`), debris, background level and core saturation.
    Returns the (N,) keep mask and the (N, 2) centres (``measured.xy`` but for crowded markers,
    re-centred by :func:`pipeline.vision.detection.crowding.split_centroids`).
    """
    xy, contrast, sectors, sat, core_sat = measured
    keep = contrast >= params.min_contrast
    if not params.rejections:
        return keep, xy
    keep &= cand[:, ELONGATION] <= params.max_elongation
    keep &= sat <= params.max_saturated_fraction
    limit = params.isolation * np.maximum(contrast, _CONTRAST_FLOOR)
    isolated = sectors.max(axis=1) <= limit
    if (keep & isolated & ~debris).sum() < MIN_TYPICAL_MARKERS:
        return keep & isolated & ~debris, xy
    # outliers against the typical marker of this image: size (a marker squeezed between touching
    # neighbours reads smaller: down to 1/ratio**2), and saturation where markers are not saturated
    # (LED glare is; exposure-clipped markers all are)
    typical = keep & isolated & ~debris
    med = float(median(cand[typical, SIGMA]))
    big_ok = cand[:, SIGMA] <= params.max_size_ratio * med
    small = cand[:, SIGMA] < med / params.max_size_ratio
    if small.any():
        idx = np.flatnonzero(small)
        need = _local_scale(cand, typical, small) / params.max_size_ratio
        small[idx] = cand[idx, SIGMA] < need
        # a candidate the size test would reject at the lowest scale of a narrowed scale space is sized
        # again with the scale below (its scale could not be refined there), where that can save it: the
        # parabola moves a scale by at most half a grid step (2**0.25)
        again = small[idx] & keep[idx] & isolated[idx] & (need <= 2.0 ** 0.25 * cand[idx, SIGMA])
        if again.any():
            small[idx[again]] = scale_below_lowest(grey, cand, idx[again], params) < need[again]
    radius = RADIUS_PER_SIGMA * cand[:, MEASURE_SIGMA]
    inside = np.zeros(len(cand), bool)
    if params.isolation_inside is not None or debris.any():
        # the marker field: the convex hull of the markers that pass the strict tests
        inside = _inside_hull(xy, xy[keep & isolated & big_ok & ~small & ~debris])
    if params.isolation_inside is not None:
        limit = np.where(inside, params.isolation_inside * np.maximum(contrast, _CONTRAST_FLOOR), limit)
    # debris explains a lit ring sector only within the marker field (specks at the edge of glare
    # outside it must not excuse the glare)
    # a pin squeezed between touching neighbours on opposite sides is elongated by their light, not
    # by its shape: a marker (then treated as any touching marker) up to a bounded elongation
    squeezed = ((contrast >= params.min_contrast) & (sat <= params.max_saturated_fraction) & big_ok & ~debris
                & (cand[:, ELONGATION] > params.max_elongation)
                & (cand[:, ELONGATION] <= _SQUEEZED_ELONGATION_FACTOR * params.max_elongation))
    if squeezed.any():
        keep |= flanked(xy, radius, squeezed, keep & big_ok & ~debris)
    peers = keep & big_ok & (~debris | inside)
    spread, crowded = ring_spread(xy, radius, sectors, peers, keep & (~isolated | small))
    keep &= (spread <= limit) & big_ok
    keep &= ~small | (crowded & (cand[:, SIGMA] >= med / params.max_size_ratio ** 2))
    if params.debris_size_ratio is not None:
        keep &= (cand[:, SIGMA] >= med / params.debris_size_ratio) & ~debris
    if params.max_background_ratio is not None and keep.any():
        idx = np.nonzero(keep)[0]
        bg = _ring_background(grey, xy[idx], radius[idx])
        keep[idx[~(bg <= params.max_background_ratio * contrast[idx])]] = False
    # (debris touching a marker is excluded from its centroid as a touching marker is)
    xy = split_centroids(grey, xy, radius, keep & crowded, (keep & big_ok) | (peers & debris), params)
    if median(core_sat[keep]) < _CLIPPED_CORE_SATURATION:
        keep &= core_sat <= _MAX_GLARE_CORE_SATURATION
    return keep, xy
