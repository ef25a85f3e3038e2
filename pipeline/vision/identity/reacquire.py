"""Re-acquisition: a marker lost before the previous frame is taken back by the frame-to-frame map.

A marker the detector merged with a crowded neighbour, or whose neighbourhood the frame-to-frame map
(:mod:`pipeline.vision.identity.temporal`) could not fit, or whose blob glare or a spurious blob beside it
took, for a frame or two, has no certified position in the previous frame to be followed from.
:func:`reacquire` predicts it from its last certified position in an earlier frame, moved by its
neighbours' motion from that frame to now, under the frame-to-frame tests unchanged, and gives it only a
blob that carries no id; its uncertified design neighbours are tested as
rivals, so a blob of two merged pins goes to neither. :func:`carry_lost` keeps, frame by frame, a place for
every marker not identified, so that it is predicted from one frame's motion (also a marker whose blob was
missing from the sequence's first frame, which has no certified position at all).
"""

from __future__ import annotations

import numpy as np

from pipeline.vision.identity.temporal import (F2F_FIT_RESIDUAL, F2F_GATE, F2F_GATE_ALONE, F2F_MARGIN, F2F_MIN_FIT,
                                               F2F_RATIO, F2F_SPREAD, _assign_mutual, _fit, _neighbourhoods,
                                               _nn_dist, _predict, expected_positions)
from pipeline.vision.nearest import knn
from pipeline.vision.identity.apart import stand_apart

__all__ = ["REACQUIRE_FRAMES", "reacquire", "carry_lost"]


#: Earlier frames a marker lost from the previous frame may be re-acquired from: its last certified
#: position there and its neighbours' motion since (a lost marker is one the detector merged with a
#: crowded neighbour, or whose neighbourhood the frame-to-frame map could not fit, for a frame or two).
REACQUIRE_FRAMES = 3


def _fit_frame(P: np.ndarray, corr: np.ndarray, pts: np.ndarray, expected: np.ndarray | None = None):
    """The frame-to-frame fit's neighbour structure for markers at ``P`` (one earlier frame), and each
    one's current prediction from the neighbours that have a current blob ``corr`` (see :func:`_predict`).
    ``expected`` (M, 2): where each marker is expected at its last velocity (NaN where unknown): where the
    marker's and its neighbours' velocities are known, the fitted motion is their departure from it
    (the frame-to-frame map's fit of the motion's change), else the increment."""
    nb, near, shell, s_prev = _neighbourhoods(P)
    pred, ok, jac, _ = _fit(P, pts, nb, near, shell, corr, s_prev, P)
    if expected is not None:
        moving = np.isfinite(expected).all(axis=1)
        if moving.sum() > F2F_MIN_FIT:
            E = np.ascontiguousarray(np.where(moving[:, None], expected, P))
            pv, okv, jv, _ = _fit(P, pts, nb, near, shell, np.where(moving, corr, -1), s_prev, E)
            okv &= moving
            pred[okv], jac[okv] = pv[okv], jv[okv]
            ok = ok | okv
    rough, rough_ok, _, _ = _predict(P, pts, nb, near, corr, s_prev, F2F_MIN_FIT, F2F_SPREAD, np.inf, P)
    return pred, ok, s_prev, np.where(ok[:, None], pred, rough), ok | rough_ok, jac


def reacquire(history, ids: np.ndarray, pts: np.ndarray, design_nbr: np.ndarray | None = None) -> np.ndarray:
    """Ids of markers lost before the previous frame that the frame-to-frame map re-acquires on the
    free blobs of the current frame (blobs without an id in ``ids`` (n,)); -1 elsewhere.

    ``history``: the certified markers (xy_px (M, 2), ids (M,)) of the frames before the previous one,
    most recent first (:data:`REACQUIRE_FRAMES` are used); an entry (xy_px, ids, lost (M,) bool) also
    holds markers not certified there, carried by :func:`carry_lost`, and only those are re-acquired
    from it (one that is not is still tried from its last certified position in an older entry). A
    marker certified in one of them but in none since (nor now) is predicted from its last certified
    position moved by the affine map of its neighbours' motion from that frame to now (neighbours
    certified in both, the marker excluded), under the tests of :func:`frame_to_frame` unchanged: at
    least :data:`F2F_MIN_FIT` neighbours spread in two directions, each fitted to
    :data:`F2F_FIT_RESIDUAL` local spacings (the first shell alone where the whole neighbourhood is
    refused); the nearest blob within :data:`F2F_GATE` (:data:`F2F_GATE_ALONE` when an immediate design
    neighbour is not certified now, so that it may share the blob, unless each such neighbour has a blob
    of its own, another than the marker's, within :data:`~pipeline.vision.identity.apart.F2F_APART` local spacings of its predicted
    place) of the prediction, :data:`F2F_RATIO` times and :data:`F2F_MARGIN` spacings nearer than the
    second-nearest blob (identified or not); and mutual: no other re-acquired prediction and no
    identified blob nearly as near to that blob. The blob must be free: a blob that carries another
    marker's id is never taken, even when it is the nearest."""
    n = len(pts)
    out = np.full(n, -1, np.int64)
    have = ids >= 0
    if n < F2F_MIN_FIT + 1 or not history or have.sum() < F2F_MIN_FIT:
        return out
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    s_cur = _nn_dist(pts)
    top = int(max(ids.max(), max((int(h[1].max(initial=-1)) for h in history), default=-1))) + 1
    blob_of = np.full(top, -1, np.int64)
    blob_of[ids[have]] = np.flatnonzero(have)
    seen = np.zeros(top, bool)                # certified in a more recent frame: not lost from this one
    seen[ids[have]] = True
    for entry in history[:REACQUIRE_FRAMES]:
        xy, hid = entry[0], np.asarray(entry[1], np.int64)
        # a carried estimate that re-acquires nothing leaves the marker to its last certified position
        sure = np.ones(len(hid), bool) if len(entry) < 3 else ~np.asarray(entry[2], bool)
        if len(hid) < F2F_MIN_FIT + 1:
            seen[hid[sure]] = True
            continue
        P = np.ascontiguousarray(xy, dtype=np.float64)
        lost = ~seen[hid] & ~sure if len(entry) > 2 else ~seen[hid]
        while lost.any():
            cur = np.where(out >= 0, out, ids)
            blob_of[:] = -1
            blob_of[cur[cur >= 0]] = np.flatnonzero(cur >= 0)
            corr = blob_of[hid]
            pred, ok, s_prev, rough, rough_ok, jac = _fit_frame(P, corr, pts)
            ok &= lost
            rivals = [rough[lost & rough_ok & ~ok]]
            if not ok.any():
                break
            gate = np.full(len(hid), F2F_GATE)
            if design_nbr is not None and len(design_nbr):
                known = np.zeros(max(len(design_nbr), top) + 1, bool)
                known[cur[cur >= 0]] = True
                known[-1] = True                      # padding
                gate[~known[design_nbr[hid]].all(axis=1)] = F2F_GATE_ALONE
                # a design neighbour not certified now may have merged with the marker into the blob:
                # it is tested as a rival, at its own rough prediction or else where the marker's map
                # takes its last position; one not certified in this frame either has no position
                # to test, and the marker is not re-acquired
                row = np.full(len(known), -1, np.int64)
                row[hid] = np.arange(len(hid))
                for i in np.flatnonzero(ok):
                    places = []
                    for n in design_nbr[hid[i]]:
                        if n < 0 or known[n]:
                            continue
                        r = row[n]
                        if r < 0:
                            ok[i] = False
                            break
                        q = rough[r] if rough_ok[r] else pred[i] + jac[i].reshape(2, 2) @ (P[r] - P[i])
                        if not rough_ok[r]:
                            rivals.append(q[None])
                        places.append(q)
                    # neighbours with blobs of their own, apart from the marker's, cannot share it
                    if ok[i] and stand_apart(pts, np.reshape(places, (-1, 2)), pred[i], s_prev[i]):
                        gate[i] = F2F_GATE
            rivals = np.vstack(rivals)
            got = _accept_free(pred, ok, pts, s_cur, s_prev, gate, cur >= 0, rivals)
            hit = got >= 0
            if not hit.any():
                break
            out[got[hit]] = hid[hit]
            lost &= ~hit
        seen[hid[sure]] = True
    return out


def _accept_free(pred, ok, pts, s_cur, s_prev, gate, taken, rivals):
    """:func:`_accept` for re-acquisition: the nearest blob must also be free (not ``taken``), and the
    identified blobs count as predictions of their markers in the mutual test, as do ``rivals``: the
    predictions of the other lost markers whose fit did not pass the residual test (a lost neighbour
    merged into the same blob by the detector is as near to it as the marker; its prediction is rough
    but says so)."""
    out = np.full(len(pred), -1, np.int64)
    idx = np.flatnonzero(ok)
    d, j = knn(pts, pred[idx], 2)
    others = np.vstack([pred[idx], pts[taken], rivals])
    s_pred = np.minimum(s_prev[idx], _nn_dist(others)[:len(idx)])
    s = np.minimum(s_cur[j[:, 0]], s_pred)
    good = (~taken[j[:, 0]] & (d[:, 0] <= gate[idx] * s) & (d[:, 1] >= F2F_RATIO * d[:, 0])
            & (d[:, 1] - d[:, 0] >= F2F_MARGIN * s))
    idx, j1, d1, s = idx[good], j[good, 0], d[good, 0], s[good]
    if len(idx) == 0:
        return out
    # mutual against the re-acquired predictions, the identified blobs and the rivals
    return _assign_mutual(out, idx, j1, d1, s, np.vstack([pred[idx], pts[taken], rivals]), pts)


def carry_lost(prev: tuple, cur: tuple, design_xy: np.ndarray, design_nbr: np.ndarray,
               before: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where the markers not certified in the current frame are, estimated, so that the next frame may
    re-acquire them from one frame's motion rather than from their last certified position several frames
    back (or never, for a marker whose blob was missing from the sequence's first frame): (xy_px (L, 2),
    ids (L,)).

    ``prev`` (xy_px, ids): the previous frame's certified markers and its carried estimates; ``cur``
    (xy_px, ids): this frame's certified markers. A marker with a previous position is moved by the affine
    map of its neighbours' motion, under the frame-to-frame fit's tests (neighbours certified in both
    frames; at least :data:`F2F_MIN_FIT`, spread in two directions, each fitted to :data:`F2F_FIT_RESIDUAL`
    local spacings); with ``before`` (xy_px, ids), the markers certified one frame earlier, by their
    departure from its and their last velocity where those are known (:func:`_fit_frame`: where
    pins crowd into a sine's crest the increment is not affine over two spacings, its change is; on
    square121 under the pi/5 sine, 3 % + 3 % defects, the carried places' median error at 5 mm fell from
    0.18 to 0.07 local spacings); one without is placed by the affine map from the design to this frame fitted to
    its certified immediate design neighbours (at least :data:`F2F_MIN_FIT`, spread in two directions,
    each within :data:`F2F_FIT_RESIDUAL` median spacings of the fit). An estimate is never an id: re-acquisition
    from it passes every frame-to-frame test on a free blob (:func:`reacquire`)."""
    cur_xy, cur_ids = np.asarray(cur[0], np.float64).reshape(-1, 2), np.asarray(cur[1], np.int64)
    prev_xy, prev_ids = np.asarray(prev[0], np.float64).reshape(-1, 2), np.asarray(prev[1], np.int64)
    n_slots = len(design_xy)
    at = np.full((n_slots, 2), np.nan)
    if len(cur_ids) < F2F_MIN_FIT + 1:
        return np.empty((0, 2)), np.empty(0, np.int64)
    certified = np.zeros(n_slots, bool)
    certified[cur_ids] = True
    if certified.all():                        # nothing lost: the usual frame, no fit
        return np.empty((0, 2)), np.empty(0, np.int64)
    row = np.full(n_slots, -1, np.int64)
    row[cur_ids] = np.arange(len(cur_ids))
    corr = row[prev_ids]
    if len(prev_ids) > F2F_MIN_FIT and (corr < 0).any():   # the fits only where a previous marker is lost now
        E = None if before is None or len(before[1]) == 0 else expected_positions(prev_xy, prev_ids, *before)
        pred, ok, _, _, _, _ = _fit_frame(np.ascontiguousarray(prev_xy), corr, np.ascontiguousarray(cur_xy), E)
        moved = ok & (corr < 0)
        at[prev_ids[moved]] = pred[moved]
    pos = np.full((n_slots, 2), np.nan)
    pos[cur_ids] = cur_xy
    s_cur = _nn_dist(cur_xy)
    spacing = float(np.median(s_cur))
    for i in np.flatnonzero(~certified & ~np.isfinite(at[:, 0])):
        nb = design_nbr[i][design_nbr[i] >= 0]
        nb = nb[certified[nb]]
        if len(nb) < F2F_MIN_FIT:          # three fix an affine map; the fourth tests it
            continue
        D = np.c_[design_xy[nb] - design_xy[i], np.ones(len(nb))]
        if np.linalg.matrix_rank(D[:, :2], tol=1e-6 * float(np.abs(D[:, :2]).max())) < 2:
            continue
        M = np.linalg.lstsq(D, pos[nb], rcond=None)[0]
        if np.hypot(*(D @ M - pos[nb]).T).max() <= F2F_FIT_RESIDUAL * spacing:
            at[i] = M[2]                       # the design offset of the slot itself is zero
    lost = np.flatnonzero(np.isfinite(at[:, 0]) & ~certified)
    return at[lost], lost
