"""Local affine fits design -> image: the sums, the leave-one-out downdate and the tables of their
design half (:func:`_loo_design`), shared by every consistency test of the certainty rule.

The frame-to-frame map (:func:`pipeline.vision.identity.temporal._predict`) fits a local affine map too,
but not with these sums, on purpose: here one neighbourhood's raw sums (:func:`_fit_sums`, one pass, about
an origin) serve every leave-one-out fit by subtracting one point, and their design half is tabulated per
design, so only raw sums can be downdated and shared; the collinearity test is on the total scatter in
design separations (:data:`COLLINEAR_SCATTER`). The temporal fit maps a marker's previous-frame
neighbours to their motion, once per marker with the marker itself never among them, so nothing is
downdated: it takes the means first and then the centred moments (two passes, no cancellation), and
tests the spread as a per-point standard deviation in the previous frame's local spacing. The two give
the same map in exact arithmetic but round differently, and their collinearity tests differ, so one
routine for both would move borderline accept/reject decisions."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.identity.constants import LOCAL_ONLY, MAX_STRETCH


@numba.njit(cache=True, nogil=True)
def _fit_sums(xy, pts, slots, blobs, m, ox, oy, ou, ov, acc):
    """Sums over points ``0..m-1`` of (slots, blobs) for :func:`_fit`, coordinates taken relative to
    (ox, oy) in the design and (ou, ov) in the image (keeps the downdated sums well conditioned),
    written into ``acc`` (12,) (a work array: the tests run per blob, so no allocation here)."""
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = 0.0
    for i in range(m):
        x = xy[slots[i], 0] - ox
        y = xy[slots[i], 1] - oy
        u = pts[blobs[i], 0] - ou
        v = pts[blobs[i], 1] - ov
        a0 += 1.0
        a1 += x
        a2 += y
        a3 += u
        a4 += v
        a5 += x * x
        a6 += x * y
        a7 += y * y
        a8 += u * x
        a9 += u * y
        a10 += v * x
        a11 += v * y
    acc[0], acc[1], acc[2], acc[3], acc[4], acc[5] = a0, a1, a2, a3, a4, a5
    acc[6], acc[7], acc[8], acc[9], acc[10], acc[11] = a6, a7, a8, a9, a10, a11
    return acc


@numba.njit(inline="always")
def _row_length(table, s):
    """Entries of ``table[s]`` before its -1 padding (a neighbour table of :class:`Lattice`)."""
    n = 0
    for k in range(table.shape[1]):
        if table[s, k] < 0:
            break
        n += 1
    return n


@numba.njit(inline="always")
def _gather(s, table, k0, k1, blob_of, slots, blobs, m):
    """Append the identified design neighbours among ``table[s, k0:k1]`` (up to the -1 padding) to
    ``slots``, and their blobs to ``blobs``, from position ``m``; returns the new count."""
    for k in range(k0, k1):
        j = table[s, k]
        if j < 0:
            break
        if blob_of[j] >= 0:
            slots[m] = j
            blobs[m] = blob_of[j]
            m += 1
    return m



#: A fit needs three points (the point count is a float sum of ones, hence the half).
FIT_MIN_POINTS = 2.5
#: Smallest eigenvalue of a fit's design scatter (the sum over its points of the squared offsets from
#: their mean, along the direction of least spread), in squared design separations: below it the
#: points are (nearly) collinear and the map across them is undetermined.
COLLINEAR_SCATTER = 0.1


@numba.njit(inline="always")
def _design_half(c0, c1, c2, c5, c6, c7, pitch):
    """The design half of a least-squares affine map from the design sums of :func:`_fit_sums`
    (count, x, y, xx, xy, yy): (usable, mean x, mean y, inverse scatter 00, 01, 11). Not usable with
    fewer than three points or (nearly) collinear ones (:data:`COLLINEAR_SCATTER`)."""
    cnt = c0
    if cnt < FIT_MIN_POINTS:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    mx, my = c1 / cnt, c2 / cnt
    sxx = c5 - cnt * mx * mx
    sxy = c6 - cnt * mx * my
    syy = c7 - cnt * my * my
    det = sxx * syy - sxy * sxy
    tr = sxx + syy
    lam_min = tr / 2 - math.sqrt(max(tr * tr / 4 - det, 0.0))
    if lam_min < COLLINEAR_SCATTER * pitch * pitch:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    return True, mx, my, syy / det, -sxy / det, sxx / det


@numba.njit(inline="always")
def _image_half(cnt, mx, my, c3, c4, c8, c9, c10, c11, i00, i01, i11):
    """The image half of the map: (mean u, mean v, L00, L01, L10, L11) from the image sums of
    :func:`_fit_sums` (u, v, ux, uy, vx, vy) and the design half of :func:`_design_half`."""
    mu, mv = c3 / cnt, c4 / cnt
    cux = c8 - cnt * mu * mx
    cuy = c9 - cnt * mu * my
    cvx = c10 - cnt * mv * mx
    cvy = c11 - cnt * mv * my
    l00 = cux * i00 + cuy * i01
    l01 = cux * i01 + cuy * i11
    l10 = cvx * i00 + cvy * i01
    l11 = cvx * i01 + cvy * i11
    return mu, mv, l00, l01, l10, l11


@numba.njit(inline="always")
def _smooth(l00, l01, l10, l11, max_stretch):
    """Can a smooth skin map this way: orientation kept (no mirror) and the larger singular value at
    most ``max_stretch`` times the smaller?"""
    dl = l00 * l11 - l01 * l10
    if dl <= 0.0:
        return False
    fro = l00 * l00 + l01 * l01 + l10 * l10 + l11 * l11
    s_max = math.sqrt(max(fro / 2 + math.sqrt(max(fro * fro / 4 - dl * dl, 0.0)), 0.0))
    s_min = dl / s_max
    return not s_max > max_stretch * s_min


@numba.njit(cache=True, nogil=True)
def _fit(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, pitch):
    """:func:`_fit_map` with the stretch limit :data:`MAX_STRETCH`."""
    return _fit_map(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, pitch, MAX_STRETCH)


@numba.njit(cache=True, nogil=True)
def _fit_map(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, pitch, max_stretch):
    """Affine map design -> image from the points summed in ``acc`` (:func:`_fit_sums`) without
    point ``skip`` (-1: none).

    Returns (ok, mean design x, y, mean image u, v, L00, L01, L10, L11), means relative to the
    origins of :func:`_fit_sums`. ``ok`` is 1 for a usable map, 0 when fewer than three points
    remain or they are (nearly) collinear, -1 when the map mirrors or stretches more than
    ``max_stretch`` (no smooth skin does that).
    """
    c0, c1, c2, c3, c4, c5 = acc[0], acc[1], acc[2], acc[3], acc[4], acc[5]
    c6, c7, c8, c9, c10, c11 = acc[6], acc[7], acc[8], acc[9], acc[10], acc[11]
    if skip >= 0:
        x = xy[slots[skip], 0] - ox
        y = xy[slots[skip], 1] - oy
        u = pts[blobs[skip], 0] - ou
        v = pts[blobs[skip], 1] - ov
        c0 -= 1.0
        c1 -= x
        c2 -= y
        c3 -= u
        c4 -= v
        c5 -= x * x
        c6 -= x * y
        c7 -= y * y
        c8 -= u * x
        c9 -= u * y
        c10 -= v * x
        c11 -= v * y
    usable, mx, my, i00, i01, i11 = _design_half(c0, c1, c2, c5, c6, c7, pitch)
    if not usable:
        return 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    mu, mv, l00, l01, l10, l11 = _image_half(c0, mx, my, c3, c4, c8, c9, c10, c11, i00, i01, i11)
    if not _smooth(l00, l01, l10, l11, max_stretch):
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return 1, mx, my, mu, mv, l00, l01, l10, l11


@numba.njit(cache=True, nogil=True)
def _loo_design(xy, nbr, nbr2, pitch):
    """The design half of every leave-one-out fit of :func:`_loo_status` when a slot's whole
    neighbourhood is identified (the common case): ``m`` (N,) the number of points fitted (the slot
    and the neighbours :func:`_loo_status` gathers), and ``tab`` (N, K1 + 1, 9) per slot and left-out
    point q (0 = the slot, then its immediate neighbours): usable (1.0, else 0.0: too few or
    collinear points), the point count, the design means, the inverse of the design scatter (00, 01,
    11) and the left-out point's design offset from the mean. Computed by the very operations of
    :func:`_fit_sums` and :func:`_design_half`, so a fit that takes them is bit for bit the full one."""
    N = len(xy)
    K = nbr2.shape[1]
    K1 = nbr.shape[1]
    m_of = np.zeros(N, np.int64)
    tab = np.zeros((N, K1 + 1, 9))
    slots = np.empty(K + 1, np.int64)
    for s in range(N):
        n_design = _row_length(nbr, s)
        slots[0] = s
        m = 1
        for k in range(K):
            j = nbr2[s, k]
            if j < 0 or (k >= n_design and n_design >= LOCAL_ONLY):
                break
            slots[m] = j
            m += 1
        m_of[s] = m
        ox, oy = xy[s, 0], xy[s, 1]
        a0 = a1 = a2 = a5 = a6 = a7 = 0.0
        for i in range(m):
            x = xy[slots[i], 0] - ox
            y = xy[slots[i], 1] - oy
            a0 += 1.0
            a1 += x
            a2 += y
            a5 += x * x
            a6 += x * y
            a7 += y * y
        for q in range(n_design + 1):
            x = xy[slots[q], 0] - ox
            y = xy[slots[q], 1] - oy
            c0 = a0 - 1.0
            c1 = a1 - x
            c2 = a2 - y
            c5 = a5 - x * x
            c6 = a6 - x * y
            c7 = a7 - y * y
            tab[s, q, 1] = c0
            usable, mx, my, i00, i01, i11 = _design_half(c0, c1, c2, c5, c6, c7, pitch)
            if not usable:
                continue
            tab[s, q, 0] = 1.0
            tab[s, q, 2], tab[s, q, 3] = mx, my
            tab[s, q, 4], tab[s, q, 5], tab[s, q, 6] = i00, i01, i11
            tab[s, q, 7] = xy[slots[q], 0] - ox - mx
            tab[s, q, 8] = xy[slots[q], 1] - oy - my
    return m_of, tab


@numba.njit(cache=True, nogil=True)
def _fit_tab(xy, pts, slots, blobs, acc, skip, ox, oy, ou, ov, row):
    """:func:`_fit` (point ``skip`` left out) with its design half taken from a row of the table of
    :func:`_loo_design`; the image half is :func:`_fit_map`'s (:func:`_image_half`)."""
    if row[0] == 0.0:
        return 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    x = xy[slots[skip], 0] - ox
    y = xy[slots[skip], 1] - oy
    u = pts[blobs[skip], 0] - ou
    v = pts[blobs[skip], 1] - ov
    cnt, mx, my = row[1], row[2], row[3]
    mu, mv, l00, l01, l10, l11 = _image_half(cnt, mx, my, acc[3] - u, acc[4] - v, acc[8] - u * x, acc[9] - u * y,
                                             acc[10] - v * x, acc[11] - v * y, row[4], row[5], row[6])
    if not _smooth(l00, l01, l10, l11, MAX_STRETCH):
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return 1, mx, my, mu, mv, l00, l01, l10, l11
