"""The certainty rule applied: :func:`certify` (consistency, anchoring, rotation), its one-pass
:func:`certify_whole` for a complete proposal, :func:`grow` (free slots predicted from identified
neighbours) and :func:`contradicted`."""

from __future__ import annotations

import math

import numba
import numpy as np

from pipeline.vision.identity.anchoring import (_alternatives_excluded, _anchored, _beyond_hits, _centre_holds,
                                                _components, _rotation_deg)
from pipeline.vision.identity.consistency import _blob_of, _consistency, _statuses, consistent
from pipeline.vision.identity.constants import (_NEED_SEARCH, AMBIGUITY_MARGIN, ANCHOR_EVIDENCE, BEYOND_HITS,
                                                GATE, GROW_GATE, MIN_PATCH, R_AMBIGUOUS, SEAM_LONGER,
                                                R_ANCHOR, R_FEW, R_NO_BLOB, R_OK, R_ROTATION)
from pipeline.vision.identity.fits import _fit, _fit_sums, _gather
from pipeline.vision.identity.lattice import Lattice, rotation_limit_deg
from pipeline.vision.identity.neighbours import _adj
from pipeline.vision.nearest import knn


@numba.njit(cache=True, nogil=True)
def _predict_free(pts, blob_of, xy, nbr, pitch):
    """Predicted image position and local pitch (px) of every free slot with a usable fit from its
    identified neighbours; ``scale`` 0 where there is none."""
    N = len(blob_of)
    K = nbr.shape[1]
    pred = np.zeros((N, 2))
    scale = np.zeros(N)
    slots = np.empty(K, np.int64)
    blobs = np.empty(K, np.int64)
    acc = np.empty(12)
    for s in range(N):
        if blob_of[s] >= 0:
            continue
        m = _gather(s, nbr, 0, K, blob_of, slots, blobs, 0)
        if m < 3:
            continue
        ox, oy, ou, ov = xy[s, 0], xy[s, 1], pts[blobs[0], 0], pts[blobs[0], 1]
        acc = _fit_sums(xy, pts, slots, blobs, m, ox, oy, ou, ov, acc)
        ok, mx, my, mu, mv, l00, l01, l10, l11 = _fit(xy, pts, slots, blobs, acc, -1, ox, oy, ou, ov, pitch)
        if ok <= 0:
            continue
        pred[s, 0] = ou + mu - l00 * mx - l01 * my
        pred[s, 1] = ov + mv - l10 * mx - l11 * my
        scale[s] = math.sqrt(l00 * l11 - l01 * l10) * pitch
    return pred, scale


def certify_whole(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice) -> bool:
    """The common case in one compiled pass: every blob carries a proposed id, and every id of the
    design is proposed (no defect at all). True when :func:`certify` would keep the whole proposal:
    every marker consistent without a blob search (intact fans, :func:`_embedded`), the pattern
    within the rotation limit, excluded from every alternative reading (and, for circular
    patterns, centred). False means only "not decided here": :func:`certify` decides."""
    N = len(lat.xy)
    if len(pts) != N or len(slot_of) != N or N < MIN_PATCH:
        return False
    adj = _adj(pts)
    if len(adj[1]) == 0:
        return False
    if not _whole_kernel(pts, adj[0], adj[1], slot_of, lat.xy, lat.nbr, lat.nbr2, lat.loo_m,
                         lat.loo_tab, lat.fan, lat.fan_closed, lat.pitch, GATE, rotation_limit_deg(lat), lat.alt,
                         lat.alt_first, ANCHOR_EVIDENCE):
        return False
    members = np.arange(N, dtype=np.int64)
    return lat.translation_lattice or _centre_holds(pts, slot_of, members, lat)


@numba.njit(cache=True, nogil=True)
def _whole_kernel(pts, adj_ptr, adj_idx, slot_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed, pitch, gate, limit, alt,
                  alt_first, evidence):
    """:func:`certify_whole` without the circular patterns' centre test."""
    n = len(slot_of)
    blob_of = np.full(len(xy), -1, np.int64)
    for b in range(n):
        s = slot_of[b]
        if s < 0 or blob_of[s] >= 0:
            return False
        blob_of[s] = b
    order = np.arange(n)
    rival = np.zeros(0, np.bool_)                  # every blob labelled: none is free
    search = False
    if fan[:, 0].max() < 0:
        # no fans (circular patterns): every test searches
        search = True
    st = _consistency(pts, search, adj_ptr, adj_idx, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed,
                      pitch, gate, order, 0, rival)
    n_need = 0
    for b in range(n):
        if st[b] == _NEED_SEARCH:
            n_need += 1
        elif st[b] != 0:
            return False
    if n_need:
        # the fans that are not exactly Delaunay stars need the blob search
        search = True
        need = np.empty(n_need, np.int64)
        k = 0
        for b in range(n):
            if st[b] == _NEED_SEARCH:
                need[k] = b
                k += 1
        st = _consistency(pts, True, adj_ptr, adj_idx, slot_of, blob_of, xy, nbr, nbr2, loo_m, loo_tab, fan, closed,
                          pitch, gate, need, 0, rival)
        for b in need:
            if st[b] != 0:
                return False
    des = np.empty((n, 2))
    for b in range(n):
        des[b, 0] = xy[slot_of[b], 0]
        des[b, 1] = xy[slot_of[b], 1]
    if abs(_rotation_deg(pts, des)) > limit:
        return False
    if alt.shape[0] == 0:
        return True
    if _alternatives_excluded(pts, search, adj_ptr, adj_idx, slot_of, order, alt, alt_first, xy, nbr, nbr2, loo_m,
                              loo_tab, fan, closed, pitch, gate, evidence):
        return True
    if search:
        return False
    return _alternatives_excluded(pts, True, adj_ptr, adj_idx, slot_of, order, alt, alt_first, xy, nbr, nbr2,
                                  loo_m, loo_tab, fan, closed, pitch, gate, evidence)


def certify(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice, reason: np.ndarray | None = None,
            consistent_input: bool = False):
    """Apply the certainty rule to a proposal.

    Parameters
    ----------
    pts : (n, 2) float64 blob centres (px)
    slot_of : (n,) int64 proposed design id per blob (-1 none; ids unique)
    lat : :class:`Lattice`
    reason : (N,) int64, optional, updated in place with the reason code of every withdrawn id
    consistent_input : bool
        ``slot_of`` is what :func:`consistent` or :func:`grow` returned (locally consistent as it stands: both
        strip labels until none fails), so the first pass skips the consistency test it would pass unchanged

    Returns
    -------
    (n,) int64 certified ids (-1 where withdrawn).
    """
    if reason is None:
        reason = np.zeros(len(lat.xy), np.int64)
    # the markers of a withdrawn patch or piece were some of the neighbours the markers beside them
    # were found consistent with (a marker joined to the rest only through a withdrawn piece is left
    # with one identified neighbour): the survivors are tested again, until nothing more is withdrawn
    checked = consistent_input
    while True:
        slot_of, withdrawn = _certify_once(pts, slot_of, lat, reason, checked)
        if not withdrawn:
            return _unrivalled(pts, slot_of, lat, reason)
        checked = False


def _rivals(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice) -> np.ndarray:
    """The blobs that may be a labelled slot's own pin displaced by a bend (``rival`` of the consistency
    test): those the reading leaves free, but not one within the growth gate of a free slot's prediction
    (that slot's own pin, crowded there)."""
    rival = slot_of < 0
    if not rival.any() or not (slot_of >= 0).any():
        return rival
    pred, scale = _predict_free(pts, _blob_of(slot_of, len(lat.xy)), lat.xy, lat.nbr2, lat.pitch)
    free = np.flatnonzero(scale > 0)
    if len(free):
        d, j = knn(pts, pred[free], 1)
        rival[j[d[:, 0] <= GROW_GATE * scale[free], 0]] = False
    return rival


def _unrivalled(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice, reason: np.ndarray) -> np.ndarray:
    """The certified reading ``slot_of`` without the ids a rival blob leaves open (reason ``R_AMBIGUOUS``):
    near a sharp press the neighbourhood bends, and the bend its leave-one-out residuals show displaces the
    slot's own pin too, so a free blob within the growth gate widened by that bend (as far as the bend may
    displace the pin) is as good a reading of the slot as the labelled blob. Tested once on the certified
    reading: the ids are withdrawn and nothing else, so no withdrawal cascades through its neighbours'
    tests or the patch's anchoring (each withdrawn marker's neighbours were certified with it; the patch
    is certified whole)."""
    rival = _rivals(pts, slot_of, lat)
    if not rival.any():
        return slot_of
    st = _statuses(pts, _adj(pts), slot_of, lat, rival=rival)
    amb = np.flatnonzero(st == R_AMBIGUOUS)
    if len(amb) == 0:
        return slot_of
    slot_of = slot_of.copy()
    reason[slot_of[amb]] = R_AMBIGUOUS
    slot_of[amb] = -1
    return slot_of


def _certify_once(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice, reason: np.ndarray,
                  checked: bool = False) -> tuple[np.ndarray, bool]:
    """One pass of :func:`certify`: consistency (unless ``checked``: ``slot_of`` is already consistent), then each
    patch's anchoring and rotation. Returns (ids, whether a patch of consistent markers was withdrawn)."""
    N = len(lat.xy)
    slot_of = slot_of.copy() if checked else consistent(pts, slot_of, lat, reason)
    lab = np.flatnonzero(slot_of >= 0)
    if len(lab) == 0:
        return slot_of, False
    blob_of = _blob_of(slot_of, N)
    # patches: identified design neighbours (every such pair passed the consistency test)
    comp_of = _components(slot_of, blob_of, lat.nbr)
    pieces = _components(slot_of, blob_of, lat.nbr, True)
    comp = comp_of[lab]
    n_comp = int(comp.max()) + 1
    beyond = np.zeros(n_comp, np.int64)
    if len(lat.beyond_slot) and len(lab) < len(slot_of):   # a hit is an unidentified blob
        hits = _beyond_hits(pts, slot_of, blob_of, lat.xy, lat.nbr2, lat.pitch, lat.beyond_slot,
                            lat.beyond_xy, GROW_GATE)
        # a real outer row continues along the ring: the longest run of consecutive outer-ring
        # slots (cyclic, canonical order) with a blob beyond them, per patch
        outer = lat.outer_ring
        hit_slot = np.zeros(N, bool)
        hit_slot[lat.beyond_slot[hits > 0]] = True
        h = hit_slot[outer]
        if h.any() and not h.all():
            start = int(np.argmin(h))                     # a slot without a hit: runs do not wrap
            h = np.roll(h, -start)
            o = np.roll(outer, -start)
            run = 0
            for k in range(len(h)):
                run = run + 1 if h[k] else 0
                if run >= BEYOND_HITS:
                    b = blob_of[o[k]]
                    if b >= 0:
                        beyond[comp_of[b]] = max(beyond[comp_of[b]], run)
        elif h.all():
            beyond[:] = len(h)
    limit = rotation_limit_deg(lat)
    withdrawn = False
    for c in range(n_comp):
        members = lab[comp == c]
        code = R_OK
        if len(members) < MIN_PATCH:
            code = R_FEW
        elif abs(_rotation_deg(np.ascontiguousarray(pts[members]), np.ascontiguousarray(lat.xy[slot_of[members]]))) > limit:
            code = R_ROTATION
        elif beyond[c] >= BEYOND_HITS:
            code = R_ANCHOR
        elif not _anchored(pts, slot_of, members, lat):
            code = R_ANCHOR
        if code != R_OK:
            reason[slot_of[members]] = code
            slot_of[members] = -1
            withdrawn = True
        elif lat.translation_lattice and len(np.unique(pieces[members])) > 1:
            loose = _loose_pieces(slot_of, members, pieces[members], lat)
            if loose.any():
                reason[slot_of[loose]] = R_ANCHOR
                slot_of[loose] = -1
                withdrawn = True
    return slot_of, withdrawn


def _loose_pieces(slot_of: np.ndarray, members: np.ndarray, piece: np.ndarray, lat: Lattice) -> np.ndarray:
    """Blobs of an anchored patch ``members`` of a translation lattice (with their triangle-connected
    pieces ``piece``) whose piece the rest of the patch does not hold in place. A piece joined to the
    rest only by bare edges (:func:`pipeline.vision.identity.anchoring._joined`) may be read shifted
    along the lattice across the gap, its local consistency intact and the patch's anchoring (won on
    the evidence of its largest piece) vouching for it. The rest excludes a shifted reading of a
    smaller piece where that reading would put its markers on slots the rest holds, or outside the
    design: every lattice shift of the design (:attr:`Lattice.alt`) applied to the piece alone that
    explains the seam one way along all of it must be excluded by :data:`ANCHOR_EVIDENCE` of its markers
    (all of them when it has fewer). A shift explains the seam by rows crowded out of the detection
    (every seam edge longer than :data:`SEAM_LONGER` pitches and lengthened along itself, the piece
    carried away from the rest) or by blobs at the seam that are not markers (every seam edge collapsed:
    the piece's seam marker on the rest's own slot). Pieces of fewer than :data:`MIN_PATCH` markers carry
    no reading of their own (every fit of theirs leans on the rest) and are left to the consistency test."""
    shifts = _shift_alternatives(lat)
    ids, size = np.unique(piece, return_counts=True)
    held = np.zeros(len(lat.xy) + 1, bool)                # the last entry: outside the design
    loose = np.zeros(len(slot_of), bool)
    for p in ids[np.argsort(-size, kind="stable")][1:]:
        mine = members[piece == p]
        if len(mine) < MIN_PATCH:
            continue
        held[:] = False
        held[-1] = True
        held[slot_of[members[piece != p]]] = True
        evidence = held[shifts[:, slot_of[mine]]].sum(axis=1)
        open_ = evidence < min(ANCHOR_EVIDENCE, len(mine))
        if open_.any():
            # a shifted reading must explain the seam as the view shows it, one way along all of it:
            # rows crowded out of the detection (each edge lengthened along itself: the piece carried
            # away from the rest, the crowded rows between them), or blobs at the seam that are not
            # markers (each edge collapsed: the piece's seam marker on the rest's own slot, the rest's
            # blob there spurious). A shift that lengthens an edge by carrying the piece over the rest
            # to its far side would have the view show the skin's markers in reversed order across the
            # seam, a skin folded over itself, which a press does not do; one that leaves an edge a
            # design neighbour's length turns it, against the view (the consistency test holds the
            # edge where it is)
            a, c = _seam(slot_of, mine, members[piece != p], lat)
            alt = shifts[open_][:, a]
            far = np.linalg.norm(lat.xy[alt] - lat.xy[c][None], axis=2) > SEAM_LONGER * lat.pitch
            away = np.einsum("kej,ej->ke", lat.xy[alt] - lat.xy[a][None], lat.xy[a] - lat.xy[c]) > 0.0
            # a seam marker shifted off the design (-1, which would index the last slot) explains nothing
            collapsed = alt == c[None]                     # c is a slot, so a collapsed edge is inside
            open_[open_] = (far & away & (alt >= 0)).all(axis=1) | collapsed.all(axis=1)
        if open_.any():
            loose[mine] = True
    return loose


def _seam(slot_of, mine, rest, lat):
    """The slots (piece side, rest side) of the design-neighbour pairs joining the piece ``mine`` to
    the ``rest`` of its patch (blob indices)."""
    in_rest = np.zeros(len(lat.xy) + 1, bool)
    in_rest[slot_of[rest]] = True
    s = slot_of[mine]
    nb = lat.nbr[s]
    hit = in_rest[nb] & (nb >= 0)
    return np.repeat(s, hit.sum(axis=1)), nb[hit]


_SHIFTS: dict = {}


def _shift_alternatives(lat: Lattice) -> np.ndarray:
    """The rows of :attr:`Lattice.alt` that shift the design along the lattice."""
    key = id(lat)
    if key not in _SHIFTS:
        _SHIFTS[key] = lat.alt[np.array([n.startswith("shifted") for n in lat.alt_names], bool)]
    return _SHIFTS[key]


def contradicted(slot_of: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Blobs whose id in ``slot_of`` a second certified reading ``other`` (same blobs) contradicts: it
    gives the blob another id, or gives the blob's id to another blob. Two readings that both passed
    the certainty rule yet disagree cannot both be right, and nothing in one frame says which is:
    a row of markers lost at the edge of the view lets the row beside it be read one row over with
    every neighbourhood still a smooth, moderately stretched map, while the same blobs followed from
    the previous frame (motion a fraction of the spacing) keep their own ids. Returns a bool mask."""
    a = slot_of >= 0
    bad = a & (other >= 0) & (other != slot_of)
    where_other = np.full(max(int(slot_of.max(initial=-1)), int(other.max(initial=-1))) + 1, -1, np.int64)
    lab = np.flatnonzero(other >= 0)
    where_other[other[lab]] = lab
    mine = np.flatnonzero(a)
    w = where_other[slot_of[mine]]
    bad[mine[(w >= 0) & (w != mine)]] = True
    return bad


def grow(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice, reason: np.ndarray, max_rounds: int = 64) -> np.ndarray:
    """Extend certified patches slot by slot (see the module notes), re-testing after every round. Given a
    reading :func:`consistent` returned, it returns one :func:`consistent` would return unchanged (each round's
    trial is its output, and a reading that gains nothing is returned as given)."""
    slot_of = slot_of.copy()
    if len(pts) < 2:
        return slot_of
    for _ in range(max_rounds):
        cand, slots = grow_round(pts, slot_of, lat, reason)
        if len(cand) == 0:
            break
        trial = slot_of.copy()
        trial[cand] = slots
        trial = consistent(pts, trial, lat, reason)
        if np.array_equal(trial >= 0, slot_of >= 0) and np.array_equal(trial, slot_of):
            break
        gained = np.count_nonzero(trial >= 0) - np.count_nonzero(slot_of >= 0)
        slot_of = trial
        if gained <= 0:
            break
    return slot_of


def grow_round(pts: np.ndarray, slot_of: np.ndarray, lat: Lattice, reason: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The blobs one round of :func:`grow` proposes for free slots (blob indices, their slots), before the
    consistency test; the reasons of the slots it cannot fill are written into ``reason``. None: ``grow``
    returns a reading as it is (with at least two blobs)."""
    blob_of = _blob_of(slot_of, len(lat.xy))
    pred, scale = _predict_free(pts, blob_of, lat.xy, lat.nbr2, lat.pitch)
    free = np.flatnonzero(scale > 0)
    if len(free) == 0:
        return free, free
    d, j = knn(pts, pred[free], 2)
    d1, d2 = d[:, 0] / scale[free], d[:, 1] / scale[free]
    near = d1 <= GROW_GATE
    reason[free[~near]] = R_NO_BLOB
    amb = near & ~((d2 >= 2 * d1) & (d2 - d1 >= AMBIGUITY_MARGIN))
    reason[free[amb]] = R_AMBIGUOUS
    take = near & ~amb & (slot_of[j[:, 0]] < 0)
    cand = j[take, 0]
    slots = free[take]
    # a blob claimed by two free slots is ambiguous for both
    u, cnt = np.unique(cand, return_counts=True)
    dup = np.isin(cand, u[cnt > 1])
    reason[slots[dup]] = R_AMBIGUOUS
    return cand[~dup], slots[~dup]
