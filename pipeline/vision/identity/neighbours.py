"""The adjacency of the Delaunay triangulation of the frame being identified, which ring coding
computed (:func:`use_triangulation`), kept for the very arrays of that frame. (Blob searches need no
structure: :func:`pipeline.vision.nearest.nearest` scans the few hundred blob centres.)"""

from __future__ import annotations

import threading

import numba
import numpy as np


#: Per thread: the two camera views of a frame are identified at once on two threads
#: (:func:`pipeline.threads.both_views`), each with its own triangulation.
_LOCAL = threading.local()
_NO_ADJ = (np.zeros(1, np.int64), np.zeros(0, np.int64))


def use_triangulation(pts: np.ndarray, simplices: np.ndarray | None) -> None:
    """Register the Delaunay triangles (M, 3) of the blob centres ``pts`` (the very array later
    passed to :func:`certify`), which ring coding has computed anyway: a blob whose Delaunay
    neighbours are exactly its design fan has an empty fan without a neighbour search. ``None``
    forgets the registered triangles (the emptiness test then searches)."""
    _LOCAL.mesh = None
    if simplices is not None and len(simplices):
        _LOCAL.mesh = (pts, _adjacency(np.ascontiguousarray(simplices, dtype=np.int64), len(pts)))


def _adj(pts: np.ndarray):
    hit = getattr(_LOCAL, "mesh", None)
    if hit is not None and hit[0] is pts:
        return hit[1]
    return (np.zeros(len(pts) + 1, np.int64), _NO_ADJ[1])


@numba.njit(cache=True, nogil=True)
def _adjacency(simp, n):
    """Neighbour lists (CSR: ``ptr`` (n+1,), ``idx``) of the vertices of triangles ``simp``."""
    cnt = np.zeros(n + 1, np.int64)
    for t in range(len(simp)):
        for k in range(3):
            cnt[simp[t, k] + 1] += 2
    ptr = np.cumsum(cnt)
    raw = np.empty(ptr[-1], np.int64)
    fill = ptr[:-1].copy()
    for t in range(len(simp)):
        for k in range(3):
            a = simp[t, k]
            raw[fill[a]] = simp[t, (k + 1) % 3]
            raw[fill[a] + 1] = simp[t, (k + 2) % 3]
            fill[a] += 2
    out_ptr = np.zeros(n + 1, np.int64)
    out = np.empty(ptr[-1], np.int64)
    w = 0
    for a in range(n):
        out_ptr[a] = w
        for q in range(ptr[a], ptr[a + 1]):
            v = raw[q]
            dup = False
            for r in range(out_ptr[a], w):
                if out[r] == v:
                    dup = True
                    break
            if not dup:
                out[w] = v
                w += 1
    out_ptr[n] = w
    return out_ptr, out[:w]
