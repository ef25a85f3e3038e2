"""Outer rows read step by step, where the certainty rule has nothing to fit.

An occluded patch that reaches the edge of a hexagonal or square pattern can leave the outer ring beyond
it joined to the rest only as a strip one marker wide. The certainty rule tests each marker against an
affine map of its identified design neighbours in two directions; a marker on such a strip has identified
neighbours along the strip only, so the rule has no map to test it against, and growth predicts no
position for it: the strip stays unread although every one of its markers is in view (the corner of a
square pattern beyond a patch in its quadrant, whose own neighbourhood is complete).

Along a straight row of the lattice one step of the skin's map is the step before it: the skin is
smooth over a marker separation, and its map's change from one step to the next is a small fraction of
a step. So a free outer-ring slot whose three predecessors along one lattice line through it are
identified, evenly spaced in the view (their two steps agree in length and direction within
:data:`ROW_STEP_SPREAD` and :data:`ROW_TURN_DEG`), is predicted one step on, and takes the nearest blob
when it lies within :data:`ROW_GATE` of that step, no other blob is nearly as near (twice as far and
:data:`~pipeline.vision.identity.constants.AMBIGUITY_MARGIN` steps farther), no identified marker holds
it, and no other row proposes another blob for the slot or this blob for another slot. Only slots the
rule cannot decide are read so: those growth cannot predict (fewer than three identified neighbours off one
line within the slot's neighbourhood), and those the consistency test refused only for want of identified
neighbours (the ends of the strip, beside the rest). Where the rule has a map and a verdict from it (no blob
near its prediction, two blobs, a blob inconsistent with its neighbours), that verdict stands. The step is
repeated along the row, so the strip is read from each end inwards.

It can be wrong where the slot's own marker is missing and another blob stands within a fifth of a step
of where the row continues: the case growth cannot tell from the marker displaced either (the
identification benchmark draws no spurious blob there). Where rows crowd (a crest pressed into the skin
near the rim), the steps before the slot shrink, and the row is not extended across it.
"""

from __future__ import annotations

import numpy as np

from pipeline.vision.identity.certify import _predict_free
from pipeline.vision.identity.consistency import _blob_of
from pipeline.vision.identity.constants import AMBIGUITY_MARGIN, LATTICE_STEP, R_FEW
from pipeline.vision.identity.lattice import Lattice
from pipeline.vision.nearest import knn

__all__ = ["ROW_GATE", "ROW_STEP_SPREAD", "ROW_TURN_DEG", "row_chains", "extend_rows"]

#: Largest distance of the blob from the row's next step, as a fraction of the step.
ROW_GATE = 0.2
#: The two steps before the slot must agree in length to this fraction of the longer ...
ROW_STEP_SPREAD = 0.1
#: ... and in direction to this many degrees.
ROW_TURN_DEG = 10.0
#: Slots within this fraction of a pitch of a lattice site count as that site.
_SITE = 0.1

_CHAINS: dict = {}


def row_chains(lat: Lattice) -> np.ndarray:
    """(C, 4) slots (s, a, b, c): ``s`` an outer-ring slot of a translation lattice and ``a``, ``b``, ``c``
    the design slots one, two and three lattice steps before it along one lattice line (empty for
    circular patterns)."""
    key = id(lat)
    if key in _CHAINS:
        return _CHAINS[key]
    out = []
    if lat.translation_lattice:
        from scipy.spatial import cKDTree

        tree = cKDTree(lat.xy)
        offsets = []
        for s in range(len(lat.xy)):             # the lattice's steps: the immediate neighbours' offsets
            nb = lat.nbr[s][lat.nbr[s] >= 0]
            d = lat.xy[nb] - lat.xy[s]
            offsets.append(d[np.hypot(*d.T) <= LATTICE_STEP * lat.pitch])
        offsets = np.vstack(offsets)
        _, first = np.unique(np.round(offsets / (_SITE * lat.pitch)).astype(np.int64), axis=0, return_index=True)
        steps = offsets[first]
        for s in lat.outer_ring:
            for v in steps:
                d, j = tree.query(lat.xy[s] - np.outer(np.arange(1, 4), v))
                if np.all(d <= _SITE * lat.pitch):
                    out.append((s, *j.tolist()))
    chains = np.asarray(out, np.int64).reshape(-1, 4)
    _CHAINS[key] = chains
    return chains


def extend_rows(pts: np.ndarray, ids: np.ndarray, lat: Lattice, reason: np.ndarray) -> np.ndarray:
    """``ids`` (id per blob) with the free outer-ring slots the rule cannot predict read along their rows
    (see the module notes); ``reason`` is cleared for each slot read. Returns a new array (``ids`` itself
    where nothing is added)."""
    chains = row_chains(lat)
    if len(chains) == 0 or len(pts) < 3 or not (ids >= 0).any():
        return ids
    # where the rule's growth has a prediction, its verdict stands, unless that verdict is only that too few
    # neighbours were identified to test the marker (a slot at the end of the strip)
    _, scale = _predict_free(pts, _blob_of(ids, len(lat.xy)), lat.xy, lat.nbr2, lat.pitch)
    chains = chains[(scale[chains[:, 0]] == 0) | (reason[chains[:, 0]] == R_FEW)]
    out = ids
    for _ in range(len(lat.outer_ring)):
        blob_of = _blob_of(out, len(lat.xy))
        c = chains[(blob_of[chains[:, 0]] < 0) & (blob_of[chains[:, 1:]] >= 0).all(axis=1)]
        if len(c) == 0:
            break
        x1, x2, x3 = pts[blob_of[c[:, 1]]], pts[blob_of[c[:, 2]]], pts[blob_of[c[:, 3]]]
        st1, st2 = x1 - x2, x2 - x3
        l1, l2 = np.hypot(*st1.T), np.hypot(*st2.T)
        cos = np.einsum("ij,ij->i", st1, st2) / np.maximum(l1 * l2, 1e-12)
        even = (np.abs(l1 - l2) <= ROW_STEP_SPREAD * np.maximum(l1, l2)) & (cos >= np.cos(np.radians(ROW_TURN_DEG)))
        c, x1, st1, l1 = c[even], x1[even], st1[even], l1[even]
        if len(c) == 0:
            break
        d, j = knn(pts, x1 + st1, 2)
        ok = ((d[:, 0] <= ROW_GATE * l1) & (d[:, 1] >= 2 * d[:, 0]) & (d[:, 1] - d[:, 0] >= AMBIGUITY_MARGIN * l1)
              & (out[j[:, 0]] < 0))
        slot, blob = c[ok, 0], j[ok, 0]
        # a slot proposed two blobs, or a blob proposed for two slots, is read by none
        pairs = np.unique(np.column_stack([slot, blob]), axis=0)
        s_u, s_n = np.unique(pairs[:, 0], return_counts=True)
        b_u, b_n = np.unique(pairs[:, 1], return_counts=True)
        keep = np.isin(pairs[:, 0], s_u[s_n == 1]) & np.isin(pairs[:, 1], b_u[b_n == 1])
        pairs = pairs[keep]
        if len(pairs) == 0:
            break
        out = out.copy() if out is ids else out
        out[pairs[:, 1]] = pairs[:, 0]
        reason[pairs[:, 0]] = 0
    return out
