"""Sub-pixel centroids and local photometry (background ring, angular sectors, core) per candidate."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from pipeline.vision.detection.candidates import MEASURE_SIGMA, RADIUS_PER_SIGMA, X, Y
from pipeline.vision.detection.images import CACHE_ENTRIES, U8_SCALE
from pipeline.vision.detection.params import DetectionParams

#: Angular sectors of the background ring for the isolation test (45 deg each: glare touching one
#: side of a marker lights one or two sectors, a marker's own edge lights none).
SECTORS = 8
#: The background ring spans ``RING_IN r + RING_GAP_PX .. RING_IN r + RING_WIDTH_PX`` px about a blob
#: of radius ``r``: just outside the marker edge (anti-aliasing and blur reach ~1 px past it) and, on
#: the densest real frames (r ~4.7 px, pitch 16.8 px), still inside the dark gap between markers.
RING_IN = 1.25
RING_GAP_PX = 1.0
RING_WIDTH_PX = 2.5
#: Margin (px) added to the centroid window radius ``centroid_radius_factor * r`` so that the pixels
#: the marker's anti-aliased edge touches are in it.
WINDOW_MARGIN_PX = 0.5
#: The core (peak and saturation) is the disc of radius ``CORE_FRACTION r + CORE_MARGIN_PX``: the
#: flat top of the marker, at least the centre pixel and its 4 neighbours.
CORE_FRACTION = 0.5
CORE_MARGIN_PX = 0.5
#: A centroid that moves more than ``RUNAWAY_FRACTION r + RUNAWAY_PX`` from the DoH peak has run away
#: (a neighbour or a plateau in its window) and keeps the peak: a true marker's DoH peak is within
#: about half a level pixel, well inside this.
RUNAWAY_FRACTION = 0.5
RUNAWAY_PX = 1.0


class Measurements(NamedTuple):
    """What :func:`refine_and_measure` finds per candidate (N rows, in the candidates' order)."""

    #: (N, 2) refined centres (u, v), px, full resolution.
    xy: np.ndarray
    #: (N,) peak of the core minus the ring median, on the [0, 1] scale.
    contrast: np.ndarray
    #: (N, SECTORS) mean of each angular ring sector minus the ring median (-inf wholly outside the image).
    sectors: np.ndarray
    #: (N,) saturated fraction of the ring.
    sat: np.ndarray
    #: (N,) saturated fraction of the core.
    core_sat: np.ndarray


#: Offset groups cached per process (one per distinct radius; a few dozen per image).
_OFFSET_ENTRIES = 256
#: Levels of a uint8 pixel: bins of the ring's median histogram.
_GREY_LEVELS = 256


def _patch_offsets(rmax: int) -> tuple[np.ndarray, np.ndarray]:
    r = np.arange(-rmax, rmax + 1)
    ox, oy = np.meshgrid(r, r)
    return ox.ravel(), oy.ravel()


def _group_geometry(r_blob: float, params: DetectionParams) -> tuple[float, float, float, int]:
    """(ring inner radius, ring outer radius, centroid window radius, max offset) for radius ``r_blob``."""
    r_win = params.centroid_radius_factor * r_blob + WINDOW_MARGIN_PX
    r_in, r_out = RING_IN * r_blob + RING_GAP_PX, RING_IN * r_blob + RING_WIDTH_PX
    return r_in, r_out, r_win, int(math.ceil(max(r_out, r_win)))


def group_offsets(r_blob: float, params: DetectionParams):
    """Pixel offsets (dx, dy) from a rounded centre of the ring (ordered by sector, with the sector
    starts), the centroid window and the core for blobs of radius ``r_blob``. Cached per radius."""
    key = (r_blob, params.centroid_radius_factor)
    hit = _OFFSETS.get(key)
    if hit is not None:
        return hit
    r_in, r_out, r_win, rmax = _group_geometry(r_blob, params)
    ox, oy = _patch_offsets(rmax)
    d2 = ox * ox + oy * oy
    ring_sel = (d2 >= r_in * r_in) & (d2 <= r_out * r_out)
    rox, roy = ox[ring_sel], oy[ring_sel]
    sector = (np.floor((np.arctan2(roy, rox) + np.pi) * (SECTORS / (2 * np.pi))).astype(np.intp)) % SECTORS
    o = np.argsort(sector, kind="stable")
    starts = np.searchsorted(sector[o], np.arange(SECTORS + 1)).astype(np.intp)
    win_sel = d2 <= r_win * r_win
    core_sel = d2 <= (CORE_FRACTION * r_blob + CORE_MARGIN_PX) ** 2
    hit = tuple(np.ascontiguousarray(a, dtype=np.intp) for a in
                (rox[o], roy[o], starts, ox[win_sel], oy[win_sel], ox[core_sel], oy[core_sel]))
    if len(_OFFSETS) > _OFFSET_ENTRIES:
        _OFFSETS.clear()
    _OFFSETS[key] = hit
    return hit


_OFFSETS: dict[tuple, tuple] = {}


@numba.njit(cache=True, nogil=True)
def _gather(img, ix, iy, dx, dy, k0, k1, out):
    """``out[k]`` = pixel ``(ix + dx[k], iy + dy[k])`` of the uint8 ``img`` on the [0, 1] scale for k
    in [k0, k1), -1 outside the image; returns the count inside."""
    h, w = img.shape
    n_in = 0
    for k in range(k0, k1):
        x, y = ix + dx[k], iy + dy[k]
        if 0 <= x < w and 0 <= y < h:
            out[k] = np.float32(img[y, x]) * U8_SCALE
            n_in += 1
        else:
            out[k] = -1.0
    return n_in


@numba.njit(cache=True, nogil=True)
def _ring_median(img, ix, iy, dx, dy, k0, k1, reach, out, hist):
    """:func:`_gather` of the ring into ``out`` plus the median of its inside pixels on the [0, 1]
    scale (NaN if none), from a histogram of the uint8 levels: exact, and without the data-dependent
    branches of a selection (which cost far more in the pipeline than on a repeated benchmark input).
    ``reach`` bounds ``|dx|``, ``|dy|`` over ``k0:k1``. Returns (count inside, median)."""
    h, w = img.shape
    hist[:] = 0
    n_in = 0
    if reach <= ix < w - reach and reach <= iy < h - reach:
        # the ring wholly inside: no bounds tests
        for k in range(k0, k1):
            q = img[iy + dy[k], ix + dx[k]]
            out[k] = np.float32(q) * U8_SCALE
            hist[q] += 1
        n_in = k1 - k0
    else:
        for k in range(k0, k1):
            x, y = ix + dx[k], iy + dy[k]
            if 0 <= x < w and 0 <= y < h:
                q = img[y, x]
                out[k] = np.float32(q) * U8_SCALE
                hist[q] += 1
                n_in += 1
            else:
                out[k] = -1.0
    if n_in == 0:
        return 0, np.nan
    lo_rank, hi_rank = (n_in - 1) // 2, n_in // 2
    cum = 0
    lo = -1
    hi = 255
    for b in range(_GREY_LEVELS):
        cum += hist[b]
        if lo < 0 and cum > lo_rank:
            lo = b
        if cum > hi_rank:
            hi = b
            break
    return n_in, 0.5 * (np.float64(np.float32(lo) * U8_SCALE) + np.float64(np.float32(hi) * U8_SCALE))


#: Largest window reach (px) for which :func:`_window_moments` is exact in any summation order.
_EXACT_REACH = 64


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _window_moments(img, ix, iy, spans, s0, s1, bg):
    """Background-subtracted light of a centroid window wholly inside ``img`` and its first moments
    about ``(ix, iy)``: ``sum(wt)``, ``sum(wt dx)``, ``sum(wt dy)`` with ``wt = max(v - bg, 0)``, ``v``
    the float32 pixel on the [0, 1] scale, over the row spans ``spans[s0:s1]`` (dy, first dx, last dx).

    Every term is exact in float64 and so is every partial sum: ``v`` and ``bg`` (a float32 median
    of such pixels, or 0) are float32 numbers in {0} U [2**-9, 1], hence multiples of 2**-32, and so
    are their differences (< 1); times an offset ``|d| <= reach`` and summed over at most
    ``(2 reach + 1)**2`` pixels they stay below ``2**21`` in magnitude for ``reach <=``
    :data:`_EXACT_REACH`, within float64's 53 bits. The sums are therefore the same whatever the order,
    which lets the compiler vectorise them (``reassoc``; no contraction, no reciprocals): the result
    is bit for bit the in-order loop's.
    """
    tot = 0.0
    mx = 0.0
    my = 0.0
    for sp in range(s0, s1):
        dy = spans[sp, 0]
        first = spans[sp, 1]
        seg = img[iy + dy, ix + first: ix + spans[sp, 2] + 1]   # indexed from 0: no negative-index wrap
        for k in range(seg.size):
            wt = max(np.float32(seg[k]) * U8_SCALE - bg, 0.0)
            tot += wt
            mx += wt * (first + k)
            my += wt * dy
    return tot, mx, my


@numba.njit(cache=True, nogil=True)
def _measure_kernel(img, cand, gid, n_iter, sat_thr, lims, ring_dx, ring_dy, ring_ptr, starts, win_dx, win_dy,
                    win_ptr, spans, span_ptr, reach, core_dx, core_dy, core_ptr, ring_reach, xy, contrast, sectors,
                    sat, core_sat):
    """Compiled per-candidate loop of :func:`refine_and_measure`.

    Candidate ``i`` (``cand[i, X]``, ``cand[i, Y]``) uses the geometry of group ``g = gid[i]``: the pixel
    offsets ``ring_dx[ring_ptr[g]:ring_ptr[g + 1]]`` (and likewise window and core), the ring's
    sector boundaries ``starts[g]`` (absolute indices) and the centroid run-away limit ``lims[g]``.
    Writes the refined centres ``xy`` (N, 2), ``contrast``, ``sectors`` (N, 8), ``sat``, ``core_sat``.
    Pixels outside the image read as -1: never ring or window light, never saturated. A centroid pass
    depends only on the rounded centre it starts from, so the passes stop once that stops changing,
    and the photometry reuses the first ring when the rounded centre is where it started (the result
    is the same as doing all the work).
    """
    h, w = img.shape
    ring = np.empty(len(ring_dx), np.float64)
    hist = np.empty(_GREY_LEVELS, np.int32)
    core = np.empty(len(core_dx), np.float64)
    for i in range(len(cand)):
        g = gid[i]
        r0, r1, w0, w1, c0, c1 = ring_ptr[g], ring_ptr[g + 1], win_ptr[g], win_ptr[g + 1], core_ptr[g], core_ptr[g + 1]
        x0, y0 = cand[i, X], cand[i, Y]
        ix0, iy0 = int(np.rint(x0)), int(np.rint(y0))
        n_in, med0 = _ring_median(img, ix0, iy0, ring_dx, ring_dy, r0, r1, ring_reach[g], ring, hist)
        if np.isnan(med0):
            med0 = 0.0
        bg = np.float64(np.float32(med0))
        x, y = x0, y0
        pix, piy = -1 << 30, -1 << 30
        for _ in range(max(1, n_iter)):
            ix, iy = int(np.rint(x)), int(np.rint(y))
            if ix == pix and iy == piy:
                break
            pix, piy = ix, iy
            tot = 0.0
            mx = 0.0
            my = 0.0
            rr = reach[g]
            if rr <= ix < w - rr and rr <= iy < h - rr and rr <= _EXACT_REACH:
                # window wholly inside: row spans, no bounds tests, sums in any order (exact)
                tot, mx, my = _window_moments(img, ix, iy, spans, span_ptr[g], span_ptr[g + 1], bg)
            elif rr <= ix < w - rr and rr <= iy < h - rr:
                for sp in range(span_ptr[g], span_ptr[g + 1]):
                    dy = spans[sp, 0]
                    for dx in range(spans[sp, 1], spans[sp, 2] + 1):
                        wt = max(np.float32(img[iy + dy, ix + dx]) * U8_SCALE - bg, 0.0)   # branch-free
                        tot += wt
                        mx += wt * dx
                        my += wt * dy
            else:
                for k in range(w0, w1):
                    u, v = ix + win_dx[k], iy + win_dy[k]
                    if 0 <= u < w and 0 <= v < h:
                        wt = max(np.float32(img[v, u]) * U8_SCALE - bg, 0.0)   # branch-free: marker edges are unpredictable
                        tot += wt
                        mx += wt * win_dx[k]
                        my += wt * win_dy[k]
            nx, ny = x, y
            if tot > 0.0:
                nx, ny = ix + mx / tot, iy + my / tot
            # a centroid that runs away (neighbour or plateau in the window) keeps the DoH peak
            if math.hypot(nx - x0, ny - y0) <= lims[g]:
                x, y = nx, ny
            else:
                x, y = x0, y0
        xy[i, 0], xy[i, 1] = x, y
        # photometry about the refined centre
        ix, iy = int(np.rint(x)), int(np.rint(y))
        bg = med0
        if ix != ix0 or iy != iy0:
            n_in, bg = _ring_median(img, ix, iy, ring_dx, ring_dy, r0, r1, ring_reach[g], ring, hist)
            if np.isnan(bg):
                bg = 0.0
        n_sat = 0
        for k in range(r0, r1):
            if ring[k] >= sat_thr:
                n_sat += 1
        sat[i] = n_sat / max(n_in, 1)
        for s in range(SECTORS):
            cnt = 0
            acc = 0.0
            for k in range(starts[g, s], starts[g, s + 1]):
                if ring[k] >= 0.0:
                    cnt += 1
                    acc += ring[k]
            sectors[i, s] = (acc / cnt if cnt > 0 else -np.inf) - bg
        _gather(img, ix, iy, core_dx, core_dy, c0, c1, core)
        peak = -np.inf
        n_sat = 0
        for k in range(c0, c1):
            peak = max(peak, core[k])
            if core[k] >= sat_thr:
                n_sat += 1
        contrast[i] = peak - bg
        core_sat[i] = n_sat / (c1 - c0)


@numba.njit(cache=True, nogil=True)
def _unique_inverse(a):
    """``np.unique(a, return_inverse=True)`` for a 1-D float64 array without NaN: the sorted distinct
    values and, per sample, the index of its value among them."""
    s = np.sort(a)
    n_u = 0
    for i in range(len(s)):
        if i == 0 or s[i] != s[i - 1]:
            s[n_u] = s[i]
            n_u += 1
    uniq = s[:n_u].copy()
    inv = np.searchsorted(uniq, a).astype(np.intp)
    return uniq, inv


def refine_and_measure(grey: np.ndarray, cand: np.ndarray, params: DetectionParams) -> Measurements:
    """Sub-pixel centroids and local photometry per candidate.

    Per candidate the background is the median of a ring about it (robust to the candidate being a
    pixel or two off, as on the coarse pyramid levels); the centroid of the window above that
    background is iterated ``centroid_iterations`` times (a centroid that moves more than
    ``RUNAWAY_FRACTION r + RUNAWAY_PX`` px from the DoH peak keeps the peak); ring, sectors and core are then laid out
    about the rounded refined centre (<= 0.71 px off) for the photometry. Geometry per measuring
    scale (``cand[:, MEASURE_SIGMA]``), so candidates of one scale share the pixel offsets.

    Returns :class:`Measurements`: ``xy`` (N, 2) refined centres, ``contrast`` (N,) peak minus ring
    median, ``sectors`` (N, SECTORS) mean of each angular ring sector minus the ring median (-inf for a sector wholly outside
    the image; sector ``k`` spans angles ``-pi + k pi/4 .. -pi + (k+1) pi/4`` of ``atan2(dv, du)``),
    ``sat`` (N,) saturated fraction of the ring,
    ``core_sat`` (N,) saturated fraction of the blob core.
    The ring spans ``RING_IN r + RING_GAP_PX .. RING_IN r + RING_WIDTH_PX`` px (r = sqrt(2) sigma with the
    measuring scale).
    """
    # grey level k is stored as float32(k / 255): compare half a level below to be exact
    sat_thr = float(np.float32((params.saturation_level - 0.5) / 255.0))
    n = len(cand)
    scales, gid = _unique_inverse(cand[:, MEASURE_SIGMA])
    out = (np.empty((n, 2)), np.empty(n), np.empty((n, SECTORS)), np.empty(n), np.empty(n))
    _measure_kernel(grey, cand, gid, int(params.centroid_iterations), sat_thr,
                    *_offset_tables(tuple(scales.tolist()), params), *out)
    return Measurements(*out)


def _offset_tables(scales: tuple[float, ...], params: DetectionParams):
    """The :func:`group_offsets` of every measuring scale, concatenated for :func:`_measure_kernel`:
    run-away limits (G,), ring dx, dy, pointers (G + 1,), sector starts (G, 9) as absolute indices,
    window dx, dy, pointers, window row spans (S, 3) with pointers and each window's reach (G,),
    core dx, dy, pointers, and each ring's reach (G,). Cached per set of scales (a stream of frames
    sees the same few)."""
    key = (scales, params.centroid_radius_factor)
    hit = _TABLES.get(key)
    if hit is not None:
        return hit
    radii = [float(RADIUS_PER_SIGMA * sc) for sc in scales]
    groups = [group_offsets(r, params) for r in radii]
    ptr = lambda k: np.concatenate([[0], np.cumsum([len(gr[k]) for gr in groups])]).astype(np.intp)  # noqa: E731
    cat = lambda k: np.concatenate([gr[k] for gr in groups]).astype(np.intp)                          # noqa: E731
    ring_ptr = ptr(0)
    starts = np.stack([gr[2] + ring_ptr[j] for j, gr in enumerate(groups)]).astype(np.intp)
    # the window as row spans (dy, first dx, last dx), in the offsets' own row-major order
    spans = []
    for gr in groups:
        dys = np.unique(gr[4])
        spans.append(np.array([[dy, gr[3][gr[4] == dy].min(), gr[3][gr[4] == dy].max()] for dy in dys], np.intp))
    span_ptr = np.concatenate([[0], np.cumsum([len(sp) for sp in spans])]).astype(np.intp)
    reach = np.array([int(max(np.abs(gr[3]).max(), np.abs(gr[4]).max())) for gr in groups], np.intp)
    ring_reach = np.array([int(max(np.abs(gr[0]).max(initial=0), np.abs(gr[1]).max(initial=0))) for gr in groups],
                          np.intp)
    hit = (np.array([RUNAWAY_FRACTION * r + RUNAWAY_PX for r in radii]), cat(0), cat(1), ring_ptr, starts,
           cat(3), cat(4), ptr(3), np.concatenate(spans), span_ptr, reach, cat(5), cat(6), ptr(5), ring_reach)
    if len(_TABLES) > CACHE_ENTRIES:
        _TABLES.clear()
    _TABLES[key] = hit
    return hit


_TABLES: dict[tuple, tuple] = {}
