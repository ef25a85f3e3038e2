"""Spatial peaks of the DoH maps, their sub-pixel and cross-scale refinement, and the suppression of
detections that are one marker."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.nearest import nearest_other_distances, x_order, x_range
from pipeline.vision.detection.candidates import (COLUMNS, ELONGATION, MEASURE_SIGMA, MEASURE_STEPS_PER_OCTAVE,
                                                  RADIUS_PER_SIGMA, RESPONSE, SIGMA, X, Y)

#: Floor of the denominators of the peak and eigenvalue fits: a flat response or a zero eigenvalue
#: (a straight edge) gives a bounded offset / a huge elongation instead of a division by zero.
_TINY = 1e-12
#: Log2-scale step (octaves) assumed beyond either end of the scale list when the continuous scale
#: is interpolated there: the half-octave step of the default sqrt(2) grid.
_EDGE_LOG2_STEP = 0.5


@numba.njit(cache=True, nogil=True)
def doh_peaks(lxx, lyy, lxy, doh, threshold, border, offset, peaks, n_peaks):
    """Bright-blob DoH of one level and its spatial peaks.

    ``doh = min(Lxx, 0) Lyy - Lxy**2`` in float32: where the DoH is positive both eigenvalues share
    the sign of ``Lxx``, so this equals the DoH on bright blobs and is <= 0 on dark ones (never a
    peak above the positive threshold). A peak is at least each of its 8 neighbours, above
    ``threshold`` and ``border`` (>= 1) px inside the level; its flat index plus ``offset`` is
    appended to ``peaks`` from ``n_peaks`` on. Returns the new count.
    """
    h, w = doh.shape
    for y in range(h):
        for x in range(w):
            doh[y, x] = min(lxx[y, x], np.float32(0.0)) * lyy[y, x] - lxy[y, x] * lxy[y, x]
    thr = np.float32(threshold)
    for y in range(border, h - border):
        for x in range(border, w - border):
            c = doh[y, x]
            if not c > thr:
                continue
            if (c >= doh[y - 1, x - 1] and c >= doh[y - 1, x] and c >= doh[y - 1, x + 1] and c >= doh[y, x - 1]
                    and c >= doh[y, x + 1] and c >= doh[y + 1, x - 1] and c >= doh[y + 1, x]
                    and c >= doh[y + 1, x + 1]):
                peaks[n_peaks] = offset + y * w + x
                n_peaks += 1
    return n_peaks


@numba.njit(cache=True, nogil=True)
def scale_sample(doh, k, x_full, y_full, offs, hs, ws, fxs, fys):
    """Response of scale ``k`` at full-resolution (x_full, y_full): its level pixel containing the
    point; -inf where scale ``k`` does not exist (outside the scale list, or a level too small)."""
    if not (0 <= k < len(hs) and hs[k] > 0):
        return -np.inf
    u = min(int((x_full + 0.5) / fxs[k]), ws[k] - 1)     # coordinates are >= 0: truncation floors
    v = min(int((y_full + 0.5) / fys[k]), max(hs[k] - 1, 0))
    return np.float64(doh[offs[k] + v * ws[k] + u])


@numba.njit(cache=True, nogil=True)
def peak_kernel(g, doh, lxx, lyy, lxy, offs, hs, ws, fxs, fys, log_s):
    """Sparse work of :func:`find_candidates` on the spatial peaks ``g`` (flat indices into the packed
    scale maps, scale by scale): sub-pixel peak, the cross-scale maximum test against the two
    neighbouring scales sampled at the same place, the continuous scale, the elongation and the
    measuring scale. Returns the (M, COLUMNS) candidates (:mod:`.candidates`) that pass, in the order of ``g``."""
    n_s = len(log_s)
    out = np.empty((len(g), COLUMNS))
    m = 0
    i_s = 0
    for gi in g:
        while gi >= offs[i_s + 1]:
            i_s += 1
        w = ws[i_s]
        ys, xs = divmod(gi - offs[i_s], w)
        # sub-pixel peak in the response (refined later on the full image); differences of float32
        # samples are exact in float32, the rest in float64
        c = np.float64(doh[gi])
        dxp = np.float32(doh[gi + 1] - doh[gi - 1])
        dyp = np.float32(doh[gi + w] - doh[gi - w])
        dx = min(max(0.5 * dxp / max(2 * c - doh[gi + 1] - doh[gi - 1], _TINY), -0.5), 0.5)
        dy = min(max(0.5 * dyp / max(2 * c - doh[gi + w] - doh[gi - w], _TINY), -0.5), 0.5)
        # peak value of the fitted parabolas (a sample up to half a level px off the peak under-reads
        # it, which would bias scale selection towards finer levels)
        c = c + 0.25 * (dxp * dx + dyp * dy)
        x_full = (xs + dx + 0.5) * fxs[i_s] - 0.5
        y_full = (ys + dy + 0.5) * fys[i_s] - 0.5
        # response of the neighbouring scales at (x_full, y_full): their level pixel containing it
        lo = scale_sample(doh, i_s - 1, x_full, y_full, offs, hs, ws, fxs, fys)
        hi = scale_sample(doh, i_s + 1, x_full, y_full, offs, hs, ws, fxs, fys)
        if not (c >= lo and c >= hi):
            continue
        # continuous scale: parabola through the three responses on the log-sigma axis (the sqrt(2)
        # grid is too coarse to place the background ring just outside the marker)
        curv = lo - 2 * c + hi
        delta = 0.0
        if np.isfinite(lo) and np.isfinite(hi) and curv < 0:
            delta = min(max(0.5 * (np.float32(lo) - np.float32(hi)) / curv, -0.5), 0.5)   # float32 samples
        if delta < 0:
            step = log_s[i_s] - log_s[i_s - 1] if i_s > 0 else _EDGE_LOG2_STEP
        else:
            step = log_s[i_s + 1] - log_s[i_s] if i_s < n_s - 1 else _EDGE_LOG2_STEP
        s_cont = 2.0 ** (log_s[i_s] + delta * step)
        a, d, e = np.float64(lxx[gi]), np.float64(lyy[gi]), np.float64(lxy[gi])
        tr, det = a + d, a * d - e * e
        disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
        l1, l2 = abs(tr / 2 - disc), abs(tr / 2 + disc)
        out[m, X], out[m, Y], out[m, SIGMA], out[m, RESPONSE] = x_full, y_full, s_cont, c
        out[m, ELONGATION] = max(l1, l2) / max(min(l1, l2), _TINY)
        out[m, MEASURE_SIGMA] = 2.0 ** (np.rint(MEASURE_STEPS_PER_OCTAVE * np.log2(s_cont)) / MEASURE_STEPS_PER_OCTAVE)
        m += 1
    return out[:m]


#: Two candidates whose scales differ by at most this ratio (one step of the default sqrt(2) scale
#: grid) are blobs of one size: in :func:`suppress`, pins side by side rather than a speck and the
#: marker it lies on.
SIBLING_SCALE_RATIO = math.sqrt(2.0)
#: ... and lie beside each other: centres at least this fraction of the sum of their radii apart
#: (pins squeezed into touching measured 0.73-1.02, the middle one of three in a row the closest; a
#: marker's own weaker, off-centre responses lie within it, ~0.58 on the real TacTip frames).
SIBLING_MIN_SEPARATION = 0.65
#: ... and answer comparably: at least this fraction of the survivor's response (squeezed pins measured
#: 0.38-0.74 of their brighter neighbour's; the faint far edge of a marker whose own response a speck
#: on it dropped, 0.28-0.29 on the real TacTip frames).
SIBLING_MIN_RESPONSE_FRACTION = 0.33


def suppress(cand: np.ndarray, min_sep: float) -> np.ndarray:
    """Cross-scale NMS: drop a candidate when a stronger one lies within ``max(min_sep, r_i, r_j)``,
    except that a candidate already dropped does not drop one of the size of the survivor it fell to,
    beside it (:func:`_suppress_kernel`)."""
    if len(cand) < 2:
        return cand
    return cand[_suppress_kernel(cand, float(min_sep), SIBLING_SCALE_RATIO, SIBLING_MIN_SEPARATION,
                                 SIBLING_MIN_RESPONSE_FRACTION)]


@numba.njit(cache=True, nogil=True)
def _suppress_kernel(cand, min_sep, sibling_ratio, sibling_separation, sibling_response):
    """Keep mask of :func:`suppress`. Candidates are visited strongest first (ties: the earlier) and each
    drops every weaker candidate closer than the larger of their radii (``max(min_sep, sqrt(2) sigma)``),
    whether or not it survives itself -- except that a candidate dropped by a survivor of finer scale
    than itself spares the candidates finer than itself whose scale is within ``sibling_ratio`` of that
    survivor's, whose centre is at least ``sibling_separation`` x the sum of the two radii
    (``sqrt(2) sigma``) away from the survivor's and whose response is at least ``sibling_response`` x
    the survivor's.

    Two pins squeezed together also answer as ONE blob at a coarser scale, centred between them and
    with a radius reaching both. That merged response is weaker than the brighter pin's but can be
    stronger than the dimmer one's: the brighter pin drops it, and it must not then drop the dimmer
    pin, a blob of the brighter one's size beside it. A dropped candidate otherwise keeps suppressing:
    a bright speck on a marker's edge drops the marker's own response, which must still drop the
    marker's other, off-centre responses (coarser than the speck, or reached only through another
    dropped response), or they would come back as a marker beside the speck. Neighbours are found along x-sorted candidates within the largest radius."""
    n = len(cand)
    radius = np.empty(n)
    for i in range(n):
        radius[i] = max(min_sep, RADIUS_PER_SIGMA * cand[i, SIGMA])
    r_max = radius.max()
    order = np.argsort(cand[:, X])
    pos = np.empty(n, np.intp)
    for a in range(n):
        pos[order[a]] = a
    by_rank = np.argsort(-cand[:, RESPONSE], kind="mergesort")   # stable: ties keep the earlier first
    rank = np.empty(n, np.intp)
    for a in range(n):
        rank[by_rank[a]] = a
    by = np.full(n, -1, np.intp)         # the candidate that dropped this one (the first, strongest)
    keep = np.ones(n, np.bool_)
    log_ratio = math.log(sibling_ratio)
    for i in by_rank:
        k = by[i]
        # a merged response: dropped directly by a survivor of finer scale
        merged = k >= 0 and keep[k] and cand[i, SIGMA] > cand[k, SIGMA]
        for step in (-1, 1):
            b = pos[i] + step
            while 0 <= b < n:
                j = order[b]
                b += step
                if abs(cand[j, X] - cand[i, X]) > r_max:
                    break
                if rank[j] < rank[i] or math.hypot(cand[i, X] - cand[j, X], cand[i, Y] - cand[j, Y]) >= max(radius[i], radius[j]):
                    continue
                if (merged and cand[j, SIGMA] < cand[i, SIGMA] and cand[j, RESPONSE] >= sibling_response * cand[k, RESPONSE]
                        and abs(math.log(cand[j, SIGMA] / cand[k, SIGMA])) <= log_ratio
                        and math.hypot(cand[k, X] - cand[j, X], cand[k, Y] - cand[j, Y])
                        >= sibling_separation * RADIUS_PER_SIGMA * (cand[j, SIGMA] + cand[k, SIGMA])):
                    continue
                if keep[j]:
                    keep[j] = False
                    by[j] = i
    return keep


@numba.njit(cache=True, nogil=True)
def _spacing_kernel(xy, strongest_first, order, xs, radius):
    keep = np.ones(len(xy), np.bool_)
    for i in strongest_first:
        if not keep[i]:
            continue
        lo, hi = x_range(xs, xy[i, 0], radius)
        for k in range(lo, hi):
            j = order[k]
            if j != i and keep[j] and math.hypot(xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1]) < radius:
                keep[j] = False
    return keep


def spacing_suppress(xy: np.ndarray, response: np.ndarray, fraction: float) -> np.ndarray:
    """Keep mask: of two centres closer than ``fraction`` x the median nearest-neighbour spacing the
    weaker response is dropped (strongest first, so a dropped centre never removes another)."""
    xy = np.ascontiguousarray(xy, np.float64)
    radius = fraction * float(np.median(nearest_other_distances(xy)))
    return _spacing_kernel(xy, np.argsort(-response, kind="stable"), *x_order(xy), radius)
