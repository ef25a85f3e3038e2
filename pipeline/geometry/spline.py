"""The smoothing thin-plate spline the skin surface is fitted with, and its compiled kernels.

A frame's spline system is built in per-thread buffers reused frame after frame, factorised by LAPACK's
getrf, and in a stream solved by iterative refinement on the kept factorisation of an earlier frame's
system (:data:`REFINE_RTOL`); the gradient at the centres, from which the skin normals come, is exact.
"""

from __future__ import annotations

import math
import threading

import numba
import numpy as np
import scipy.linalg

__all__ = ["ThinPlateSpline", "SMOOTHING", "REFINE_RTOL", "REFINE_STEPS"]

# Thin-plate-spline smoothing (added to the kernel diagonal as scipy's RBFInterpolator does; mm^2 of z): 1e-3 leaves exact
# data interpolated to ~1 um yet keeps the normals stable under ~0.01 mm triangulation noise.
SMOOTHING = 1e-3
_GETRF, _GETRS = scipy.linalg.get_lapack_funcs(("getrf", "getrs"), (np.empty((2, 2)),))   # float64: dgetrf, dgetrs
# A frame's spline system is solved by iterative refinement on the factorisation of an earlier frame's system
# of the same size (:meth:`_Scratch.refined`), and factorised afresh only where that does not reach a residual
# |b - A x| <= REFINE_RTOL (|A| |x| + |b|) (infinity norms) within REFINE_STEPS corrections. Measured on the
# latency benchmark's circular217_dome press sequence (0-3 mm in 20 frames, and the 3 -> 0 mm jump): each
# correction gains 1-1.5 decades; the direct solve's own residual is ~5e-20 on this scale, 1e-15 is reached
# in 5-6 corrections, and the skin points then differ from the direct solve's by ~1e-10 mm (1e-17: 7-8
# corrections, ~1e-11 mm). A correction costs two triangular solves and a product (~0.02 ms for 217 markers)
# against ~0.3 ms for the factorisation; the press sequence is factorised again every ~10 frames.
REFINE_RTOL = 1e-15
REFINE_STEPS = 10


@numba.njit(cache=True, nogil=True)
def _pairwise_r2(xy, out):
    """``out`` (N, N) = r_ij^2, and 1 where that is 0 (the diagonal, duplicated points): its logarithm is
    then 0 there, which :func:`_tps_fill` needs."""
    n = len(xy)
    for i in range(n):
        xi, yi = xy[i, 0], xy[i, 1]
        row = out[i]
        for j in range(n):
            dx, dy = xi - xy[j, 0], yi - xy[j, 1]
            r2 = dx * dx + dy * dy
            row[j] = r2 if r2 > 0 else 1.0


@numba.njit(cache=True, nogil=True)
def _tps_fill(xy, log_r2, tail, smoothing, lhs):
    """Fill the (N + 3)^2 spline system ``[[K + s I, P], [P^T, 0]]`` (K_ij = r^2 log r = r_ij^2 log(r_ij^2)
    / 2, P = ``tail``) from the pairwise ``log_r2``, row by row, r_ij^2 computed again alongside (cheaper
    than reading it back from a block of the system: 106 against 112-123 us for circular217's whole system,
    in a loop). Returns the system's infinity norm (largest absolute row sum)."""
    n = len(xy)
    rows = np.zeros(n + 3)
    for i in range(n):
        xi, yi = xy[i, 0], xy[i, 1]
        lg, out = log_r2[i], lhs[i]
        total = 0.0
        for j in range(n):
            dx, dy = xi - xy[j, 0], yi - xy[j, 1]
            k = 0.5 * (dx * dx + dy * dy) * lg[j]               # 0 at r = 0, where log_r2 is 0
            out[j] = k
            total += abs(k)
        out[i] = smoothing
        rows[i] = total + abs(smoothing)
        for c in range(3):
            out[n + c] = tail[i, c]
            lhs[n + c, i] = tail[i, c]
            rows[i] += abs(tail[i, c])
            rows[n + c] += abs(tail[i, c])
    for a in range(3):
        for b in range(3):
            lhs[n + a, n + b] = 0.0
    return rows.max()


def _tps_system(xy, tail, smoothing, lhs, log_r2):
    """The spline system into ``lhs`` and log(r_ij^2) (0 on the diagonal) into ``log_r2``; returns the
    system's infinity norm. The logarithms are numpy's vectorised ones over the whole (N, N) block: a
    compiled loop takes one scalar logarithm per pair, at about twice the cost of the whole system
    (circular217: 0.21 ms against 0.10 ms for the system, measured in a loop; both are symmetric to the
    bit, as the factorisation assumes)."""
    _pairwise_r2(xy, log_r2)
    np.log(log_r2, out=log_r2)
    return _tps_fill(xy, log_r2, tail, float(smoothing), lhs)


@numba.njit(cache=True, nogil=True)
def _tail_rank(tail):
    """The rank of the (N, 3) tail as ``np.linalg.matrix_rank`` reads it (singular values above
    max(N, 3) eps times the largest), from the 3 x 3 factor R of its Householder QR, which has the same
    singular values; a compiled call instead of numpy's SVD of the whole tail (~15 us, far more on a
    frame's cold caches)."""
    m, k = tail.shape
    q = tail.copy()
    for c in range(k):
        norm2 = 0.0
        for i in range(c, m):
            norm2 += q[i, c] * q[i, c]
        norm = math.sqrt(norm2)
        if norm == 0.0:
            continue
        alpha = -norm if q[c, c] >= 0 else norm
        v0 = q[c, c] - alpha
        vv = v0 * v0 + norm2 - q[c, c] * q[c, c]              # |v|^2, v = (q[c, c] - alpha, q[c + 1:, c])
        q[c, c] = v0
        for j in range(c + 1, k):
            d = 0.0
            for i in range(c, m):
                d += q[i, c] * q[i, j]
            f = 2.0 * d / vv
            for i in range(c, m):
                q[i, j] -= f * q[i, c]
        q[c, c] = alpha
        for i in range(c + 1, m):
            q[i, c] = 0.0
    r = np.zeros((k, k))
    for i in range(k):
        for j in range(i, k):
            r[i, j] = q[i, j]
    s = np.linalg.svd(r)[1]
    tol = s.max() * max(m, k) * np.finfo(np.float64).eps
    return int(np.sum(s > tol))


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _tps_gradient_at_centres(xy, log_r2, w, tail_grad):
    """The spline gradient at its own centres: sum_j w_j (x_i - x_j)(log r_ij^2 + 1), plus the linear
    tail's gradient ``tail_grad`` (2,). The sums may be reordered (``reassoc``: vectorised, 3.5x
    faster; a few 1e-15 of the gradient from the in-order sums)."""
    n = len(xy)
    xs, ys = xy[:, 0].copy(), xy[:, 1].copy()
    out = np.empty((n, 2))
    for i in range(n):
        gx = 0.0
        gy = 0.0
        xi, yi, lg = xs[i], ys[i], log_r2[i]
        for j in range(n):
            g = (lg[j] + 1.0) * w[j]
            gx += g * (xi - xs[j])
            gy += g * (yi - ys[j])
        out[i, 0], out[i, 1] = gx + tail_grad[0], gy + tail_grad[1]
    return out


@numba.njit(cache=True, nogil=True)
def _unit_normals(grad):
    """Unit normals (-f_x, -f_y, 1) / |.| from the gradients (N, 2)."""
    out = np.empty((len(grad), 3))
    for i in range(len(grad)):
        inv = 1.0 / math.sqrt(grad[i, 0] * grad[i, 0] + grad[i, 1] * grad[i, 1] + 1.0)
        out[i, 0], out[i, 1], out[i, 2] = -grad[i, 0] * inv, -grad[i, 1] * inv, inv
    return out


@numba.njit(cache=True, nogil=True)
def _residual(lhs, x, rhs, r):
    """``r`` = rhs - lhs x for the symmetric ``lhs`` (row j of it scaled by x_j, row after row: contiguous
    and vectorised); returns (max |r|, max |x|), NaN in the first where x is not finite. One compiled call
    for what took five numpy calls of each refinement step."""
    n = len(x)
    x_norm = 0.0
    finite = True
    for i in range(n):
        r[i] = rhs[i]
        finite &= math.isfinite(x[i])
        x_norm = max(x_norm, abs(x[i]))
    for j in range(n):
        xj, row = x[j], lhs[j]
        for i in range(n):
            r[i] -= row[i] * xj
    res = 0.0
    for i in range(n):
        finite &= math.isfinite(r[i])
        res = max(res, abs(r[i]))
    if not finite:
        res = math.nan
    return res, x_norm


class _Scratch:
    """Per-thread buffers for the spline system and its pairwise logarithms, reused frame after frame.

    The system of a 217-marker sensor is ~390 kB and its logarithms as much again: fresh arrays of
    that size come from the kernel page by page on every frame, and where page faults are slow (2
    shared cores) that cost the skin stage of circular217_dome 1.66 ms against 0.99 ms with the
    buffers kept (one sensor per process, a frame after any other job). Kept per marker count (a
    stream sees a few), at most :data:`_ENTRIES` of them."""

    _ENTRIES = 8
    _local = threading.local()

    @classmethod
    def get(cls, name: str, shape: tuple[int, int]) -> np.ndarray:
        bufs = getattr(cls._local, "bufs", None)
        if bufs is None:
            bufs = cls._local.bufs = {}
        key = (name, shape)
        buf = bufs.get(key)
        if buf is None:
            if len(bufs) >= 2 * cls._ENTRIES:
                bufs.clear()
            buf = bufs[key] = np.empty(shape)
        return buf

    @classmethod
    def system(cls, m: int) -> np.ndarray:
        """An (m, m) buffer for this frame's system: not the one holding the kept factorisation."""
        kept = getattr(cls._local, "factor", None)
        name = "lhs1" if kept is not None and kept[0] is cls.get("lhs0", (m, m)) else "lhs0"
        return cls.get(name, (m, m))

    @classmethod
    def keep_factor(cls, system: np.ndarray, lu: np.ndarray, piv: np.ndarray) -> None:
        """Keep a fresh factorisation (``lu`` overwrote ``system``) for the next frames' refinement."""
        cls._local.factor = (system, lu, piv)

    @classmethod
    def refined(cls, lhs: np.ndarray, rhs: np.ndarray, norm: float) -> np.ndarray | None:
        """Solve ``lhs x = rhs`` by iterative refinement on the kept factorisation of an earlier
        frame's system of the same size (a sensor's markers move little between frames, so that
        factorisation is a close preconditioner): at most :data:`REFINE_STEPS` corrections until the
        residual is at the level of a direct solve's (:data:`REFINE_RTOL`). None where there is no
        such factorisation or it does not get there: the caller factorises this system afresh."""
        kept = getattr(cls._local, "factor", None)
        if kept is None or kept[1].shape != lhs.shape:
            return None
        _, lu, piv = kept
        x, info = _GETRS(lu, piv, rhs)
        r = np.empty_like(rhs)
        b_norm = float(np.abs(rhs).max())
        last = math.inf
        for _ in range(REFINE_STEPS):
            res, x_norm = _residual(lhs, x, rhs, r)
            if info != 0 or not math.isfinite(res):     # a non-finite x gives a non-finite residual
                return None
            if res <= REFINE_RTOL * (norm * x_norm + b_norm):
                return x
            if res >= last:       # not contracting: this system is too far from the kept one
                return None
            last = res
            dx, info = _GETRS(lu, piv, r)
            x += dx
        return None


class ThinPlateSpline:
    """Smoothing thin-plate spline z = f(x, y) with a linear tail, and its analytic gradient.

    The function scipy's ``RBFInterpolator(kernel="thin_plate_spline", degree=1, smoothing=s)`` fits
    (kernel ``phi(r) = r**2 log r``; ``s`` added to the kernel matrix's diagonal; the tail's coordinates
    shifted and scaled to [-1, 1] for conditioning; tests/test_surface.py compares the two), solved
    directly: at the pipeline's sizes (<= a few hundred markers) scipy's general machinery costs more
    than the fit, and the normals needed four extra evaluations per marker for finite differences.
    ``gradient`` is exact, and at the centres it reuses the fit's pairwise logarithms. The system and
    the gradient at the centres are compiled loops over the (N, N) pairs (no temporaries of that size
    but the logarithms, which numpy takes over the whole block: :func:`_tps_system`).
    """

    _CHUNK = 4096  # query points evaluated at a time (bounds the (chunk, N) blocks)

    def __init__(self, xy: np.ndarray, z: np.ndarray, smoothing: float = SMOOTHING, *, scratch: bool = False) -> None:
        """``scratch``: build the system in this thread's reused buffers (:class:`_Scratch`); the
        spline is then valid only until the next ``scratch`` fit on the same thread (for a caller
        that evaluates it at once and drops it, as :func:`skin_surface` does)."""
        xy = np.ascontiguousarray(xy, dtype=np.float64)
        n = len(xy)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        self._shift = 0.5 * (hi + lo)
        self._scale = np.where(hi > lo, 0.5 * (hi - lo), 1.0)
        self.centres = xy
        tail = self._tail(xy)
        if _tail_rank(tail) < 3:
            raise np.linalg.LinAlgError("the points are collinear: the linear tail is not determined")
        if scratch:
            lhs = _Scratch.system(n + 3)
            self._log_r2 = _Scratch.get("log_r2", (n, n))
        else:
            lhs = np.empty((n + 3, n + 3))
            self._log_r2 = np.empty((n, n))
        norm = _tps_system(xy, tail, smoothing, lhs, self._log_r2)
        rhs = np.concatenate([np.asarray(z, dtype=np.float64), np.zeros(3)])
        sol = _Scratch.refined(lhs, rhs, norm) if scratch else None
        if sol is None:
            # symmetric system: its transpose is the Fortran-ordered array LAPACK wants, factorised in place
            # (LAPACK's getrf/getrs called directly: what scipy.linalg.lu_factor / lu_solve call, without
            # their per-call checks and lookups)
            lu, piv, info = _GETRF(lhs.T, overwrite_a=True)
            if info > 0:
                raise np.linalg.LinAlgError(f"Diagonal number {info} is exactly zero. Singular matrix.")
            sol, info = _GETRS(lu, piv, rhs, overwrite_b=True)
            if info != 0:
                raise np.linalg.LinAlgError(f"the spline system could not be solved (LAPACK info {info})")
            if not np.all(np.isfinite(sol)):
                raise np.linalg.LinAlgError("the spline system is singular (duplicated points?)")
            if scratch:
                _Scratch.keep_factor(lhs, lu, piv)
        self._w, self._a = sol[:n], sol[n:]

    def _tail(self, q: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones(len(q)), (q - self._shift) / self._scale])

    def _pairwise(self, q: np.ndarray):
        """dx, dy, r**2 and log(r**2) (0 where r = 0) from the centres to the query points (M, N)."""
        dx = q[:, 0, None] - self.centres[None, :, 0]
        dy = q[:, 1, None] - self.centres[None, :, 1]
        r2 = dx * dx + dy * dy
        return dx, dy, r2, np.log(np.where(r2 > 0, r2, 1.0))

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """f at query points (M, 2)."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, 2)
        out = np.empty(len(q))
        for k in range(0, len(q), self._CHUNK):
            c = q[k:k + self._CHUNK]
            _, _, r2, lg = self._pairwise(c)
            out[k:k + self._CHUNK] = (0.5 * r2 * lg) @ self._w + self._tail(c) @ self._a   # r**2 log r
        return out

    def gradient(self, q: np.ndarray | None = None) -> np.ndarray:
        """(df/dx, df/dy) at query points (M, 2), default the centres: grad phi = (x - c)(2 log r + 1),
        which vanishes at r = 0 with x - c."""
        if q is None:
            return _tps_gradient_at_centres(self.centres, self._log_r2, self._w, self._a[1:] / self._scale)
        q = np.asarray(q, dtype=np.float64).reshape(-1, 2)
        out = np.empty((len(q), 2))
        for k in range(0, len(q), self._CHUNK):
            dx, dy, _, lg = self._pairwise(q[k:k + self._CHUNK])
            g = lg + 1.0
            out[k:k + len(dx), 0] = (g * dx) @ self._w
            out[k:k + len(dx), 1] = (g * dy) @ self._w
        return out + self._a[1:] / self._scale

    def normals_at_centres(self) -> np.ndarray:
        """Unit normals (-f_x, -f_y, 1) / |.| of the surface at its own centres (N, 3)."""
        return _unit_normals(self.gradient())
