"""Stereo matching and tracking by DTRC codes: identity is the code, so every frame is re-coded;
the previous frame's certain markers only propose ids. :class:`NearestNeighbourTracker` is the
paper's KNN baseline."""

from __future__ import annotations

import math
from dataclasses import replace

import numba
import numpy as np
from scipy.spatial import cKDTree

from pipeline.design import SensorDesign
from pipeline.types import Blobs, MarkerMatches
from pipeline.vision.dtrc.coding import RingCoding, code_rings
from pipeline.vision.dtrc.ring_codes import _marker_count
from pipeline.vision.identity import REASONS, lattice_of
from pipeline.vision.identity.constants import R_AMBIGUOUS
from pipeline.vision.identity.reacquire import REACQUIRE_FRAMES, carry_lost

#: A first frame's view that ring coding identifies to fewer than this fraction of its blobs (the
#: lattice registration's threshold, ``SEED_BELOW``) takes the rest pattern's reading when that reading
#: identifies at least this fraction; above it, the rest reading may only extend ring coding's.
REST_BELOW = 0.9


# ----- stereo matching and tracking ---------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _pair_indices(left_ids, right_ids, n_markers):
    """Ids coded in both views (ascending), their blob index in each view, and the other ids."""
    li = np.full(n_markers, -1, np.int64)
    ri = np.full(n_markers, -1, np.int64)
    for k in range(len(left_ids)):
        if left_ids[k] >= 0:
            li[left_ids[k]] = k
    for k in range(len(right_ids)):
        if right_ids[k] >= 0:
            ri[right_ids[k]] = k
    both = (li >= 0) & (ri >= 0)
    mid = np.flatnonzero(both).astype(np.int64)
    return mid, li[mid], ri[mid], np.flatnonzero(~both).astype(np.int64)


def _pair(left: Blobs, right: Blobs, lc: RingCoding, rc: RingCoding, n_markers: int) -> MarkerMatches:
    mid, li, ri, unmatched = _pair_indices(lc.ids, rc.ids, n_markers)
    return MarkerMatches(ids=mid, left_px=left.xy_px[li], right_px=right.xy_px[ri], unmatched_ids=unmatched)


def match_stereo(left: Blobs, right: Blobs, design: SensorDesign) -> MarkerMatches:
    """Match markers between the left and right views by their DTRC codes.

    Parameters
    ----------
    left, right : Blobs
        Marker centres in each half image (right coordinates relative to the right half).
    design : SensorDesign

    Returns
    -------
    MarkerMatches
        Ids coded in both views (ascending), their pixel centres, and ``unmatched_ids``: design ids
        not coded in at least one view.
    """
    return _pair(left, right, code_rings(left, design), code_rings(right, design), _marker_count(design))


def read_from_rest(blobs: Blobs, design: SensorDesign, coding: RingCoding,
                   rest: tuple[np.ndarray, np.ndarray]) -> RingCoding:
    """A first frame's coding of one view, coded again from the rest pattern ``rest`` ((N, 2) px where
    the calibration puts the undeformed skin's markers, their ids) wherever ring coding left a blob (or
    slot) unidentified.

    * Ring coding left more than a tenth unidentified (:data:`REST_BELOW`; e.g. a pattern whose middle
      a press crowds beyond ring peeling, or a circular pattern with its centre hidden and the rings
      about it too thinned to fix their turn): the rest pattern's
      reading is taken when it explains the view, identifying all but a tenth of the blobs (or slots);
      a partial reading does not replace ring coding's.
    * Ring coding read the view but left some markers unidentified (next to an occluded patch, where
      a marker's neighbourhood reaches across ring coding's withdrawn pieces): the rest reading is
      taken only when it *extends* ring coding's, giving every blob ring coding identified the same id
      and identifying more. Two readings that disagree on a blob leave ring coding's as it is.

    A calibration off by a whole separation can still explain a view (half a pattern read one step
    towards its hidden side: 67 of 67 blobs, all wrong, in both views alike), which the first test
    cannot see: the runner's stereo check drops such a frame (:data:`pipeline.runner.REST_DOUBT`, told
    by :attr:`DTRCTracker.read_from_rest`). Under the second test such a reading may add nothing that
    contradicts ring coding's certain ids (measured with the rest pattern a whole or half separation off:
    it adds nothing at all, ``tests/test_identity.py``)."""
    n = min(len(blobs), _marker_count(design))
    have = int(np.count_nonzero(coding.ids >= 0))
    if n < 4 or have >= n:
        return coding
    again = _keep_ambiguous(coding, code_rings(blobs, design, previous=(_aligned(rest[0], blobs.xy_px), rest[1])))
    got = int(np.count_nonzero(again.ids >= 0))
    if got < REST_BELOW * n:
        return coding
    if have < REST_BELOW * n:
        return again
    coded = coding.ids >= 0
    if got <= have or np.any(again.ids[coded] != coding.ids[coded]):
        return coding
    return again


def _keep_ambiguous(coding: RingCoding, again: RingCoding) -> RingCoding:
    """``again`` (the rest pattern's reading) without the ids ring coding left open as ambiguous: two blobs near
    the slot's prediction from the frame's own identified neighbours. A reading from rest predicts the slot from
    the markers' whole motion since rest, which a press makes larger and less regular: it must not settle what the
    frame's own neighbours could not. (A circular view pressed 4.4 mm off the axis: ring coding left marker 166
    open beside a spurious blob 0.33 separations from it; the rest reading gave the spurious blob the id, and the
    stereo check kept the pair.)"""
    amb = np.array([i for i, r in zip(coding.unmatched_ids.tolist(), coding.unmatched_reasons)
                    if r == REASONS[R_AMBIGUOUS]], np.int64)
    hit = np.isin(again.ids, amb)
    if not np.any(hit):
        return again
    ids, carried = again.ids.copy(), again.carried.copy()
    ids[hit] = -1
    carried[np.isin(carried, amb)] = -1
    reasons = dict(zip(again.unmatched_ids.tolist(), again.unmatched_reasons))
    reasons.update({int(i): REASONS[R_AMBIGUOUS] for i in again.ids[hit]})
    unmatched = np.array(sorted(reasons), np.int64)
    return replace(again, ids=ids, carried=carried, unmatched_ids=unmatched,
                   unmatched_reasons=tuple(reasons[int(i)] for i in unmatched))


#: The rest pattern is brought onto a first frame by an affine map fitted to mutual nearest pairs within
#: this fraction of the blobs' median spacing, refitted this many times (the rest pattern as it stands
#: when fewer than REST_ALIGN_MIN pairs are found). A press bulges the pattern by up to ~15 % and a
#: calibration turns it by a degree or two, so with the pattern's centre hidden every visible marker can
#: lie beyond the frame-to-frame map's bootstrap gate from its rest position (0.15 separations) and the
#: map finds nowhere to start; pairs within half a spacing do not jump to a neighbour's blob.
REST_ALIGN_GATE = 0.5
REST_ALIGN_ROUNDS = 5
REST_ALIGN_MIN = 6


def _aligned(rest_xy: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``rest_xy`` (N, 2) moved by the affine map that best carries it onto the blobs ``pts`` (ICP on
    mutual nearest pairs within :data:`REST_ALIGN_GATE` spacings)."""
    rest_xy = np.asarray(rest_xy, np.float64)
    pts = np.asarray(pts, np.float64)
    if len(pts) < REST_ALIGN_MIN:
        return rest_xy
    tree = cKDTree(pts)
    spacing = float(np.median(tree.query(pts, k=2)[0][:, 1]))
    cur = rest_xy
    for _ in range(REST_ALIGN_ROUNDS):
        d, j = tree.query(cur)
        back = cKDTree(cur).query(pts)[1]
        pair = (d < REST_ALIGN_GATE * spacing) & (back[j] == np.arange(len(cur)))
        if np.count_nonzero(pair) < REST_ALIGN_MIN:
            break
        A = np.column_stack([rest_xy[pair], np.ones(np.count_nonzero(pair))])
        M, *_ = np.linalg.lstsq(A, pts[j[pair]], rcond=None)
        cur = np.column_stack([rest_xy, np.ones(len(rest_xy))]) @ M
    return cur


_NONE = (np.empty((0, 2)), np.empty(0, np.int64))


class DTRCTracker:
    """DTRC tracking: every frame is re-coded, so identity survives arbitrarily large motion; the
    previous frame's identified markers propose ids where coding alone cannot (crowding, large
    deformation, partial occlusion), under the same certainty rule, and keep their ids where the
    frame-to-frame map certifies which blob each became (:func:`pipeline.vision.identity.frame_to_frame`;
    the frame before that gives each marker's last velocity).

    ``update(left, right) -> MarkerMatches`` (also callable). ``last_codings`` holds the two
    :class:`RingCoding` of the latest frame.

    ``rest`` (left_px (N, 2), right_px (N, 2)), optional: where the calibration puts every marker of
    the undeformed skin in each view. A view of a sequence's first frame (or the first after
    :meth:`reset`) whose ring coding alone leaves more than a tenth of its blobs unidentified is coded
    again with the rest pattern as its previous frame: a patch whose reading the design alone cannot
    anchor (half the pattern hidden: the same patch read one lattice step towards the hidden side
    fits the design as well) is then followed from rest, under the frame-to-frame map's own tests,
    which refuse a marker farther from its neighbours' motion than a fifth of a spacing. The rest
    pattern thus fixes a reading by absolute position, which holds as long as the calibration puts
    the markers within a fraction of a separation of where they are (it has to for triangulation).
    It also stands as the frame before the first one when the second is coded: the first frame's
    motion from rest is the markers' velocity for the frame-to-frame fit of the motion's change
    (``code_rings(rest_before=True)``). A press from rest bends the pattern's edge, held by the
    clamped rim, away from what its inner neighbours' increment predicts (the twin's narrow sine at
    1 -> 2 mm: an outer-ring pin 0.18 spacings off), while the increment's change from the first
    frame's motion is still affine there.
    """

    def __init__(self, design: SensorDesign, *, temporal: bool = True,
                 rest: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.design = design
        self.temporal = temporal
        self.rest = None
        if rest is not None:
            ids = np.arange(_marker_count(design), dtype=np.int64)
            self.rest = [(np.asarray(r, np.float64).reshape(-1, 2), ids) for r in rest]
            if any(len(xy) != len(ids) for xy, _ in self.rest):
                raise ValueError(f"DTRCTracker: rest positions must give all {len(ids)} markers in each view")
        self.last_codings: tuple[RingCoding, RingCoding] | None = None
        self.read_from_rest = False       # whether the latest frame's ids came from the rest pattern
        self._previous: list | None = None
        self._before: list | None = None
        self._older: list = []        # per earlier frame (most recent first): [(xy, ids) left, (xy, ids) right]
        self._lost: list = [_NONE] * 2  # per view: where the latest frame's unidentified markers were carried
        self._frames = 0              # frames committed since the start (or the last reset)

    def code_view(self, view: int, blobs: Blobs) -> tuple[RingCoding, bool]:
        """One view's coding (``view`` 0 = left, 1 = right) and whether it was read from the rest pattern.

        Reads only what earlier frames left (the tracker's state is changed by :meth:`commit` alone), so
        the two views of a frame may be coded at once on two threads
        (:func:`pipeline.threads.both_views`)."""
        prev = self._previous[view] if self.temporal and self._previous is not None else None
        hist, rest_before = None, False
        if prev is not None:
            # the previous frame again, with where its lost markers were carried (only those may be
            # re-acquired from it), then the frames before it
            (xy, ids), (vxy, vids) = prev, self._lost[view]
            hist = [(np.vstack([xy, vxy]), np.concatenate([ids, vids]),
                     np.r_[np.zeros(len(ids), bool), np.ones(len(vids), bool)])]
            rest_before = self._frames == 1 and self.rest is not None
            prev = (*prev, *(self.rest[view] if rest_before else self._before[view]))
            hist += [frame[view] for frame in [self._before, *self._older]]
        coding = code_rings(blobs, self.design, previous=prev, history=hist, rest_before=rest_before)
        if prev is None and self.rest is not None:
            again = read_from_rest(blobs, self.design, coding, self.rest[view])
            return again, again is not coding
        return coding, False

    def commit(self, left: Blobs, right: Blobs, codings: tuple[tuple[RingCoding, bool], tuple[RingCoding, bool]]
               ) -> MarkerMatches:
        """Take the frame's two view codings (from :meth:`code_view`) as the latest and pair them."""
        (lc, lrest), (rc, rrest) = codings
        self.read_from_rest = lrest or rrest
        self.last_codings = (lc, rc)
        self.advance([(b.xy_px[c.carried >= 0], c.carried[c.carried >= 0]) for b, c in ((left, lc), (right, rc))])
        return _pair(left, right, lc, rc, _marker_count(self.design))

    @property
    def certified(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per view, (pixels, ids) of the markers the latest frame certified: what :meth:`advance` took."""
        return self._previous if self._previous is not None else [_NONE] * 2

    def advance(self, certified: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """The part of :meth:`commit` that the next frame's :meth:`code_view` reads: ``certified`` per view
        (pixels (n, 2), ids (n,)) become the latest frame, the one before it the frame before, and the lost
        markers' places are carried on. A tracker that codes one view for another's (a worker process) follows
        it with the other's :attr:`certified` alone."""
        two_back = self._before if self._before is not None else [_NONE] * 2   # certified in the frame before the latest
        if self._before is not None and len(self._before[0][1]) + len(self._before[1][1]):
            self._older = [self._before, *self._older][:REACQUIRE_FRAMES - 1]
        self._before = self._previous if self._previous is not None else [_NONE] * 2
        if self.temporal:
            lat = lattice_of(self.design)
            was = ([(np.vstack([p[0], q[0]]), np.concatenate([p[1], q[1]])) for p, q in zip(self._previous, self._lost)]
                   if self._previous is not None else [_NONE] * 2)
            # velocities against certified places only: the velocity between two carried places (two estimates)
            # once extrapolated a lost marker's place 0.37 local spacings off, onto a spurious blob that the
            # next frame's re-acquisition then took (hexagon217_sep180, pi/5 sine, 5 mm)
            self._lost = [carry_lost(w, c, lat.xy, lat.nbr, b) for w, c, b in zip(was, certified, two_back)]
        self._previous = certified
        self._frames += 1

    def update(self, left: Blobs, right: Blobs) -> MarkerMatches:
        return self.commit(left, right, (self.code_view(0, left), self.code_view(1, right)))

    __call__ = update

    def forget(self, ids: np.ndarray) -> None:
        """Drop ``ids`` from the markers the next frame is given as certain in the previous one: a
        pair of views whose rays do not meet (the runner's stereo check) is not one marker, so at
        least one view's id is wrong and must not be carried on."""
        if self._previous is None or len(ids) == 0:
            return
        self._previous = [(xy[~np.isin(i, ids)], i[~np.isin(i, ids)]) for xy, i in self._previous]

    def reset(self) -> None:
        self.last_codings = None
        self._frames = 0
        self._lost = [_NONE] * 2
        self._previous = None
        self._before = None
        self._older = []


class NearestNeighbourTracker:
    """The paper's KNN baseline: ids carried from the previous frame to the nearest blob.

    The first frame (or after :meth:`reset`) is coded by DTRC. Afterwards each view independently
    moves every id to the nearest current blob within ``gate_factor`` x the median marker pitch of
    the first frame; when two ids claim one blob the closer keeps it, the other becomes unmatched.
    """

    def __init__(self, design: SensorDesign, *, gate_factor: float = 1.0) -> None:
        self.design = design
        self.gate_factor = float(gate_factor)
        self._prev: list[dict[int, np.ndarray]] | None = None
        self._gate = [math.inf, math.inf]

    def reset(self) -> None:
        self._prev = None

    def _carry(self, view: int, blobs: Blobs) -> dict[int, np.ndarray]:
        prev = self._prev[view]
        if not prev or len(blobs) == 0:
            return {}
        pid = np.fromiter(prev.keys(), np.int64)
        ppx = np.asarray([prev[i] for i in pid])
        d, j = cKDTree(blobs.xy_px).query(ppx)
        ok = d <= self._gate[view]
        out: dict[int, np.ndarray] = {}
        best: dict[int, tuple[float, int]] = {}
        for i, dd, jj, k in zip(pid, d, j, ok):
            if k and (jj not in best or dd < best[jj][0]):
                best[int(jj)] = (float(dd), int(i))
        for jj, (_, i) in best.items():
            out[i] = blobs.xy_px[jj]
        return out

    def update(self, left: Blobs, right: Blobs) -> MarkerMatches:
        n = self.design.marker_count
        if self._prev is None:
            lc, rc = code_rings(left, self.design), code_rings(right, self.design)
            views = []
            for v, (b, c) in enumerate(((left, lc), (right, rc))):
                ok = c.ids >= 0
                views.append({int(i): b.xy_px[k] for i, k in zip(c.ids[ok], np.nonzero(ok)[0])})
                if len(b) >= 2:
                    nn, _ = cKDTree(b.xy_px).query(b.xy_px, k=2)
                    self._gate[v] = self.gate_factor * float(np.median(nn[:, 1]))
        else:
            views = [self._carry(0, left), self._carry(1, right)]
        self._prev = views
        common = sorted(set(views[0]) & set(views[1]))
        ids = np.asarray(common, np.int64)
        lp = np.asarray([views[0][i] for i in common]).reshape(-1, 2)
        rp = np.asarray([views[1][i] for i in common]).reshape(-1, 2)
        return MarkerMatches(ids, lp, rp, np.setdiff1d(np.arange(n, dtype=np.int64), ids))

    __call__ = update
