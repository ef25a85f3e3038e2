"""Frame-to-frame certification: a marker certified in the previous frame keeps its id when the
frame-to-frame map alone says which current blob it became.

The design-to-image map of a strongly pressed skin is not locally affine where pins crowd (the crests
of a narrow sine), so the certainty rule withdraws correct ids there. The increment between two frames
of a sequence is small and locally smooth even then: each marker's new position is predicted from its
previous position moved by a local affine fit of its previous-frame neighbours' motion (previous ->
current positions), and the marker takes the one blob within a tight gate of that prediction. The
fit never uses the marker itself (leave-one-out), so a marker's own correspondence is always tested
against its neighbours' motion, not assumed.

Procedure (:func:`frame_to_frame`): the correspondences start from mutual nearest neighbours
(a previous marker's expected position - its previous position moved on at the velocity of the last
frame, where known - and a current blob) within :data:`F2F_BOOTSTRAP` local spacings that pass the
ratio test both ways; then every previous marker is predicted from its :data:`F2F_NEIGHBOURS`
nearest previous markers that currently have a correspondence, and the correspondences are replaced
by those that pass the tests below; repeated until nothing changes. Where the marker and its
neighbours were also certified in the frame before (their last velocity is known), the fitted
motion is their departure from that velocity, added to where the marker's own velocity puts it: as
pins crowd into a crest, the increment grows frame by frame and is not affine over two spacings,
while its change from one frame to the next still is (on the twin's narrow-sine presses, the fit's
residual test then passes where the increment's refused); elsewhere the increment itself is fitted.
A marker's correspondence is accepted only when

* at least :data:`F2F_MIN_FIT` of its neighbours have one, spread in two directions, and the affine
  map fits them all to within :data:`F2F_FIT_RESIDUAL` local spacings (one neighbour followed to the
  wrong blob is a whole spacing off, so the fit refuses to predict rather than mislead); where the
  whole neighbourhood is refused, its first shell (:data:`F2F_SHELL`) is fitted alone under the same
  tests (a press bends the map over two spacings where one spacing is still affine), and where both
  are refused, a marker the start found is fitted from its nearest followed markers in the image
  (:data:`F2F_FOLLOWED_REACH`) or, where too few lie within that reach, in the design
  (:data:`F2F_DESIGN_REACH`);
* the nearest blob lies within :data:`F2F_GATE` local spacings of the prediction (:data:`F2F_GATE_ALONE`
  next to a marker that was not followed), and the second-nearest blob is at least :data:`F2F_RATIO`
  times and :data:`F2F_MARGIN` local spacings farther;
* it is mutual: no other marker's prediction is nearly as near to that blob (same ratio and margin).

A blob that moved more than the gate from where its neighbours' motion puts it loses its id; a
missing blob leaves its marker unmatched; a spurious blob next to a marker makes it ambiguous.

A marker lost before the previous frame (its blob merged with a crowded neighbour's for a frame, or
its neighbourhood not fitted) is re-acquired by :func:`reacquire` under the same tests, from its
last certified position and its neighbours' motion since then.
"""

from __future__ import annotations

import numba
import numpy as np

from pipeline.vision.identity.apart import lost_neighbours_apart
from pipeline.vision.identity.motion_fit import _predict
from pipeline.vision.nearest import knn, nearest_other_distances

#: Gate about a marker's predicted position, as a fraction of the local spacing (the smallest of the
#: nearest blob's nearest-neighbour distance now, the marker's and its neighbours' (median) in the
#: previous frame, and the distance between the predictions: where pins crowd, the crowded distance).
#: The prediction's error is the detector's noise plus the non-affine part of one frame's increment
#: over two spacings: measured on the twin's narrow-sine presses in 0.5 and 1 mm steps, median 0.03,
#: 99 % below 0.15 local spacings; a neighbour is a whole (local) spacing away.
F2F_GATE = 0.2
#: A marker one of whose immediate design neighbours was not followed into the previous frame (lost
#: where the pins crowded until the detector no longer separated them) may share its blob with that
#: neighbour, whose centre lies between the two: its gate is this tighter one (the detector's noise
#: and a press's increment over two spacings leave ~0.03 spacings).
F2F_GATE_ALONE = 0.1
#: The correspondences start from markers that moved less than this fraction of the local spacing
#: (nearest blob to the previous position). It is what the certification rests on: a frame that
#: moved by more than 1 - F2F_BOOTSTRAP spacings between frames would be followed to the neighbours'
#: blobs, or a marker's motion that changed by that much from one frame to the next. A press at a
#: steady rate changes its increment by a few hundredths of a spacing a frame.
F2F_BOOTSTRAP = 0.15
#: The second-nearest blob (and the second-nearest prediction to the blob) must be at least this many
#: times farther than the nearest ...
F2F_RATIO = 2.0
#: ... and this many local spacings farther.
F2F_MARGIN = 0.15
#: Previous-frame markers (nearest first) a marker's increment is fitted from (two shells of a hexagonal
#: lattice: a marker beside a straight front of followed markers has four of them) ...
F2F_NEIGHBOURS = 12
#: ... within this many previous local spacings of it ...
F2F_RADIUS = 2.5
#: ... of which at least this many must have a correspondence (an affine map needs three; the fourth
#: makes one wrong neighbour visible in the residual).
F2F_MIN_FIT = 4
#: Largest residual of a neighbour in the fit, in local spacings.
F2F_FIT_RESIDUAL = 0.15
#: The neighbours' previous positions must spread in two directions: the smaller principal standard
#: deviation at least this fraction of the local spacing (collinear neighbours fix no affine map).
F2F_SPREAD = 0.25
#: Where the fit over all of them is refused, the marker is fitted from its first shell alone: its
#: nearest this many neighbours (six on a hexagonal lattice) that are within reach. A press bends the
#: map over two spacings where one spacing is still affine (a far flank seen obliquely, a crest's
#: pins crowding faster than their second shell): there the second shell's residual fails the whole
#: fit although the first shell's motion is one affine map. The tests are the fit's own (at least
#: :data:`F2F_MIN_FIT` neighbours spread in two directions, each to :data:`F2F_FIT_RESIDUAL`), and a
#: neighbour followed to the wrong blob is still a whole spacing off: in a ring of six about the
#: marker, half of that stays in its residual, and with four neighbours a quarter (both over the limit).
F2F_SHELL = 6
#: The first shell is within reach wherever it lies within this many of the frame's median spacings,
#: even beyond :data:`F2F_RADIUS` local spacings: where pins crowd in one direction only (along a
#: crest), the local spacing is the crowded one and a fraction of the distance to the neighbours
#: across the crest, which would leave the marker too few neighbours to be fitted at all. A hexagonal
#: lattice's first shell lies at one spacing, its second at 1.7.
F2F_SHELL_REACH = 1.5
#: Where both fits are refused for want of neighbours with a correspondence (crowded pins merged into
#: one blob leave holes in the first shell; where the pins crowd in one direction only, the local
#: spacing is the crowded one and the radius above shrinks with it), a marker whose start found its
#: blob is fitted from its nearest neighbours that have one, within this many median spacings ...
F2F_FOLLOWED_REACH = 3.0
#: ... at least this many of them (one more than :data:`F2F_MIN_FIT`: a wider neighbourhood bends more,
#: and the residual test, still in the marker's own local spacings, must have a neighbour to spare).
#: Measured on the twin's narrow sine (pi/5, hexagon217_sep180, 4 -> 5 mm with friction): 10 pins merged
#: into their neighbours' blobs and the fits refused around them ate 20 followed markers away, round
#: by round; with this fit all 207 markers that kept a blob of their own were followed, none wrong.
F2F_FOLLOWED_MIN_FIT = 5
#: Where every fit above is refused for want of neighbours with a correspondence within reach in the
#: image (a view that stretches the skin in one direction: square121 under the pi/5 sine at 5 mm puts a
#: crest marker 26-34 px from three neighbours and 67 px or more from all others, beyond both image
#: reaches), a marker whose start found its blob is fitted from its nearest followed markers in the
#: design (their ids are known), within this many design pitches, at least :data:`F2F_FOLLOWED_MIN_FIT`
#: of them, under the same tests: a design neighbourhood does not shrink with the view's foreshortening.
F2F_DESIGN_REACH = 2.5
#: Rounds of prediction (a correspondence reaches a marker from neighbours one ring nearer the
#: bootstrapped ones each round). A large step bootstraps only the slow part of the skin (the twin's
#: 2 pi / 5 sine at 3 -> 4 mm: 79 of 216 markers) and the rest is reached ring by ring across a
#: pattern 8 rings in radius, with crowded rings taking more than one round: 12 rounds stopped that
#: growth still under way; a frame that converges stops at once.
F2F_ROUNDS = 24


def _nn_dist(xy: np.ndarray) -> np.ndarray:
    """Each point's distance to its nearest other point, inf for a lone point (:func:`~pipeline.vision.nearest.
    nearest_other_distances`: what a k-d tree's ``query(xy, k=2)`` gives, several times a frame, without the tree)."""
    return nearest_other_distances(np.ascontiguousarray(xy, np.float64).reshape(-1, 2))


def expected_positions(xy: np.ndarray, ids: np.ndarray, xy_before: np.ndarray, ids_before: np.ndarray) -> np.ndarray:
    """Where each marker certified in the last frame (``xy``, ``ids``) is expected now: moved on by its
    motion since the frame before (``xy_before``, ``ids_before``); NaN where it was not certified then
    (the frame-to-frame map then starts from its last position)."""
    if len(ids) == 0:
        return np.empty((0, 2))
    then = np.full((int(max(ids.max(), ids_before.max(initial=0))) + 1, 2), np.nan)
    then[ids_before] = xy_before
    return 2.0 * xy - then[ids]


def _neighbourhoods(P: np.ndarray):
    """Each previous marker's fit neighbourhood (markers at ``P`` (M, 2)): up to :data:`F2F_NEIGHBOURS`
    nearest other markers within :data:`F2F_RADIUS` local spacings, its first shell
    (:data:`F2F_SHELL`) also within :data:`F2F_SHELL_REACH` median spacings. Returns (nb (M, K)
    neighbour indices, near (M, K) within reach, shell (M, K) the reachable first shell, s_prev (M,)
    local spacing: the marker's nearest-neighbour distance or its neighbours' median, the smaller)."""
    m = len(P)
    k = min(F2F_NEIGHBOURS, m - 1)
    dn, nb = knn(P, P, k + 1)
    dn, nb = dn[:, 1:], nb[:, 1:]                              # never the marker itself
    s_prev = dn[:, 0].copy() if k > 0 else np.full(m, np.inf)  # the nearest other marker (:func:`_nn_dist`)
    near = np.isfinite(dn) & (dn <= F2F_RADIUS * s_prev[:, None])
    first = np.arange(k) < F2F_SHELL
    near |= first & np.isfinite(dn) & (dn <= F2F_SHELL_REACH * np.median(s_prev[np.isfinite(s_prev)]))
    nb = np.ascontiguousarray(np.where(near, nb, 0), dtype=np.int64)
    # a marker whose crowded neighbour merged with it into one blob has a wide spacing itself; its
    # neighbours' spacing says how crowded the skin is there
    s_prev = np.minimum(s_prev, _median_where(s_prev[nb], near, s_prev))
    return nb, near, near & first, s_prev


def _fit(P, pts, nb, near, shell, corr, s_prev, B, far=None, design=None):
    """:func:`_predict` under the frame-to-frame tests, over the whole neighbourhood ``near`` and,
    where that fit is refused, over the first ``shell`` alone (:data:`F2F_SHELL`); where both are
    refused, for the markers ``far`` (those whose start found their blob: the fit then only confirms a
    correspondence, never carries one into a region the start did not reach), over the nearest followed
    markers in the image (:data:`F2F_FOLLOWED_REACH`) and then, with ``design`` ((M, 2) the markers'
    design x-y, design pitch), in the design (:data:`F2F_DESIGN_REACH`)."""
    pred, ok, jac, res = _predict(P, pts, nb, near, corr, s_prev, F2F_MIN_FIT, F2F_SPREAD, F2F_FIT_RESIDUAL, B)
    if not ok.all():
        p1, ok1, j1, r1 = _predict(P, pts, nb, shell, corr, s_prev, F2F_MIN_FIT, F2F_SPREAD, F2F_FIT_RESIDUAL, B)
        ok1 &= ~ok
        pred[ok1], jac[ok1], res[ok1] = p1[ok1], j1[ok1], r1[ok1]
        ok = ok | ok1
    if far is None:
        return pred, ok, jac, res
    wider = [(P, F2F_FOLLOWED_REACH * np.median(s_prev[np.isfinite(s_prev)]))]
    if design is not None:
        wider.append((design[0], F2F_DESIGN_REACH * design[1]))
    for space, reach in wider:
        if not (far & ~ok).any():
            break
        p2, ok2, j2, r2 = _fit_nearest(P, pts, corr, s_prev, B, far & ~ok, space, reach)
        pred[ok2], jac[ok2], res[ok2] = p2[ok2], j2[ok2], r2[ok2]
        ok = ok | ok2
    return pred, ok, jac, res


def _fit_nearest(P, pts, corr, s_prev, B, which, space, reach):
    """:func:`_predict` for the markers ``which`` from their :data:`F2F_NEIGHBOURS` nearest markers that
    have a correspondence, nearest and within ``reach`` in ``space`` (M, 2): the image (``P``) or the
    design; at least :data:`F2F_FOLLOWED_MIN_FIT` of them (same spread and residual tests)."""
    has = np.flatnonzero(corr >= 0)
    if len(has) < F2F_FOLLOWED_MIN_FIT + 1:
        return P, np.zeros(len(P), bool), np.zeros((len(P), 4)), np.full(len(P), np.inf)
    d, j = knn(space[has], space, min(F2F_NEIGHBOURS + 1, len(has)))
    nb = np.ascontiguousarray(has[j], dtype=np.int64)
    near = (nb != np.arange(len(P))[:, None]) & (d <= reach) & which[:, None]
    pred, ok, jac, res = _predict(P, pts, nb, near, corr, s_prev, F2F_FOLLOWED_MIN_FIT, F2F_SPREAD, F2F_FIT_RESIDUAL, B)
    return pred, ok & which, jac, res


def _median_where(v: np.ndarray, mask: np.ndarray, default: np.ndarray) -> np.ndarray:
    """Row-wise median of ``v`` over ``mask`` (``default`` for rows without any): ``np.nanmedian`` of the row with
    the unmasked entries NaN, value for value (the middle one, or the two middle ones' sum halved; NaN entries
    ignored), compiled: numpy takes the masked-array path for rows this short (~0.5 ms a call)."""
    return _median_where_kernel(np.ascontiguousarray(v, np.float64), np.ascontiguousarray(mask, np.bool_),
                                np.asarray(default, np.float64))


@numba.njit(cache=True, nogil=True)
def _median_where_kernel(v, mask, default):
    out = default.copy()
    s = np.empty(v.shape[1])
    for i in range(v.shape[0]):
        m, any_mask = 0, False
        for j in range(v.shape[1]):
            if mask[i, j]:
                any_mask = True
                x = v[i, j]
                if not np.isnan(x):
                    k = m                      # insertion sort into s[:m + 1] (a row is a dozen values)
                    while k > 0 and s[k - 1] > x:
                        s[k] = s[k - 1]
                        k -= 1
                    s[k] = x
                    m += 1
        if not any_mask:
            continue
        if m == 0:
            out[i] = np.nan
            continue
        h = m // 2
        out[i] = s[h] if m % 2 == 1 else (s[h - 1] + s[h]) / 2.0
    return out


def _accept(pred: np.ndarray, ok: np.ndarray, pts: np.ndarray, s_cur: np.ndarray, s_prev: np.ndarray,
            gate) -> np.ndarray:
    """Current blob index per prediction (-1 where refused): nearest blob within the gate, clear of the
    second-nearest, and mutual (no other prediction nearly as near to that blob). ``gate``: in local
    spacings, per prediction or one for all. The local spacing is
    the smaller of the blob's nearest-neighbour distance now and the marker's in the previous frame:
    two crowded pins detected as one blob have a wider spacing now than either had."""
    out = np.full(len(pred), -1, np.int64)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return out
    d, j = knn(pts, pred[idx], 2)
    s = np.minimum(s_cur[j[:, 0]], s_prev[idx])
    good = ((d[:, 0] <= np.broadcast_to(gate, len(pred))[idx] * s) & (d[:, 1] >= F2F_RATIO * d[:, 0])
            & (d[:, 1] - d[:, 0] >= F2F_MARGIN * s))
    idx, j1, d1, s = idx[good], j[good, 0], d[good, 0], s[good]
    if len(idx) == 0:
        return out
    if len(idx) < 2:       # a single prediction is its blob's nearest, with no other near it
        out[idx] = j1
        return out
    return _assign_mutual(out, idx, j1, d1, s, pred[idx], pts)


def _assign_mutual(out: np.ndarray, idx: np.ndarray, j1: np.ndarray, d1: np.ndarray, s: np.ndarray,
                   cand: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The mutual test and the assignment shared by :func:`_accept` and re-acquisition: prediction ``idx[k]``
    (at ``cand[k]``, whose nearest blob ``j1[k]`` lies ``d1[k]`` away, local spacing ``s[k]``) gets that blob
    when the blob's nearest candidate is this prediction and the next candidate is :data:`F2F_RATIO` times
    and :data:`F2F_MARGIN` spacings farther (``cand`` may hold more points after the predictions: they only
    compete), and no other prediction takes the same blob. Writes into ``out`` and returns it."""
    pd, pj = knn(cand, pts[j1], 2)
    mutual = (pj[:, 0] == np.arange(len(idx))) & (pd[:, 1] >= F2F_RATIO * d1) & (pd[:, 1] - d1 >= F2F_MARGIN * s)
    idx, j1 = idx[mutual], j1[mutual]
    u, c = np.unique(j1, return_counts=True)
    single = ~np.isin(j1, u[c > 1])
    out[idx[single]] = j1[single]
    return out


def frame_to_frame(prev_xy: np.ndarray, prev_ids: np.ndarray, pts: np.ndarray, expected: np.ndarray | None = None,
                   design_nbr: np.ndarray | None = None, design_xy: np.ndarray | None = None,
                   start_at_previous: bool = False, design_pitch: float | None = None) -> np.ndarray:
    """Ids of the previous frame's certified markers (``prev_xy`` (M, 2) px, ``prev_ids`` (M,)) that the
    frame-to-frame map certifies on the current blobs ``pts`` (n, 2); -1 elsewhere (see the module
    notes). The previous ids are taken as right: what this certifies is only which blob each became.
    ``expected`` (M, 2): where each marker is expected now (its previous position moved on at its
    last frame's velocity; NaN where unknown): the start and the base of the fit of the motion's
    change; default its previous position. ``start_at_previous``: the velocity is a guess (the motion
    from the rest pattern, see :class:`~pipeline.vision.dtrc.DTRCTracker`): start from the previous
    positions even so, and predict from the fit of the motion's change only where its worst residual
    is no larger than the increment fit's.
    ``design_nbr`` (slots, K): each design slot's immediate design neighbours (-1 padded); a marker
    with one of them missing from ``prev_ids`` gets the gate :data:`F2F_GATE_ALONE`, unless (with
    ``design_xy`` (slots, 2), the design's x-y) each such neighbour has a blob of its own now
    (:func:`~pipeline.vision.identity.apart.lost_neighbours_apart`); the design x-y also gives the fit from
    the nearest followed markers in the design (:data:`F2F_DESIGN_REACH`), in units of ``design_pitch`` (the
    design's median nearest-neighbour distance, the lattice's ``pitch``; computed from ``design_xy`` when not
    given)."""
    n, m = len(pts), len(prev_ids)
    out = np.full(n, -1, np.int64)
    if n < F2F_MIN_FIT + 1 or m < F2F_MIN_FIT + 1:
        return out
    P = np.ascontiguousarray(prev_xy, dtype=np.float64)
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    s_cur = _nn_dist(pts)
    nb, near, shell, s_prev = _neighbourhoods(P)

    gate = np.full(m, F2F_GATE)
    alone = np.zeros(m, bool)
    if design_nbr is not None and len(design_nbr):
        known = np.zeros(len(design_nbr) + 1, bool)          # index -1 (padding) stays "known"
        known[prev_ids] = True
        known[-1] = True
        alone = ~known[design_nbr[prev_ids]].all(axis=1)
        gate[alone] = F2F_GATE_ALONE
    apart = alone if design_xy is not None else np.zeros(m, bool)
    design = None
    if design_xy is not None and len(design_xy) > 1:
        if design_pitch is None:
            design_pitch = float(np.median(_nn_dist(design_xy)))
        design = (np.asarray(design_xy, np.float64)[prev_ids], design_pitch)

    # bootstrap: mutual nearest neighbours with the ratio test, the previous position as prediction
    E = P if expected is None else np.where(np.isfinite(expected), expected, P)
    corr = _accept(P if start_at_previous else E, np.ones(m, bool), pts, s_cur, s_prev, F2F_BOOTSTRAP)
    started = corr >= 0
    moving = None if expected is None else np.isfinite(expected).all(axis=1)
    for _ in range(F2F_ROUNDS):
        pred, ok, jac, res = _fit(P, pts, nb, near, shell, corr, s_prev, P, started, design)
        g = gate
        if apart.any():
            g = gate.copy()
            g[lost_neighbours_apart(P, prev_ids, pred, jac, ok & apart, known, design_nbr, design_xy, pts, s_prev)] = F2F_GATE
        if moving is not None and moving.any():
            # where the increment itself is not affine over the neighbourhood (pins crowding into
            # the crests faster frame by frame), its change from the last frame's still is: the
            # neighbours' departures from their last velocity, fitted the same way, move the
            # marker on from where its own last velocity puts it
            pv, okv, _, rv = _fit(P, pts, nb, near, shell, np.where(moving, corr, -1), s_prev, E, started, design)
            okv &= moving
            if start_at_previous:
                # a guessed velocity (the motion from rest; a sequence may start pressed and held)
                # predicts only where its fit's worst residual is no larger than the increment's
                okv &= rv <= res
            pred = np.where(okv[:, None], pv, pred)
            ok = ok | okv
        # where the skin crowds in this very frame, the predictions crowd with it
        s_pred = np.minimum(s_prev, _nn_dist(pred))
        new = _accept(pred, ok, pts, s_cur, s_pred, g)
        if np.array_equal(new, corr):
            break
        corr = new
    hit = corr >= 0
    out[corr[hit]] = prev_ids[hit]
    return out
