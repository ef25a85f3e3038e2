"""Whether a marker next to lost design neighbours can have shared its blob with one of them.

A marker one of whose immediate design neighbours was not followed into the previous frame may have
merged with that neighbour into one blob (pins crowded until the detector no longer separated them),
so the frame-to-frame map gives it a tighter gate (:data:`pipeline.vision.identity.temporal.F2F_GATE_ALONE`),
unless each such neighbour has a blob of its own now, where the marker's neighbourhood puts it. Shared by
the frame-to-frame map and re-acquisition (:mod:`pipeline.vision.identity.reacquire`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: A lost neighbour stands apart from the marker when it has a blob of its own within this many local
#: spacings of where the marker's neighbourhood puts it (:func:`lost_neighbours_apart`): a neighbour whose
#: blob was missing from the previous frame (glare, a worn marker, a spurious blob beside it) and is back
#: cannot share the marker's blob.
F2F_APART = 0.3


def lost_neighbours_apart(P, prev_ids, pred, jac, which, known, design_nbr, design_xy, tree, s_prev) -> np.ndarray:
    """Markers (of ``which``) whose immediate design neighbours missing from the previous frame each have a
    blob of their own now, so that none of them can have merged with the marker into one blob (the case
    :data:`~pipeline.vision.identity.temporal.F2F_GATE_ALONE` guards): the neighbour's previous position is
    put where the design-to-image map of the marker's known neighbours (a linear map of design offsets, fitted to at least two, spread in two
    directions) places it beside the marker, moved on by the marker's frame-to-frame map (Jacobian
    ``jac``); its nearest blob now must be another than the marker's predicted one and within
    :data:`F2F_APART` local spacings of that place. A neighbour without such a blob (missing now too, or
    crowded onto the marker) leaves the marker at the tight gate."""
    out = np.zeros(len(P), bool)
    row = np.full(len(known), -1, np.int64)
    row[prev_ids] = np.arange(len(prev_ids))
    for i in np.flatnonzero(which):
        me = prev_ids[i]
        nbrs = design_nbr[me][design_nbr[me] >= 0]
        have, missing = nbrs[known[nbrs]], nbrs[~known[nbrs]]
        if len(have) < 2 or len(missing) == 0:
            continue
        dD = design_xy[have] - design_xy[me]
        if np.linalg.matrix_rank(dD, tol=1e-6 * float(np.abs(dD).max())) < 2:
            continue
        A = np.linalg.lstsq(dD, P[row[have]] - P[i], rcond=None)[0]        # design offset -> previous image
        J = jac[i].reshape(2, 2)
        q = pred[i] + ((design_xy[missing] - design_xy[me]) @ A) @ J.T        # the neighbours now
        out[i] = stand_apart(tree, q, pred[i], s_prev[i])
    return out


def stand_apart(tree: cKDTree, places: np.ndarray, pred: np.ndarray, spacing: float) -> bool:
    """Whether each of ``places`` (k, 2), where a marker's lost neighbours are put now, has a blob of its own
    within :data:`F2F_APART` local spacings (``spacing``, px) that is not the marker's nearest blob to its
    prediction ``pred`` (2,)."""
    d, j = tree.query(places)
    return bool(np.all((j != tree.query(pred)[1]) & (d <= F2F_APART * spacing)))
