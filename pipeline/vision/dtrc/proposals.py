"""From proposals to certain ids: the ring-coding proposal, ids carried from the previous frame and
lattice registrations, each certified by :mod:`pipeline.vision.identity`, merged, checked against
the previous frame and completed by following markers from it."""

from __future__ import annotations

import numpy as np

from pipeline.design import SensorDesign
from pipeline.vision.identity.anchoring import _components
from pipeline.vision.identity.certify import grow_round
from pipeline.vision.identity.consistency import _blob_of
from pipeline.vision.identity.reacquire import reacquire
from pipeline.vision.identity.rows import extend_rows
from pipeline.vision.identity.constants import R_FEW
from pipeline.vision.identity.temporal import expected_positions
from pipeline.vision.nearest import knn, nearest_other_distances
from pipeline.vision.identity import (R_CONTRADICTED, R_NO_BLOB, R_NOT_FOLLOWED, certify, certify_whole, consistent,
                                      contradicted, frame_to_frame, grow, lattice_of, register_seed)


def _merge(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Union of two id proposals per blob; a blob given two different ids, or an id given to two
    different blobs, is dropped from both."""
    out = np.where(a >= 0, a, b)
    conflict = (a >= 0) & (b >= 0) & (a != b)
    out[conflict] = -1
    lab = out[out >= 0]
    u, cnt = np.unique(lab, return_counts=True)
    out[np.isin(out, u[cnt > 1])] = -1
    return out


#: The lattice registration is tried when ring coding leaves more than this fraction of the blobs
#: (or slots) unidentified.
SEED_BELOW = 0.9
#: Placements scored by the spread registration (six anchor blobs, each on every slot, at one to three
#: rotations: at most ~3,900 for the largest built-in pattern); a cap on its memory, (H, N, 2) floats.
SPREAD_HYPOTHESES = 4_000


def _certain_ids(pts: np.ndarray, proposal: np.ndarray, design: SensorDesign, defects: bool,
                 msgs: list[str], previous=None, history=None, rest_before: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The certainty rule (:mod:`pipeline.vision.identity`) applied to the ring-coding proposal and, when
    ``previous`` (the previous frame's certain markers: xy_px (M, 2), ids (M,)) is given and the
    proposal is not certified whole, to the ids carried from it (:func:`carry_ids`), each extended
    by growth; when that leaves markers unidentified, also to the placements of a lattice
    registration independent of ring peeling, anchored in the middle of the blobs and, for a
    hexagonal or square lattice still read below :data:`SEED_BELOW` with no id carried from a previous
    frame, half-way out (``register_seed(spread=True)``: a sharp press crowds the middle). Markers
    still unidentified are then followed from the previous frame
    (:func:`pipeline.vision.identity.frame_to_frame`), and markers lost before it are re-acquired from
    the earlier frames ``history`` (:func:`pipeline.vision.identity.reacquire.reacquire`).
    ``rest_before``: the frame before the previous one in ``previous`` is the rest pattern (see
    :func:`~pipeline.vision.dtrc.coding.code_rings`). Returns (certified id per blob, reason code per design id,
    the frame-to-frame reading kept from the output (:func:`_with_frame_to_frame`) or None, and which blobs
    took their id from the markers' motion alone (the frame-to-frame map or re-acquisition, where this frame's
    rule left them open) or None where none could)."""
    lat = lattice_of(design)
    n_slots = len(lat.xy)
    reason = np.full(n_slots, R_NO_BLOB, np.int64)
    if len(pts) < 4:
        return np.full(len(pts), -1, np.int64), reason, None, None
    if int((proposal >= 0).sum()) == n_slots:
        # ring coding identified every marker (the common case, pressed frames included): the
        # certainty rule need only confirm it, in one compiled pass when there is no other blob
        if certify_whole(pts, proposal, lat):
            if defects:
                msgs.append(f"certainty rule: {n_slots} of {n_slots} ids certain")
            reason[:] = 0
            return proposal.copy(), reason, None, None
        ids = certify(pts, proposal, lat, reason)
        if int((ids >= 0).sum()) == n_slots:
            if defects:
                msgs.append(f"certainty rule: {n_slots} of {n_slots} ids certain")
            return ids, reason, None, None
        reason[:] = R_NO_BLOB
    # Each proposal is made locally consistent, grown and certified on its own (a wrong proposal
    # must not spoil a right one); the two best certified results are merged and certified again.
    def run(p):
        r = np.full(n_slots, R_NO_BLOB, np.int64)
        grown = grow(pts, consistent(pts, p, lat, r), lat, r)
        ids = certify(pts, grown, lat, r, consistent_input=True)
        return ids, r, np.array_equal(ids, grown)

    def count(c):
        return int((c[0] >= 0).sum())

    enough = SEED_BELOW * min(n_slots, len(pts))
    cands = [run(proposal)]
    carried = None if previous is None else carry_ids(previous[0], previous[1], pts)
    carries = carried is not None and bool((carried >= 0).any())
    if carries:
        cands.append(run(carried))
    # the registration anchored in the middle, then (hexagonal, square) the one anchored half-way out: it
    # costs 35-90 ms a view where it runs (hexagon217, square121), so it is a first frame's (or one after
    # everything was lost); in a sequence the previous frame's ids carry the reading
    registrations = [{}]
    if lat.translation_lattice and not carries:
        registrations.append({"spread": True, "max_hypotheses": SPREAD_HYPOTHESES})
    for kw in registrations:
        if max(map(count, cands)) >= enough:
            break
        for p in register_seed(pts, lat, **kw):
            cands.append(run(p))
            if count(cands[-1]) >= enough:
                break
    cands.sort(key=lambda c: -count(c))
    if len(cands) > 1 and count(cands[1]) > 0:
        merged = _merge(cands[0][0], cands[1][0])
        if not _settled(pts, cands[0], merged, lat):
            cands.append(run(merged))
    ids, reason, _ = max(cands, key=count)
    ids, reason = _withdraw_thinly_held(ids, reason, lat, msgs)
    rule_ids = ids
    if carries:
        bad = _temporally_contradicted(previous, pts, ids, carried)
        if bad.any():
            ids, reason = ids.copy(), reason.copy()
            reason[ids[bad]] = R_CONTRADICTED
            ids[bad] = -1
            msgs.append(f"withdrew {int(bad.sum())} id(s) that the previous frame's markers contradict")
    followed, by_motion = None, None
    if previous is not None and int((ids >= 0).sum()) < min(n_slots, len(pts)):
        open_ = ids < 0
        ids, reason, followed = _with_frame_to_frame(previous, pts, ids, rule_ids, reason, lat, msgs, rest_before)
        if history and followed is None and int((ids >= 0).sum()) < min(n_slots, len(pts)):
            back = reacquire(history, ids, pts, lat.nbr)
            if (back >= 0).any():
                ids = np.where(back >= 0, back, ids)
                msgs.append(f"re-acquired {int((back >= 0).sum())} marker(s) lost in earlier frames")
        by_motion = open_ & (ids >= 0)
    if lat.translation_lattice and int((ids >= 0).sum()) < min(n_slots, len(pts)):
        rows = extend_rows(pts, ids, lat, reason)
        if rows is not ids:
            msgs.append(f"read {int((rows >= 0).sum() - (ids >= 0).sum())} outer-ring marker(s) along their rows")
            ids = rows
    reason[ids[ids >= 0]] = 0
    n_certified = int((ids >= 0).sum())
    if defects or n_certified < n_slots:
        msgs.append(f"certainty rule: {n_certified} of {n_slots} ids certain")
    return ids, reason, followed, by_motion


def _settled(pts: np.ndarray, best: tuple, merged: np.ndarray, lat) -> bool:
    """Whether certifying the merged reading ``merged`` again would give the best reading ``best`` (ids, reasons,
    whether certification withdrew nothing after growth) back unchanged, so that it need not run: the merge
    added nothing to it, its certification withdrew nothing (it is consistent and anchored as it stands), and
    growth would propose no blob for any free slot. (The usual frame with a missing or spurious blob: ring
    coding's reading and the ids carried from the previous frame certify to the same ids.)"""
    return bool(best[2] and np.array_equal(merged, best[0])
                and len(grow_round(pts, merged, lat, np.zeros(len(lat.xy), np.int64))[0]) == 0)


#: An interior marker of a hexagonal or square pattern keeps its id only with at least this many of its
#: immediate design neighbours identified beside it.
HELD_BY = 3
#: The same for a circular pattern, whose markers about a hidden centre keep their ids by their rings (a ring
#: neighbour on either side). Near a sharp press off the axis a blob given an interior slot held by one identified
#: neighbour of six was the next slot's pin or a spurious blob (docs/IDENTIFICATION.md).
HELD_BY_RINGS = 2


def held(ids: np.ndarray, lab: np.ndarray, lat, at_least: int = HELD_BY) -> np.ndarray:
    """Which of the identified blobs ``lab`` (their ids in ``ids``, one id per blob) are outer-ring markers or
    have at least ``at_least`` of their immediate design neighbours identified in ``ids``."""
    has = np.zeros(len(lat.xy), bool)
    has[ids[ids >= 0]] = True
    nb = lat.nbr[ids[lab]]
    count = np.count_nonzero((nb >= 0) & has[np.maximum(nb, 0)], axis=1)
    return (count >= at_least) | np.isin(ids[lab], lat.outer_ring)


def _withdraw_thinly_held(ids: np.ndarray, reason: np.ndarray, lat, msgs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Withdraw the ids of interior markers with fewer than :data:`HELD_BY` identified immediate design
    neighbours (:data:`HELD_BY_RINGS` on a circular pattern; reason ``R_FEW``), once. Near a sharp press
    tip the skin crowds to half the median spacing and a missing marker's slot, predicted across a gap
    from one side, is taken by whatever
    blob sits about where the displaced pin would be: a spurious blob, or the next pin. Such an id is
    held by two neighbours or fewer; a marker inside the pattern that is really identified has its
    ring of six (eight) neighbours mostly identified too. The outer ring, where a marker has only
    three or four neighbours, is left to the anchoring test.

    Measured on 2,755 sharply pressed views with up to 10 % missing and spurious blobs (5 mm, sigma
    1-2.5 mm; hexagon127, square121, hexagon217_sep180): 5 -> 3 wrong ids, coverage 93.61 -> 93.50 %."""
    lab = np.flatnonzero(ids >= 0)
    if len(lab) == 0:
        return ids, reason
    need = HELD_BY if lat.translation_lattice else HELD_BY_RINGS
    drop = ~held(ids, lab, lat, need)
    if not drop.any():
        return ids, reason
    ids, reason = ids.copy(), reason.copy()
    reason[ids[lab[drop]]] = R_FEW
    ids[lab[drop]] = -1
    msgs.append(f"withdrew {int(drop.sum())} interior id(s) held by fewer than {need} identified neighbours")
    return ids, reason


#: More contradictions than this fraction of the markers both certifications cover (and more than
#: :data:`F2F_FEW_CONTRADICTIONS`) put the premise of one of them in doubt: a frame that moved so far
#: that markers were followed to their neighbours' blobs (the rule's reading stands when it covers
#: :data:`SEED_BELOW` of the pattern), or crowding beyond what the design-to-image rule can read
#: (otherwise: only the markers on which both agree are kept).
F2F_CONTRADICTED_SHARE = 0.2
F2F_FEW_CONTRADICTIONS = 2


def _with_frame_to_frame(previous, pts: np.ndarray, ids: np.ndarray, rule_ids: np.ndarray, reason: np.ndarray, lat,
                         msgs: list[str], rest_before: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Add the markers the frame-to-frame map certifies (:func:`pipeline.vision.identity.frame_to_frame`)
    to the design-to-image ids ``ids``: where the pins crowd, the design-to-image map is not locally
    affine and the certainty rule withdraws correct ids, while one frame's increment is still small
    and smooth. Two certified readings that disagree cannot both be right: a blob on which they
    disagree (another id, or its id on another blob) loses both, and so does every design-to-image
    id of the same patch (a patch read one lattice step over is wrong as a whole, also where the
    frame-to-frame map has nothing to say). Many disagreements: when the rule read nearly the whole
    pattern, the frame-to-frame map is set aside (the frame moved too far to be followed); otherwise
    only the agreement is kept. A previous marker certified by neither is unmatched with its own
    reason. Disagreement is judged against ``rule_ids``, the rule's reading before the previous
    frame's ids withdrew any of it (:func:`_temporally_contradicted`): an id withdrawn there is not
    handed to the reading that contradicted it.

    Returns (ids, reasons, followed): ``followed`` is the frame-to-frame reading when many
    disagreements kept it from the output (None otherwise). Nothing in one frame says which reading
    is wrong; following it on keeps the question open in the next frame, where it withholds again
    whatever this frame's rule reads differently (a rule misled by crowding keeps disagreeing with
    the markers' continuous motion), instead of letting the rule's reading stand alone."""
    expected = expected_positions(*previous) if len(previous) == 4 else None
    t = frame_to_frame(previous[0], previous[1], pts, expected, lat.nbr, lat.xy, start_at_previous=rest_before,
                       design_pitch=lat.pitch)
    ids, reason = ids.copy(), reason.copy()
    followed = None
    if (t >= 0).any():
        bad = contradicted(rule_ids, t) | contradicted(t, rule_ids)
        n_bad = int(bad.sum())
        if n_bad:
            agree = (ids >= 0) & (ids == t)
            few = n_bad <= max(F2F_FEW_CONTRADICTIONS,
                               F2F_CONTRADICTED_SHARE * int(((rule_ids >= 0) & (t >= 0)).sum()))
            if few:
                comp = _components(rule_ids, _blob_of(rule_ids, len(lat.xy)), lat.nbr)
                drop_d = (ids >= 0) & np.isin(comp, np.unique(comp[bad & (rule_ids >= 0)])) & ~agree
                drop_t = bad & (t >= 0)
                msgs.append(f"withdrew {int((drop_d | drop_t).sum())} id(s) where the frame-to-frame map and this "
                            "frame's rule disagree")
            elif int((rule_ids >= 0).sum()) >= SEED_BELOW * min(len(lat.xy), len(pts)):
                # the rule read (nearly) the whole pattern, anchored by its whole outline: the skin
                # moved so far since the previous frame that its markers were followed to their
                # neighbours' blobs
                msgs.append(f"frame-to-frame map set aside: it contradicts {n_bad} id(s) of a whole reading")
                return ids, reason, None
            else:
                drop_d, drop_t = (ids >= 0) & ~agree, (t >= 0) & ~agree
                followed = t.copy()
                msgs.append(f"the frame-to-frame map and this frame's rule disagree on {n_bad} marker(s): "
                            f"kept the {int(agree.sum())} they agree on")
            reason[ids[drop_d]] = R_CONTRADICTED
            reason[t[drop_t]] = R_CONTRADICTED
            ids[drop_d] = -1
            t[drop_t] = -1
        add = (ids < 0) & (t >= 0)
        if add.any():
            ids[add] = t[add]
            msgs.append(f"frame-to-frame map certified {int(add.sum())} more marker(s)")
    lost = np.setdiff1d(previous[1], ids[ids >= 0])
    lost = lost[reason[lost] != R_CONTRADICTED]
    reason[lost] = R_NOT_FOLLOWED
    return ids, reason, followed


#: A frame's motion is small when this fraction of its certified markers moved less than
#: :data:`SMALL_MOTION` local spacings since the previous frame ...
SMALL_MOTION_QUANTILE = 0.95
#: ... (then a marker's nearest blob within a third of a spacing is that marker: a neighbour, at
#: least ~0.6 spacings away even where the skin crowds, would have to move more than a quarter).
SMALL_MOTION = 0.25


def _temporally_contradicted(previous, pts: np.ndarray, ids: np.ndarray, carried: np.ndarray) -> np.ndarray:
    """Blobs whose certified id the previous frame contradicts (bool mask), when the frame's motion is
    small: :data:`SMALL_MOTION_QUANTILE` of the markers certified in both frames (``ids`` on ``pts``
    now, ``previous`` then) moved less than :data:`SMALL_MOTION` local spacings. Then every marker is
    still the blob nearest to where it was, so a certified id is contradicted when the blob carries
    another marker's id from the previous frame (:func:`carry_ids`), when its id was carried to
    another blob, or when the marker of that id moved more than a third of a spacing (the carrying
    gate) while its neighbours barely moved. After a larger step a marker's previous nearest blob may
    be its neighbour, and nothing is withdrawn."""
    bad = np.zeros(len(pts), bool)
    lab = np.flatnonzero(ids >= 0)
    if len(lab) < 3 or len(pts) < 3 or len(previous[1]) == 0:
        return bad
    where = np.full(int(max(ids.max(), previous[1].max())) + 1, -1, np.int64)
    where[previous[1]] = np.arange(len(previous[1]))
    j = where[ids[lab]]
    both = j >= 0
    if both.sum() < 3:
        return bad
    step = np.linalg.norm(pts[lab[both]] - previous[0][j[both]], axis=1)
    spacing = float(np.median(nearest_other_distances(np.ascontiguousarray(pts, np.float64))))
    if np.quantile(step, SMALL_MOTION_QUANTILE) >= SMALL_MOTION * spacing:
        return bad
    bad |= contradicted(ids, carried)
    bad[lab[both][step > spacing / 3]] = True
    return bad


def carry_ids(prev_xy_px: np.ndarray, prev_ids: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Ids of the previous frame's identified markers proposed for the current blobs: each previous
    marker goes to the nearest current blob when that blob is within a third of the local spacing,
    at least twice as near as the second-nearest blob, and nearest to no other previous marker.
    Only a proposal: a whole pattern that moved by one spacing between frames carries consistently
    wrong ids, which the anchoring test withdraws."""
    out = np.full(len(pts), -1, np.int64)
    if len(pts) < 2 or len(prev_ids) < 2:
        return out
    spacing = float(np.median(nearest_other_distances(np.ascontiguousarray(pts, np.float64))))
    d, j = knn(pts, prev_xy_px, 2)
    ok = (d[:, 0] <= spacing / 3) & (d[:, 1] >= 2 * d[:, 0])
    u, cnt = np.unique(j[ok, 0], return_counts=True)
    ok &= ~np.isin(j[:, 0], u[cnt > 1])
    out[j[ok, 0]] = prev_ids[ok]
    return out
