"""DTRC step 3 for defects: design slots predicted from local affine fits to coded neighbours, to
rotate an irregular ring onto the design, verify codes and code free slots."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.nearest import nearest, nearest_members


#: are 1 pitch apart, so 0.4 leaves a 0.2-pitch margin to the half-way point).
PREDICT_GATE = 0.4
#: Coded design neighbours a slot's local affine prediction is fitted to (a hexagonal slot's first
#: shell holds 6, a square slot's first shell with its diagonals 8).
PREDICT_NEIGHBOURS = 8
#: Ridge (mm^2) added to the diagonal of the fits' normal matrix: keeps collinear neighbours
#: solvable, far below any real neighbourhood's scatter (~ separation^2 per point).
PREDICT_RIDGE = 1e-9


# ----- prediction: nearest coded design points and local affine fits -----------------------
# The defect paths (irregular rings, verification, growth) predict design slots from local affine fits
# to the k nearest coded DESIGN points. Design lattices tie exactly (a quarter of the hexagon slots have
# two design points at the same float distance around the 8th neighbour), and which tied point enters
# the fit changes the prediction far beyond rounding. The neighbours are therefore defined exactly:
# ascending distance, ties to the lower design index (:mod:`pipeline.vision.nearest`), taken from the
# design's neighbour table (:func:`design_order`, once per design) restricted to the coded slots; the
# points are summed into the fit in that order. Coded ids are unique (one blob per slot).
# The 3x3 least squares are solved directly (Gaussian elimination, partial pivoting); they differ from
# LAPACK by rounding only (~1e-15 relative), far below the gates' margins.

@numba.njit(cache=True, nogil=True)
def _affine_fit(query_ids, ref_ids, ref_px, xy_d, order, k, exclude_self):
    """Predict image positions of design slots from local affine fits to coded neighbours.

    Least squares (``+ PREDICT_RIDGE I`` on the normal matrix) of px ~ [x, y, 1] A over the ``k``
    design slots of ``ref_ids`` (coded, unique; image positions ``ref_px``) nearest to each query slot
    ``query_ids[q]``, in (distance, design index) order (without the query slot itself when
    ``exclude_self``); ``order``: :func:`pipeline.vision.nearest.design_order` of the design points
    ``xy_d``. Returns (predicted px (Q, 2), local pixels per design mm (Q,) = sqrt |det A_2x2|).
    """
    n_slots = len(xy_d)
    member = np.zeros(n_slots, np.bool_)
    row_of = np.full(n_slots, -1, np.int64)
    for r in range(len(ref_ids)):
        member[ref_ids[r]] = True
        row_of[ref_ids[r]] = r
    nb = np.empty(max(k, 1), np.int64)
    pred = np.empty((len(query_ids), 2))
    scale = np.empty(len(query_ids))
    M = np.empty((3, 3))
    B = np.empty((3, 2))
    for q in range(len(query_ids)):
        s = query_ids[q]
        m = nearest_members(xy_d, order, member, s, k, exclude_self, nb)
        M[:] = 0.0
        B[:] = 0.0
        for t in range(m):
            j = nb[t]
            r = row_of[j]
            X = (xy_d[j, 0], xy_d[j, 1], 1.0)
            for i in range(3):
                for jj in range(3):
                    M[i, jj] += X[i] * X[jj]
                B[i, 0] += X[i] * ref_px[r, 0]
                B[i, 1] += X[i] * ref_px[r, 1]
        for i in range(3):
            M[i, i] += PREDICT_RIDGE  # as the numpy definition
        # Gaussian elimination with partial pivoting (M is positive definite)
        for c in range(3):
            p = c
            for r in range(c + 1, 3):
                if abs(M[r, c]) > abs(M[p, c]):
                    p = r
            if p != c:
                for j in range(3):
                    M[c, j], M[p, j] = M[p, j], M[c, j]
                for j in range(2):
                    B[c, j], B[p, j] = B[p, j], B[c, j]
            for r in range(c + 1, 3):
                f = M[r, c] / M[c, c]
                for j in range(c, 3):
                    M[r, j] -= f * M[c, j]
                for j in range(2):
                    B[r, j] -= f * B[c, j]
        for c in range(2, -1, -1):
            for j in range(2):
                v = B[c, j]
                for i in range(c + 1, 3):
                    v -= M[c, i] * B[i, j]
                B[c, j] = v / M[c, c]
        qx, qy = xy_d[s, 0], xy_d[s, 1]
        pred[q, 0] = qx * B[0, 0] + qy * B[1, 0] + B[2, 0]
        pred[q, 1] = qx * B[0, 1] + qy * B[1, 1] + B[2, 1]
        scale[q] = math.sqrt(abs(B[0, 0] * B[1, 1] - B[0, 1] * B[1, 0]))
    return pred, scale


@numba.njit(cache=True, nogil=True)
def _verify_and_grow(pts, ids, active, xy_d, order, pitch_mm, max_rounds):
    """Uncode ids that disagree with their coded neighbours, then code free slots by prediction.

    Verification: each coded blob must lie within ``PREDICT_GATE`` local pitches of its slot predicted
    from its :data:`PREDICT_NEIGHBOURS` nearest coded design neighbours. Growth (up to ``max_rounds``
    rounds): every free slot is predicted from the coded ones and takes the nearest candidate blob
    (active, uncoded) when it is within the gate and the slot is that blob's nearest prediction
    (mutual nearest). Modifies ``ids`` in place; returns the number of ids removed by verification.
    """
    gate = PREDICT_GATE * pitch_mm
    removed = 0
    coded = np.flatnonzero(ids >= 0)
    if len(coded) >= 4:
        pred, sc = _affine_fit(ids[coded], ids[coded], pts[coded], xy_d, order, PREDICT_NEIGHBOURS, True)
        for i in range(len(coded)):
            dx, dy = pred[i, 0] - pts[coded[i], 0], pred[i, 1] - pts[coded[i], 1]
            if math.sqrt(dx * dx + dy * dy) > gate * sc[i]:
                ids[coded[i]] = -1
                removed += 1
    one = np.empty(1, np.int64)
    one_d2 = np.empty(1)
    for _ in range(max_rounds):
        coded = np.flatnonzero(ids >= 0)
        used = np.zeros(len(xy_d), np.bool_)
        for i in coded:
            used[ids[i]] = True
        free = np.flatnonzero(~used)
        cand = np.flatnonzero(active & (ids < 0))
        if len(coded) < 4 or len(free) == 0 or len(cand) == 0:
            break
        pred, sc = _affine_fit(free, ids[coded], pts[coded], xy_d, order, PREDICT_NEIGHBOURS, False)
        cand_px = pts[cand]
        take = np.full(len(free), -1, np.int64)
        for q in range(len(free)):
            nearest(cand_px, pred[q, 0], pred[q, 1], 1, one, one_d2)
            j = one[0]
            if not math.sqrt(one_d2[0]) <= gate * sc[q]:
                continue
            nearest(pred, cand_px[j, 0], cand_px[j, 1], 1, one, one_d2)
            if one[0] == q:
                take[q] = cand[j]
        if not np.any(take >= 0):
            break
        for q in range(len(free)):
            if take[q] >= 0:
                ids[take[q]] = free[q]
    return removed


#: A ring of the design's size but irregular spacing (a deformed skin) is rotated onto the design by
#: prediction from the rings inside it: the best cyclic shift must fit with a mean distance below
#: this many local pitches, and the runner-up shift must fit at least SHIFT_MARGIN x worse.
SHIFT_FIT = 0.45
SHIFT_MARGIN = 2.0


@numba.njit(cache=True, nogil=True)
def _shift_by_prediction(members, d_ids, pts, ids, xy_d, order, pitch_mm):
    """Cyclic shift coding a complete ring (``members`` sorted CCW) whose gaps are irregular.

    The ring's cyclic order is topological and survives deformation; only its start is unknown. Each
    design slot of the ring is predicted from a local affine fit to the coded markers (the rings
    inside, already coded), and the shift whose found points lie nearest the predictions (mean
    distance in local pitches) wins when it is unambiguous (:data:`SHIFT_FIT`, :data:`SHIFT_MARGIN`).
    Returns the shift (found point ``(i + shift) % n`` is slot ``i``), -1 when there is none.
    """
    coded = np.flatnonzero(ids >= 0)
    if len(coded) < 4:
        return -1
    pred, sc = _affine_fit(d_ids, ids[coded], pts[coded], xy_d, order, PREDICT_NEIGHBOURS, False)
    n = len(d_ids)
    cost = np.empty(n)
    for s in range(n):
        acc = 0.0
        for i in range(n):
            m = members[(i + s) % n]
            dx, dy = pts[m, 0] - pred[i, 0], pts[m, 1] - pred[i, 1]
            acc += math.sqrt(dx * dx + dy * dy) / (pitch_mm * max(sc[i], 1e-9))
        cost[s] = acc / n
    best = 0
    for s in range(1, n):
        if cost[s] < cost[best]:
            best = s
    runner_up = np.inf
    for s in range(n):
        if s != best and cost[s] < runner_up:
            runner_up = cost[s]
    if cost[best] > SHIFT_FIT or (n > 1 and runner_up < SHIFT_MARGIN * cost[best]):
        return -1
    return best
