"""A compiled k-d tree that returns exactly what ``scipy.spatial.cKDTree`` returns, ties included.

:mod:`pipeline.vision.dtrc` predicts design slots from local affine fits to the k nearest coded DESIGN
points. Design lattices tie exactly (a quarter of the hexagon slots have two design points at the
same float distance around the 8th neighbour), and which tied point enters the fit changes the
prediction far beyond rounding. Its numpy definition took the neighbours from cKDTree, so these
kernels reproduce cKDTree step for step: leafsize 16, median splits by libstdc++'s ``nth_element`` and
``partition``, compact boxes; a best-first query with its two binary heaps, a point replacing the
farthest neighbour only when strictly nearer. Checked against cKDTree on tie-heavy inputs
(tests/test_dtrc.py): same indices in the same order, bit-identical distances.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["kd_build", "kd_query"]

_KD_LEAFSIZE = 16  # cKDTree's default


@numba.njit(cache=True)
def _kd_partition(key, idx, first, last, pivot):
    """``std::partition(first, last, key < pivot)`` (libstdc++, bidirectional) on ``idx``; returns the
    first position of the second group."""
    while True:
        while True:
            if first == last:
                return first
            if key[idx[first]] < pivot:
                first += 1
            else:
                break
        last -= 1
        while True:
            if first == last:
                return first
            if not key[idx[last]] < pivot:
                last -= 1
            else:
                break
        idx[first], idx[last] = idx[last], idx[first]
        first += 1


@numba.njit(cache=True)
def _kd_adjust_heap(key, idx, first, hole, n, value):
    """libstdc++ ``__adjust_heap`` + ``__push_heap`` (max-heap by ``key``) on ``idx[first:first + n]``."""
    top = hole
    child = hole
    while child < (n - 1) // 2:
        child = 2 * (child + 1)
        if key[idx[first + child]] < key[idx[first + child - 1]]:
            child -= 1
        idx[first + hole] = idx[first + child]
        hole = child
    if (n & 1) == 0 and child == (n - 2) // 2:
        child = 2 * (child + 1)
        idx[first + hole] = idx[first + child - 1]
        hole = child - 1
    parent = (hole - 1) // 2
    while hole > top and key[idx[first + parent]] < key[value]:
        idx[first + hole] = idx[first + parent]
        hole = parent
        parent = (hole - 1) // 2
    idx[first + hole] = value


@numba.njit(cache=True)
def _kd_nth_element(key, idx, first, nth, last):
    """``std::nth_element`` (libstdc++ introselect) on ``idx`` ordered by ``key``."""
    if first == last or nth == last:
        return
    depth = 0
    while (last - first) >> (depth + 1):
        depth += 1
    depth *= 2  # 2 floor(log2(n))
    while last - first > 3:
        if depth == 0:  # heap select (introselect's fallback; a max-heap of the nth + 1 smallest)
            middle = nth + 1
            n = middle - first
            if n >= 2:
                parent = (n - 2) // 2
                while True:
                    _kd_adjust_heap(key, idx, first, parent, n, idx[first + parent])
                    if parent == 0:
                        break
                    parent -= 1
            for i in range(middle, last):
                if key[idx[i]] < key[idx[first]]:
                    value = idx[i]
                    idx[i] = idx[first]
                    _kd_adjust_heap(key, idx, first, 0, n, value)
            idx[first], idx[nth] = idx[nth], idx[first]
            return
        depth -= 1
        # median of (first + 1, mid, last - 1) moved to first, then unguarded partition about it
        a, b, c = first + 1, first + (last - first) // 2, last - 1
        ka, kb, kc = key[idx[a]], key[idx[b]], key[idx[c]]
        if ka < kb:
            s = b if kb < kc else (c if ka < kc else a)
        else:
            s = a if ka < kc else (c if kb < kc else b)
        idx[first], idx[s] = idx[s], idx[first]
        pv = key[idx[first]]
        lo, hi = first + 1, last
        while True:
            while key[idx[lo]] < pv:
                lo += 1
            hi -= 1
            while pv < key[idx[hi]]:
                hi -= 1
            if not lo < hi:
                break
            idx[lo], idx[hi] = idx[hi], idx[lo]
            lo += 1
        if lo <= nth:
            first = lo
        else:
            last = lo
    # insertion sort
    for i in range(first + 1, last):
        v = idx[i]
        if key[v] < key[idx[first]]:
            for j in range(i, first, -1):
                idx[j] = idx[j - 1]
            idx[first] = v
        else:
            j = i
            while key[v] < key[idx[j - 1]]:
                idx[j] = idx[j - 1]
                j -= 1
            idx[j] = v


@numba.njit(cache=True)
def kd_build(data):
    """``cKDTree(data)`` (2-D, defaults): (permuted indices, per node: split dim (-1 = leaf), split
    value, start, end, less child, greater child; the data's bounding box lo (2,), hi (2,); work
    arrays for :func:`_kd_query`)."""
    n = len(data)
    idx = np.arange(n)
    cap = 2 * n + 1
    sdim = np.full(cap, -1, np.int64)
    split = np.zeros(cap)
    start = np.zeros(cap, np.int64)
    end = np.zeros(cap, np.int64)
    less = np.full(cap, -1, np.int64)
    greater = np.full(cap, -1, np.int64)
    end[0] = n
    count = 1
    stack = [0]
    while len(stack):
        nd = stack.pop()
        s, e = start[nd], end[nd]
        if e - s <= _KD_LEAFSIZE:
            continue
        # compact box, split dimension = first of largest spread
        mn0 = mx0 = data[idx[s], 0]
        mn1 = mx1 = data[idx[s], 1]
        for j in range(s + 1, e):
            x, y = data[idx[j], 0], data[idx[j], 1]
            mx0 = mx0 if mx0 > x else x
            mn0 = mn0 if mn0 < x else x
            mx1 = mx1 if mx1 > y else y
            mn1 = mn1 if mn1 < y else y
        d = 0
        if mx0 - mn0 > 0.0:
            d, size = 0, mx0 - mn0
        else:
            size = 0.0
        if mx1 - mn1 > size:
            d = 1
        if (mx0 if d == 0 else mx1) == (mn0 if d == 0 else mn1):
            continue  # all points identical: leaf
        key = data[:, d]
        mid = s + (e - s) // 2
        _kd_nth_element(key, idx, s, mid, e)
        sp = key[idx[mid]]
        p = _kd_partition(key, idx, s, mid, sp)
        if p == s:  # no point below the median: slide the split just above the minimum
            mi = s
            for j in range(s + 1, e):
                if key[idx[j]] < key[idx[mi]]:
                    mi = j
            sp = np.nextafter(key[idx[mi]], np.inf)
            p = _kd_partition(key, idx, s, e, sp)
        sdim[nd], split[nd] = d, sp
        less[nd], greater[nd] = count, count + 1
        start[count], end[count], start[count + 1], end[count + 1] = s, p, p, e
        count += 2
        stack.append(count - 1)
        stack.append(count - 2)
    lo = np.array([data[:, 0].min(), data[:, 1].min()])
    hi = np.array([data[:, 0].max(), data[:, 1].max()])
    # query work space (node infos, node queue, neighbour heap), allocated once per tree
    m = 2 * count + 1
    work = (np.empty(m, np.int64), np.empty(m), np.empty((m, 2)), np.empty(m), np.empty(m, np.int64),
            np.empty(n + 1), np.empty(n + 1, np.int64))
    return idx, sdim, split, start, end, less, greater, lo, hi, work


@numba.njit(cache=True)
def _heap_push(pri, con, n, p, c):
    """cKDTree's binary min-heap: push (priority p, content c) onto the first n items; returns n + 1."""
    i = n
    pri[i], con[i] = p, c
    while i > 0 and pri[i] < pri[(i - 1) // 2]:
        h = (i - 1) // 2
        pri[i], pri[h] = pri[h], pri[i]
        con[i], con[h] = con[h], con[i]
        i = h
    return n + 1


@numba.njit(cache=True)
def _heap_remove(pri, con, n):
    """cKDTree's heap ``remove`` (drop the top); returns n - 1."""
    pri[0], con[0] = pri[n - 1], con[n - 1]
    n -= 1
    i, j, k = 0, 1, 2
    while (j < n and pri[i] > pri[j]) or (k < n and pri[i] > pri[k]):
        l = k if (k < n and pri[j] > pri[k]) else j
        pri[i], pri[l] = pri[l], pri[i]
        con[i], con[l] = con[l], con[i]
        i, j, k = l, 2 * l + 1, 2 * l + 2
    return n


@numba.njit(cache=True)
def kd_query(data, tree, x0, x1, k, out_idx, out_d2):
    """``cKDTree(data).query((x0, x1), k)`` into ``out_idx`` / ``out_d2`` (squared distances), nearest
    first; ``tree`` from :func:`_kd_build`, ``k <= len(data)``."""
    idx, sdim, split, start, end, less, greater, box_lo, box_hi, work = tree
    # node infos (node, min distance, side distances), the node queue and the neighbour heap
    ni_node, ni_min, ni_side, q_pri, q_con, nb_pri, nb_con = work
    nq = 0
    nnb = 0
    ni1 = 0
    n_ni = 1
    ni_node[0] = 0
    ni_min[0] = 0.0
    x = (x0, x1)
    for i in range(2):
        s = 0.0
        t = x[i] - box_hi[i]
        if t > s:
            s = t
        else:
            t = box_lo[i] - x[i]
            if t > s:
                s = t
        s = s * s
        ni_side[0, i] = 0.0
        ni_min[0] += s - ni_side[0, i]
        ni_side[0, i] = s
    bound = np.inf
    while True:
        nd = ni_node[ni1]
        if sdim[nd] == -1:
            for i in range(start[nd], end[nd]):
                dx = data[idx[i], 0] - x0
                dy = data[idx[i], 1] - x1
                d = dx * dx + dy * dy
                if d < bound:  # replace the farthest neighbour
                    if nnb == k:
                        nnb = _heap_remove(nb_pri, nb_con, nnb)
                    nnb = _heap_push(nb_pri, nb_con, nnb, -d, idx[i])
                    if nnb == k:
                        bound = -nb_pri[0]
            if nq == 0:
                break
            ni1 = q_con[0]
            nq = _heap_remove(q_pri, q_con, nq)
        else:
            if ni_min[ni1] > bound:
                break
            sd, spv = sdim[nd], split[nd]
            ni2 = n_ni
            n_ni += 1
            ni_side[ni2, 0], ni_side[ni2, 1], ni_min[ni2] = ni_side[ni1, 0], ni_side[ni1, 1], ni_min[ni1]
            if x[sd] < spv:
                ni_node[ni1], ni_node[ni2] = less[nd], greater[nd]
                side = spv - x[sd]
            else:
                ni_node[ni1], ni_node[ni2] = greater[nd], less[nd]
                side = x[sd] - spv
            side = side * side
            ni_min[ni2] += side - ni_side[ni2, sd]
            ni_side[ni2, sd] = side
            if ni_min[ni1] > ni_min[ni2]:
                ni1, ni2 = ni2, ni1
            if ni_min[ni2] <= bound:
                nq = _heap_push(q_pri, q_con, nq, ni_min[ni2], ni2)
    for i in range(nnb - 1, -1, -1):  # heap sort: farthest popped first
        out_idx[i], out_d2[i] = nb_con[0], -nb_pri[0]
        nnb = _heap_remove(nb_pri, nb_con, nnb)
