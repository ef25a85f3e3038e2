"""numpy's float arithmetic order in compiled kernels: float ranges as ``np.arange`` fills them and sums in the
pairwise order of ``ndarray.sum``, so that a kernel replacing numpy code gives its numbers bit for bit (detection
compares floats against thresholds: a last-bit difference can move a blob). Tested against numpy in
tests/test_detection_kernels.py."""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["arange", "float_sum", "median"]


@numba.njit(cache=True, nogil=True)
def arange(start, stop, step):
    """``np.arange(start, stop, step)`` for floats, value for value: length ceil((stop - start) / step), the
    second value start + step and each further one start + i ((start + step) - start), as numpy fills it."""
    n = int(math.ceil((stop - start) / step))
    out = np.empty(max(n, 0))
    if n > 0:
        out[0] = start
    if n > 1:
        out[1] = start + step
        delta = out[1] - out[0]
        for i in range(2, n):
            out[i] = start + i * delta
    return out


@numba.njit(cache=True, nogil=True)
def _block(a, lo, n):
    """numpy's pairwise sum of ``a[lo:lo + n]`` for n <= 128: sequential below eight values, else eight
    accumulators combined in pairs, then the remainder."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r = a[lo:lo + 8].copy()
    i = 8
    while i < n - n % 8:
        for k in range(8):
            r[k] += a[lo + i + k]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@numba.njit(cache=True, nogil=True)
def _pairwise(a, lo, n):
    """Sum of ``a[lo:lo + n]`` in numpy's pairwise order: halves (the first a multiple of eight long) summed
    separately down to blocks of at most 128 values. Evaluated with an explicit stack (numba's cache does not
    keep recursive functions reliably)."""
    s_lo = np.empty(64, np.int64)
    s_n = np.empty(64, np.int64)
    s_st = np.zeros(64, np.int64)
    vals = np.empty(64)
    top, nv = 1, 0
    s_lo[0], s_n[0], s_st[0] = lo, n, 0
    while top > 0:
        lo_, n_ = s_lo[top - 1], s_n[top - 1]
        if n_ <= 128:
            vals[nv] = _block(a, lo_, n_)
            nv += 1
            top -= 1
            continue
        n2 = n_ // 2
        n2 -= n2 % 8
        if s_st[top - 1] == 0:
            s_st[top - 1] = 1
            s_lo[top], s_n[top], s_st[top] = lo_, n2, 0
            top += 1
        elif s_st[top - 1] == 1:
            s_st[top - 1] = 2
            s_lo[top], s_n[top], s_st[top] = lo_ + n2, n_ - n2, 0
            top += 1
        else:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
            top -= 1
    return vals[0]


@numba.njit(cache=True, nogil=True)
def float_sum(a):
    """``a.sum()`` of a 1-D float64 array, bit for bit (numpy adds the pairwise sum to its identity, 0.0)."""
    return 0.0 + _pairwise(a, 0, len(a))


@numba.njit(cache=True, nogil=True)
def median(a):
    """``np.median`` of a 1-D float64 array, the same value bit for bit (middle sample, or the two
    middle samples' sum halved), NaN when empty or when any sample is NaN; without numpy's per-call
    overhead, which is most of the cost for the few hundred blobs of a view."""
    n = len(a)
    if n == 0:
        return np.nan
    s = np.sort(a)
    if np.isnan(s[n - 1]):
        return np.nan
    m = n // 2
    if n % 2 == 1:
        return s[m]
    return (s[m - 1] + s[m]) / 2.0
