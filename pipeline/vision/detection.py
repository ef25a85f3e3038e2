"""Stage 3: marker detection in ONE camera view (determinant-of-Hessian blobs, bright on dark).

Markers are bright dots on a dark background. The detector works on a small Gaussian scale space
built on an image pyramid (two scales per octave, octave ``L`` computed on the image reduced
``2**L`` times, so the cost stays around a millisecond per 640x480 view whatever the largest scale):

1. scale-normalised determinant of Hessian ``DoH = sigma**4 (Lxx Lyy - Lxy**2)``, kept only where
   the Laplacian ``Lxx + Lyy`` is negative (bright blob; DoH alone is positive for both polarities);
2. non-maximum suppression in space (3x3 neighbourhood) and across scales (the strongest scale
   within ``min_separation_px`` wins);
3. sub-pixel centres: background-subtracted intensity centroid on the full-resolution image in a
   disc of radius ``centroid_radius_factor * sqrt(2) * sigma`` about the peak, iterated;
4. rejection of what is not a marker (LED-ring glare, the bright rim outside the skin): a blob must
   be brighter than its surrounding ring on ALL sides (``isolation``), must not be much larger than
   the median blob, must not be elongated, and must not sit on a saturated plateau.

The Gaussian filtering is OpenCV's; the per-pixel and per-marker loops around it (pyramid
reductions, DoH and peaks, sparse peak work, suppression, centroids and photometry) are numba-compiled
with the arithmetic of the numpy/OpenCV code they replaced (tests compare them with OpenCV where it
has the same operation).

References
----------
StereoTacTip paper, Sec. "Marker Localization" (greyscale, Determinant of Hessian blob detection).
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field, replace

import cv2
import numba
import numpy as np
from scipy.spatial import cKDTree

from pipeline.types import Blobs, DataError

__all__ = ["DetectionParams", "MONOCULAR_DOME", "detect_markers", "marker_radius_px", "to_grey"]


@dataclass(frozen=True)
class DetectionParams:
    """Parameters of :func:`detect_markers`.

    Attributes
    ----------
    sigmas_px : tuple of float
        Gaussian scales (px). Two per octave; octave ``L`` (scales in ``[1.4, 2.8) * 2**L``) runs on the
        ``2**L``-reduced image. A disc of radius ``r`` peaks at ``sigma ~ r / sqrt(2)``: the default
        1.4..8.5 px covers marker radii of about 2..12 px.
    threshold : float
        Minimum scale-normalised DoH on the [0, 1] image. A noise-free disc of contrast ``C`` gives
        about ``0.06 C**2`` (measured for radii 3-10 px), so 0.004 accepts contrast down to ~0.25.
    min_contrast : float
        Minimum (peak - surrounding ring median) intensity on the [0, 1] image.
    min_separation_px : float
        Two detections closer than this are one marker (the stronger is kept).
    border_px : int
        Peaks closer than this to the image edge are dropped.
    isolation : float
        The brightest of 8 angular sectors of the surrounding ring (mean) must stay below ``ring + isolation * contrast``
        (markers are surrounded by dark on all sides; glare touching a bright region is not).
    max_size_ratio : float
        Blobs whose scale is above ``max_size_ratio`` x or below 1/``max_size_ratio`` x the median
        scale are rejected (also: blobs with a saturated core when the median marker is not).
    max_elongation : float
        Blobs whose Hessian eigenvalue ratio exceeds this are rejected (edges, streaks).
    saturation_level : int
        Grey level treated as saturated.
    max_saturated_fraction : float
        Blobs whose ring is more than this fraction saturated sit on glare: rejected.
    centroid_radius_factor : float
        Centroid window radius as a multiple of the blob radius ``sqrt(2) * sigma``.
    centroid_iterations : int
        Re-centred centroid passes.
    debris_size_ratio : float or None
        When set, blobs whose scale is below 1/``debris_size_ratio`` x the median scale are debris, not
        markers: they are taken out BEFORE the cross-scale suppression (so a bright speck lying on a
        marker cannot shadow the marker's own, weaker, response) and never accepted, crowded or not.
        ``None`` (default): small blobs compete in the suppression and are accepted when a neighbour
        touches them (down to 1/``max_size_ratio**2``), as squeezed markers of a flat module need.
    isolation_inside : float or None
        When set, the isolation limit (as ``isolation``) for candidates inside the convex hull of the
        markers that pass the strict test. Glare (LED ring, bright rim) lies outside the marker field of
        a dome seen from inside; within it, a lit ring sector is debris or a touching neighbour.
        ``None`` (default): ``isolation`` everywhere.
    min_spacing_fraction : float or None
        When set, two accepted markers whose refined centres are closer than this fraction of the
        median nearest-neighbour spacing are one marker (the stronger response is kept): the
        cross-scale suppression works on unrefined peaks, which can converge on one marker after
        refinement. ``None`` (default): no such test.
    max_background_ratio : float or None
        When set, the median of a blob's surrounding ring must stay below this x its contrast: markers
        on a dark skin (ring ~0.1-0.35 of full scale against contrast ~0.35-0.6 on the real TacTip
        frames), not bumps on a bright rim (ring ~0.7, contrast ~0.2). ``None`` (default): no such test.
    """

    sigmas_px: tuple[float, ...] = (1.4, 2.0, 2.8, 4.0, 5.6, 8.0)
    threshold: float = 0.004
    min_contrast: float = 0.08
    min_separation_px: float = 3.0
    border_px: int = 2
    isolation: float = 0.5
    max_size_ratio: float = 1.4
    max_elongation: float = 4.0
    saturation_level: int = 250
    max_saturated_fraction: float = 0.25
    centroid_radius_factor: float = 1.5
    centroid_iterations: int = 2
    rejections: bool = field(default=True)
    debris_size_ratio: float | None = None
    isolation_inside: float | None = None
    min_spacing_fraction: float | None = None
    max_background_ratio: float | None = None

    def __post_init__(self) -> None:
        if not self.sigmas_px or any(not (s > 0 and math.isfinite(s)) for s in self.sigmas_px):
            raise DataError(f"DetectionParams.sigmas_px: need positive finite scales, got {self.sigmas_px}")
        if not self.threshold > 0:
            raise DataError(f"DetectionParams.threshold: must be > 0, got {self.threshold}")
        if self.border_px < 0 or self.min_separation_px < 0:
            raise DataError("DetectionParams.border_px / min_separation_px: must be >= 0")
        for name in ("debris_size_ratio", "isolation_inside", "min_spacing_fraction", "max_background_ratio"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise DataError(f"DetectionParams.{name}: must be None or a positive finite number, got {v}")

    def for_marker_radius(self, radius_px: float) -> "DetectionParams":
        """These parameters with the scale space narrowed to markers of about ``radius_px`` (px).

        Keeps three consecutive scales of ``sigmas_px``: the one nearest ``radius_px / sqrt(2)`` and
        its neighbours (the same grid, so the same discretisation and scale selection as the full
        set). With the default sqrt(2) grid the interpolated scale then sizes markers from ~0.7 r to
        ~1.4 r (indentation changes the apparent size by far less), and the scale space costs about
        half (the fine scales, which run on the largest pyramid levels, are skipped). Typical use:
        detect the first frame with the defaults, then ``params.for_marker_radius(marker_radius_px(blobs))``
        for the stream.

        Raises
        ------
        DataError
            ``radius_px`` is not a positive finite number.
        """
        r = float(radius_px)
        if not (r > 0 and math.isfinite(r)):
            raise DataError(f"DetectionParams.for_marker_radius: radius_px must be positive and finite, got {radius_px}")
        sig = sorted(self.sigmas_px)
        if len(sig) <= 3:
            return self
        k = int(np.argmin(np.abs(np.log(np.asarray(sig) * math.sqrt(2) / r))))
        k = min(max(k - 1, 0), len(sig) - 3)
        return replace(self, sigmas_px=tuple(sig[k:k + 3]))


#: Detection for a monocular dome (TacTip-type) sensor: one camera inside a dark hemispherical skin,
#: markers of one size on pins, LED glare and the bright rim only outside the marker field, and debris
#: in the gel (bright specks of about half a marker's scale, measured sigma 0.4-0.67 x the median on the
#: real 331-pin frames against >= 0.74 x for markers) next to or on markers. Specks are removed before
#: the scale suppression, a ring sector lit by a speck or a touching neighbour inside the marker field
#: is tolerated up to the marker's own contrast, centres that converge after refinement closer than
#: half the local spacing are one marker, and a marker's surround is darker than the marker stands
#: out from it (the skin is dark; the bright rim outside it is not).
MONOCULAR_DOME = DetectionParams(debris_size_ratio=1.4, isolation_inside=1.0, min_spacing_fraction=0.5,
                                 max_background_ratio=1.0)


def marker_radius_px(blobs: Blobs) -> float:
    """Typical marker radius (px) of a detection: ``sqrt(2)`` x the median scale.

    Raises
    ------
    DataError
        ``blobs`` is empty.
    """
    if len(blobs) == 0:
        raise DataError("marker_radius_px: no blobs detected, cannot estimate the marker radius")
    return float(math.sqrt(2) * np.median(blobs.sigma_px))


def to_grey(image: np.ndarray, *, name: str = "image") -> np.ndarray:
    """Validate a uint8 grey (H, W) / (H, W, 1) or BGR (H, W, 3) image and return it grey (H, W) uint8."""
    if not isinstance(image, np.ndarray):
        raise DataError(f"{name}: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise DataError(f"{name}: expected uint8 pixels, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        if image.size == 0:
            return np.zeros(image.shape[:2], np.uint8)
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    raise DataError(f"{name}: expected a grey (H, W) or BGR (H, W, 3) image, got shape {image.shape}")


_SECTORS = 8  # angular sectors of the background ring for the isolation test
_RING_IN = 1.25



class _Workspace:
    """Per-thread reusable image buffers, keyed by (name, shape, dtype).

    Fresh multi-MB arrays are expensive where page faults are slow (measured here: 8 new 640x480
    float32 arrays cost ~7 ms, reusing them ~0.5 ms), so the per-frame temporaries are kept.
    """

    _local = threading.local()

    @classmethod
    def get(cls, name: str, shape: tuple[int, ...], dtype=np.float32) -> np.ndarray:
        bufs = getattr(cls._local, "bufs", None)
        if bufs is None:
            bufs = cls._local.bufs = {}
        key = (name, tuple(shape), np.dtype(dtype).str)
        buf = bufs.get(key)
        if buf is None:
            if len(bufs) > 64:  # many image sizes in one process: start over
                bufs.clear()
            buf = bufs[key] = np.empty(shape, dtype)
        return buf


def _hessian_kernels(sigma: float, norm: float):
    """1-D kernels (smooth, second difference, first difference) of a Gaussian of ``sigma`` (level px)
    convolved with the 3-tap differences, scaled by ``norm**2`` / ``norm`` so that the Hessian comes
    out scale-normalised. Same result as GaussianBlur followed by the 3-tap filters (OpenCV's own
    kernel size for float images), in 3 instead of 4 image passes."""
    key = (sigma, norm)
    hit = _KERNELS.get(key)
    if hit is None:
        ksize = int(round(sigma * 4 * 2 + 1)) | 1
        g = cv2.getGaussianKernel(ksize, sigma, cv2.CV_64F).ravel()
        gxx = np.convolve(g, [1.0, -2.0, 1.0]) * norm**2
        gx = np.convolve(g, [0.5, 0.0, -0.5]) * norm  # correlation with [-0.5, 0, 0.5] after g
        g0 = np.concatenate([[0.0], g, [0.0]])
        hit = _KERNELS[key] = tuple(k.astype(np.float32) for k in (g0, gxx, gx))
    return hit


_KERNELS: dict[tuple, tuple] = {}


def _hessian(level: np.ndarray, sigma: float, norm_sigma: float, out: list[np.ndarray]) -> None:
    """Scale-normalised Hessian entries Lxx, Lyy, Lxy of one pyramid level into ``out``.

    ``sigma`` is the blur applied here; ``norm_sigma`` the total scale, in level px, used to normalise
    (``norm_sigma**2`` times the second derivatives). Each entry is one separable OpenCV filter with
    the Gaussian and the 3-tap difference fused (:func:`_hessian_kernels`).
    """
    g0, gxx, gx = _hessian_kernels(float(sigma), float(norm_sigma))
    cv2.sepFilter2D(level, -1, gxx, g0, dst=out[0])
    cv2.sepFilter2D(level, -1, g0, gxx, dst=out[1])
    cv2.sepFilter2D(level, -1, gx, gx, dst=out[2])


@numba.njit(cache=True, nogil=True)
def _doh_peaks(lxx, lyy, lxy, doh, threshold, border, offset, peaks, n_peaks):
    """Bright-blob DoH of one level and its spatial peaks.

    ``doh = min(Lxx, 0) Lyy - Lxy**2`` in float32: where the DoH is positive both eigenvalues share
    the sign of ``Lxx``, so this equals the DoH on bright blobs and is <= 0 on dark ones (never a
    peak above the positive threshold). A peak is at least each of its 8 neighbours, above
    ``threshold`` and ``border`` (>= 1) px inside the level; its flat index plus ``offset`` is
    appended to ``peaks`` from ``n_peaks`` on. Returns the new count.
    """
    h, w = doh.shape
    for y in range(h):
        for x in range(w):
            doh[y, x] = min(lxx[y, x], np.float32(0.0)) * lyy[y, x] - lxy[y, x] * lxy[y, x]
    thr = np.float32(threshold)
    for y in range(border, h - border):
        for x in range(border, w - border):
            c = doh[y, x]
            if not c > thr:
                continue
            if (c >= doh[y - 1, x - 1] and c >= doh[y - 1, x] and c >= doh[y - 1, x + 1] and c >= doh[y, x - 1]
                    and c >= doh[y, x + 1] and c >= doh[y + 1, x - 1] and c >= doh[y + 1, x]
                    and c >= doh[y + 1, x + 1]):
                peaks[n_peaks] = offset + y * w + x
                n_peaks += 1
    return n_peaks


def _half(img: np.ndarray, name: str) -> np.ndarray:
    """Exact 2x2 mean (odd last row/column dropped) into a reused buffer."""
    h2, w2 = img.shape[0] // 2, img.shape[1] // 2
    src = img if img.shape == (2 * h2, 2 * w2) else img[: 2 * h2, : 2 * w2]
    return cv2.resize(src, (w2, h2), dst=_Workspace.get(name, (h2, w2)), interpolation=cv2.INTER_AREA)


#: Grey level k of a uint8 image is the float32 ``k * _U8_SCALE`` on the [0, 1] scale.
_U8_SCALE = np.float32(1.0 / 255.0)


def _grey_float(grey: np.ndarray) -> np.ndarray:
    """The uint8 image on the [0, 1] scale as float32 (a reused buffer)."""
    out = _Workspace.get("grey_f", grey.shape)
    np.multiply(grey, _U8_SCALE, out=out, casting="unsafe")
    return out


@numba.njit(cache=True, nogil=True)
def _half_u8(grey, out):
    """2x2 mean of a uint8 image on the [0, 1] scale (odd last row/column dropped) into ``out``:
    the integer sum of the four, scaled once."""
    scale = np.float32(0.25 / 255.0)
    h2, w2 = out.shape
    pairs = np.empty(2 * w2, np.int32)
    for y in range(h2):
        # row by row (vectorises also on a strided view, e.g. one half of a stereo frame)
        r0, r1 = grey[2 * y], grey[2 * y + 1]
        for x in range(2 * w2):
            pairs[x] = np.int32(r0[x]) + np.int32(r1[x])
        for x in range(w2):
            out[y, x] = np.float32(pairs[2 * x] + pairs[2 * x + 1]) * scale
    return out


@functools.lru_cache(maxsize=32)
def _area_table(ssize: int, dsize: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-resampling weights from ``ssize`` to ``dsize`` samples, as OpenCV's INTER_AREA computes
    them (computeResizeAreaTab): each output cell averages the input cells it overlaps, weighted by
    the overlap. Returns (source index, float32 weight, pointer (dsize + 1,)) in CSR form."""
    scale = ssize / dsize
    idx, wts, ptr = [], [], [0]
    for d in range(dsize):
        f1 = d * scale
        f2 = f1 + scale
        cell = min(scale, ssize - f1)
        s2 = min(math.floor(f2), ssize - 1)
        s1 = min(math.ceil(f1), s2)
        if s1 - f1 > 1e-3:
            idx.append(s1 - 1)
            wts.append((s1 - f1) / cell)
        for k in range(s1, s2):
            idx.append(k)
            wts.append(1.0 / cell)
        if f2 - s2 > 1e-3:
            idx.append(s2)
            wts.append(min(f2 - s2, 1.0, cell) / cell)
        ptr.append(len(idx))
    return np.array(idx, np.intp), np.array(wts, np.float32), np.array(ptr, np.intp)


@functools.lru_cache(maxsize=32)
def _area_taps(ssize: int, dsize: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_area_table` as a fixed number of taps per output sample: output ``d`` is
    ``sum_t weights[t, d] * src[first[d] + t]`` for t in ``range(len(weights))``, with zero weights
    where the sample has fewer taps (the source cells of one sample are consecutive). Returns (first
    (dsize,), weights (T, dsize) float32); ``first + T - 1`` stays inside the source."""
    idx, wts, ptr = _area_table(ssize, dsize)
    n = np.diff(ptr)
    taps = int(min(n.max(), ssize))
    first = np.minimum(idx[ptr[:-1]], ssize - taps).astype(np.intp)
    weights = np.zeros((taps, dsize), np.float32)
    for d in range(dsize):
        cells = idx[ptr[d]:ptr[d + 1]]
        assert np.all(np.diff(cells) == 1)
        weights[cells - first[d], d] = wts[ptr[d]:ptr[d + 1]]
    return first, weights


@numba.njit(cache=True, nogil=True)
def _area_resize_kernel(src, xf, xw, yi, yw, yp, out, row):
    """Separable area resampling of ``src`` into ``out`` with :func:`_area_table` weights: rows
    first (contiguous, vectorised), then the columns of the combined row (:func:`_area_taps`: a fixed
    tap count, tap by tap across the row, vectorised); float32 throughout.

    Each output is ``0 + w_0 s_0 + w_1 s_1 + ...`` in the order of the source cells, as a loop over
    the CSR table sums it; the padding taps add ``0 * s`` = +0 (finite ``s``), which leaves a sum that
    is never -0 unchanged, so the result is the same bit for bit.
    """
    n_taps, w1 = xw.shape
    for y in range(out.shape[0]):
        row[:] = 0.0
        for k in range(yp[y], yp[y + 1]):
            wk, r = yw[k], yi[k]
            for x in range(src.shape[1]):
                row[x] += wk * src[r, x]
        o = out[y]
        o[:] = 0.0
        for t in range(n_taps):
            wt = xw[t]
            for x in range(w1):
                o[x] += wt[x] * row[xf[x] + t]
    return out


def _area_resize(src: np.ndarray, w1: int, h1: int, name: str) -> np.ndarray:
    """``src`` (float32) area-resampled to ``(h1, w1)`` into a reused buffer: OpenCV's INTER_AREA
    (within 2e-7 on [0, 1] images; tests/test_detection.py) at less than half its cost for the
    non-integer sqrt(2) reduction, where OpenCV takes its general path (measured on one thread,
    320x240 -> 226x170: 0.074 ms against 0.18 ms)."""
    return _area_resize_kernel(src, *_area_taps(src.shape[1], w1), *_area_table(src.shape[0], h1),
                               _Workspace.get(name, (h1, w1)), _Workspace.get(name + "_row", (src.shape[1],)))


def _level(grey: np.ndarray, j: int, cache: dict) -> tuple[np.ndarray, float, float]:
    """Half-octave pyramid level ``j`` of the uint8 image ``grey``: the image area-reduced
    ~``sqrt(2)**j`` times, float32 on the [0, 1] scale.

    Level ``j`` is the exact 2x2 mean of level ``j - 2`` (level 2 straight from the uint8 pixels, so
    the full-resolution float image is never made unless level 0 or 1 is asked for), except the odd
    bases: level 3 is an INTER_AREA resize of level 2 by 1/sqrt(2) (level 1, used only for scales
    below ~1.4 px, one of the full image). Returns (image, fx, fy): level pixel ``(i_x, i_y)`` is
    centred at full pixel ``((i_x + 0.5) fx - 0.5, (i_y + 0.5) fy - 0.5)``.
    """
    if j not in cache:
        if j == 0:
            cache[0] = (_grey_float(grey), 1.0, 1.0)
        elif j == 2 and min(grey.shape) >= 10:
            h2, w2 = grey.shape[0] // 2, grey.shape[1] // 2
            cache[2] = (_half_u8(grey, _Workspace.get("lvl2", (h2, w2))), 2.0, 2.0)
        elif j in (1, 3):
            prev, px, py = _level(grey, j - 1 if j == 1 else 2, cache)
            h, w = prev.shape
            w1, h1 = max(1, int(round(w / math.sqrt(2)))), max(1, int(round(h / math.sqrt(2))))
            img = _area_resize(prev, w1, h1, f"lvl{j}")
            cache[j] = (img, px * w / w1, py * h / h1)
        else:
            prev, fx, fy = _level(grey, j - 2, cache)
            if min(prev.shape) < 10:
                cache[j] = cache[j - 2]
            else:
                cache[j] = (_half(prev, f"lvl{j}"), 2 * fx, 2 * fy)
    return cache[j]


#: Scales run on a half-octave area pyramid at this level blur (level px). Every scale then sees the
#: same discretisation (3-tap second differences of a Gaussian of sigma ~1 are ~10 % below the
#: continuous ones, the SAME 10 % at every scale, so scale selection is unbiased), the blob is
#: ~1.4 level px in radius, and the work is a fraction of the full-resolution scale space. Centres are
#: refined afterwards on the full-resolution image.
_LEVEL_SIGMA = 0.95
#: Scales that would run on the sqrt(2) level run on the half-resolution level instead when they are
#: still this many level px there (the default 1.4 px scale: 0.7 px, slightly under-read by the
#: 3-tap differences, which only nudges the sizes of the smallest markers up), which saves the full-
#: resolution resize, the most expensive single operation of the scale space.
_MIN_HALF_SIGMA = 0.69


def _scale_plan(grey: np.ndarray, params: DetectionParams, cache: dict):
    """What :func:`_candidates` does per scale on an image of this shape: the pyramid level of each
    scale, its blur, normalising scale and border (level px), where its maps sit in the packed buffers,
    and the per-scale arrays of :func:`_peak_kernel`. A function of the image shape and the scales only,
    so it is worked out once per (shape, scales, border) and kept; building it computes the levels
    into ``cache``. None when no scale has a level of at least 5 px."""
    key = (grey.shape, tuple(params.sigmas_px), params.border_px)
    hit = _PLANS.get(key)
    if hit is not None:
        return hit[0]
    sig = np.asarray(sorted(params.sigmas_px), dtype=np.float64)
    log_s = np.log2(sig)
    level_of = np.floor(2 * np.log2(np.maximum(sig / _LEVEL_SIGMA, 1.0))).astype(int)
    level_of[(level_of == 1) & (sig / 2 >= _MIN_HALF_SIGMA)] = 2
    levels = []
    for j in level_of:
        level, fx, fy = _level(grey, int(j), cache)
        levels.append((level, fx, fy) if min(level.shape) >= 5 else None)
    hs = np.array([lv[0].shape[0] if lv else 0 for lv in levels], np.intp)
    ws = np.array([lv[0].shape[1] if lv else 1 for lv in levels], np.intp)
    fxs = np.array([lv[1] if lv else 1.0 for lv in levels])
    fys = np.array([lv[2] if lv else 1.0 for lv in levels])
    sizes = np.where(hs > 0, hs * ws, 0)
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
    total = int(offs[-1])
    plan = None
    if total > 0:
        steps = []
        for i_s, lv in enumerate(levels):
            if lv is None:
                steps.append(None)
                continue
            level, fx, fy = lv
            f = math.sqrt(fx * fy)
            s_full = sig[i_s]
            # blur on top of the box averaging so that the total scale is s_full
            s_blur = math.sqrt(max(s_full**2 - max(f * f - 1, 0.0) / 12.0, 0.25 * s_full**2)) / f
            b = max(1, int(math.ceil(params.border_px / min(fx, fy))))  # >= 1: neighbours stay on the level
            steps.append((float(s_blur), float(s_full / f), b, int(offs[i_s]), int(offs[i_s + 1]), level.shape))
        plan = ([int(j) for j in level_of], steps, total, offs, hs, ws, fxs, fys, log_s)
    if len(_PLANS) > 64:
        _PLANS.clear()
    _PLANS[key] = (plan,)
    return plan


_PLANS: dict[tuple, tuple] = {}


def _candidates(grey: np.ndarray, params: DetectionParams):
    """Scale-space maxima: (N, 6) array of x_full, y_full, sigma_full (continuous), response,
    elongation, measuring scale (sigma quantised to 1/8 octave, shared pixel offsets per group).

    Scale ``s`` (full-resolution px) is evaluated on the half-octave area pyramid level where it is
    about ``_LEVEL_SIGMA`` level px: the blob is ~1.4 level px in radius, which is all the DoH needs
    to find and size it. A peak is kept only where it is also a maximum across scale (against the two
    neighbouring scales sampled at the same place: edge and plateau responses of a marker at finer
    scales fall here), and its scale is refined by a parabola in log-sigma through those three
    responses. Centres are refined later on the full-resolution image.

    All scales' maps live in one packed buffer per quantity, so the sparse work on the peaks is done
    once for all scales (flat indices) rather than once per scale.
    """
    cache: dict = {}
    plan = _scale_plan(grey, params, cache)
    if plan is None:
        return np.empty((0, 6))
    level_of, steps, total, offs, hs, ws, fxs, fys, log_s = plan
    packs = [_Workspace.get(f"pack_{q}", (total,)) for q in ("doh", "lxx", "lyy", "lxy")]
    peaks = _Workspace.get("pack_peaks", (total,), np.intp)
    n_peaks = 0
    threshold = float(params.threshold)
    for i_s, step in enumerate(steps):
        if step is None:
            continue
        s_blur, norm, b, o0, o1, shp = step
        level = _level(grey, level_of[i_s], cache)[0]
        views = [p[o0:o1].reshape(shp) for p in packs]
        _hessian(level, s_blur, norm, views[1:])
        n_peaks = _doh_peaks(*views[1:], views[0], threshold, b, o0, peaks, n_peaks)
    if n_peaks == 0:
        return np.empty((0, 6))
    return _peak_kernel(peaks[:n_peaks], *packs, offs, hs, ws, fxs, fys, log_s)


@numba.njit(cache=True, nogil=True)
def _scale_sample(doh, k, x_full, y_full, offs, hs, ws, fxs, fys):
    """Response of scale ``k`` at full-resolution (x_full, y_full): its level pixel containing the
    point; -inf where scale ``k`` does not exist (outside the scale list, or a level too small)."""
    if not (0 <= k < len(hs) and hs[k] > 0):
        return -np.inf
    u = min(int((x_full + 0.5) / fxs[k]), ws[k] - 1)     # coordinates are >= 0: truncation floors
    v = min(int((y_full + 0.5) / fys[k]), max(hs[k] - 1, 0))
    return np.float64(doh[offs[k] + v * ws[k] + u])


@numba.njit(cache=True, nogil=True)
def _peak_kernel(g, doh, lxx, lyy, lxy, offs, hs, ws, fxs, fys, log_s):
    """Sparse work of :func:`_candidates` on the spatial peaks ``g`` (flat indices into the packed
    scale maps, scale by scale): sub-pixel peak, the cross-scale maximum test against the two
    neighbouring scales sampled at the same place, the continuous scale, the elongation and the
    measuring scale. Returns the (M, 6) candidates that pass, in the order of ``g``."""
    n_s = len(log_s)
    out = np.empty((len(g), 6))
    m = 0
    i_s = 0
    for gi in g:
        while gi >= offs[i_s + 1]:
            i_s += 1
        w = ws[i_s]
        ys, xs = divmod(gi - offs[i_s], w)
        # sub-pixel peak in the response (refined later on the full image); differences of float32
        # samples are exact in float32, the rest in float64
        c = np.float64(doh[gi])
        dxp = np.float32(doh[gi + 1] - doh[gi - 1])
        dyp = np.float32(doh[gi + w] - doh[gi - w])
        dx = min(max(0.5 * dxp / max(2 * c - doh[gi + 1] - doh[gi - 1], 1e-12), -0.5), 0.5)
        dy = min(max(0.5 * dyp / max(2 * c - doh[gi + w] - doh[gi - w], 1e-12), -0.5), 0.5)
        # peak value of the fitted parabolas (a sample up to half a level px off the peak under-reads
        # it, which would bias scale selection towards finer levels)
        c = c + 0.25 * (dxp * dx + dyp * dy)
        x_full = (xs + dx + 0.5) * fxs[i_s] - 0.5
        y_full = (ys + dy + 0.5) * fys[i_s] - 0.5
        # response of the neighbouring scales at (x_full, y_full): their level pixel containing it
        lo = _scale_sample(doh, i_s - 1, x_full, y_full, offs, hs, ws, fxs, fys)
        hi = _scale_sample(doh, i_s + 1, x_full, y_full, offs, hs, ws, fxs, fys)
        if not (c >= lo and c >= hi):
            continue
        # continuous scale: parabola through the three responses on the log-sigma axis (the sqrt(2)
        # grid is too coarse to place the background ring just outside the marker)
        curv = lo - 2 * c + hi
        delta = 0.0
        if np.isfinite(lo) and np.isfinite(hi) and curv < 0:
            delta = min(max(0.5 * (np.float32(lo) - np.float32(hi)) / curv, -0.5), 0.5)   # float32 samples
        if delta < 0:
            step = log_s[i_s] - log_s[i_s - 1] if i_s > 0 else 0.5
        else:
            step = log_s[i_s + 1] - log_s[i_s] if i_s < n_s - 1 else 0.5
        s_cont = 2.0 ** (log_s[i_s] + delta * step)
        a, d, e = np.float64(lxx[gi]), np.float64(lyy[gi]), np.float64(lxy[gi])
        tr, det = a + d, a * d - e * e
        disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
        l1, l2 = abs(tr / 2 - disc), abs(tr / 2 + disc)
        out[m, 0], out[m, 1], out[m, 2], out[m, 3] = x_full, y_full, s_cont, c
        out[m, 4] = max(l1, l2) / max(min(l1, l2), 1e-12)
        out[m, 5] = 2.0 ** (np.rint(8 * np.log2(s_cont)) / 8)
        m += 1
    return out[:m]


def _suppress(cand: np.ndarray, min_sep: float) -> np.ndarray:
    """Cross-scale NMS: drop a candidate when a stronger one lies within ``max(min_sep, r_i, r_j)``."""
    if len(cand) < 2:
        return cand
    return cand[_suppress_kernel(cand, float(min_sep))]


@numba.njit(cache=True, nogil=True)
def _suppress_kernel(cand, min_sep):
    """Keep mask of :func:`_suppress`: for every pair closer than the larger of their radii
    (``max(min_sep, sqrt(2) sigma)``) the weaker (ties: the later) is dropped, whether or not the
    stronger survives. Pairs are found along x-sorted candidates within the largest radius."""
    n = len(cand)
    radius = np.empty(n)
    for i in range(n):
        radius[i] = max(min_sep, math.sqrt(2.0) * cand[i, 2])
    r_max = radius.max()
    order = np.argsort(cand[:, 0])
    keep = np.ones(n, np.bool_)
    for a in range(n):
        i = order[a]
        for b in range(a + 1, n):
            j = order[b]
            if cand[j, 0] - cand[i, 0] > r_max:
                break
            if math.hypot(cand[i, 0] - cand[j, 0], cand[i, 1] - cand[j, 1]) < max(radius[i], radius[j]):
                lo, hi = min(i, j), max(i, j)
                keep[hi if cand[lo, 3] >= cand[hi, 3] else lo] = False
    return keep


def _patch_offsets(rmax: int) -> tuple[np.ndarray, np.ndarray]:
    r = np.arange(-rmax, rmax + 1)
    ox, oy = np.meshgrid(r, r)
    return ox.ravel(), oy.ravel()


def _group_geometry(r_blob: float, params: DetectionParams) -> tuple[float, float, float, int]:
    """(ring inner radius, ring outer radius, centroid window radius, max offset) for radius ``r_blob``."""
    r_win = params.centroid_radius_factor * r_blob + 0.5
    r_in, r_out = _RING_IN * r_blob + 1.0, _RING_IN * r_blob + 2.5
    return r_in, r_out, r_win, int(math.ceil(max(r_out, r_win)))


def _group_offsets(r_blob: float, params: DetectionParams):
    """Pixel offsets (dx, dy) from a rounded centre of the ring (ordered by sector, with the sector
    starts), the centroid window and the core for blobs of radius ``r_blob``. Cached per radius."""
    key = (r_blob, params.centroid_radius_factor)
    hit = _OFFSETS.get(key)
    if hit is not None:
        return hit
    r_in, r_out, r_win, rmax = _group_geometry(r_blob, params)
    ox, oy = _patch_offsets(rmax)
    d2 = ox * ox + oy * oy
    ring_sel = (d2 >= r_in * r_in) & (d2 <= r_out * r_out)
    rox, roy = ox[ring_sel], oy[ring_sel]
    sector = (np.floor((np.arctan2(roy, rox) + np.pi) * (_SECTORS / (2 * np.pi))).astype(np.intp)) % _SECTORS
    o = np.argsort(sector, kind="stable")
    starts = np.searchsorted(sector[o], np.arange(_SECTORS + 1)).astype(np.intp)
    win_sel = d2 <= r_win * r_win
    core_sel = d2 <= (0.5 * r_blob + 0.5) ** 2
    hit = tuple(np.ascontiguousarray(a, dtype=np.intp) for a in
                (rox[o], roy[o], starts, ox[win_sel], oy[win_sel], ox[core_sel], oy[core_sel]))
    if len(_OFFSETS) > 256:
        _OFFSETS.clear()
    _OFFSETS[key] = hit
    return hit


_OFFSETS: dict[tuple, tuple] = {}


@numba.njit(cache=True, nogil=True)
def _gather(img, ix, iy, dx, dy, k0, k1, out):
    """``out[k]`` = pixel ``(ix + dx[k], iy + dy[k])`` of the uint8 ``img`` on the [0, 1] scale for k
    in [k0, k1), -1 outside the image; returns the count inside."""
    h, w = img.shape
    n_in = 0
    for k in range(k0, k1):
        x, y = ix + dx[k], iy + dy[k]
        if 0 <= x < w and 0 <= y < h:
            out[k] = np.float32(img[y, x]) * _U8_SCALE
            n_in += 1
        else:
            out[k] = -1.0
    return n_in


@numba.njit(cache=True, nogil=True)
def _ring_median(img, ix, iy, dx, dy, k0, k1, reach, out, hist):
    """:func:`_gather` of the ring into ``out`` plus the median of its inside pixels on the [0, 1]
    scale (NaN if none), from a histogram of the uint8 levels: exact, and without the data-dependent
    branches of a selection (which cost far more in the pipeline than on a repeated benchmark input).
    ``reach`` bounds ``|dx|``, ``|dy|`` over ``k0:k1``. Returns (count inside, median)."""
    h, w = img.shape
    hist[:] = 0
    n_in = 0
    if reach <= ix < w - reach and reach <= iy < h - reach:
        # the ring wholly inside: no bounds tests
        for k in range(k0, k1):
            q = img[iy + dy[k], ix + dx[k]]
            out[k] = np.float32(q) * _U8_SCALE
            hist[q] += 1
        n_in = k1 - k0
    else:
        for k in range(k0, k1):
            x, y = ix + dx[k], iy + dy[k]
            if 0 <= x < w and 0 <= y < h:
                q = img[y, x]
                out[k] = np.float32(q) * _U8_SCALE
                hist[q] += 1
                n_in += 1
            else:
                out[k] = -1.0
    if n_in == 0:
        return 0, np.nan
    lo_rank, hi_rank = (n_in - 1) // 2, n_in // 2
    cum = 0
    lo = -1
    hi = 255
    for b in range(256):
        cum += hist[b]
        if lo < 0 and cum > lo_rank:
            lo = b
        if cum > hi_rank:
            hi = b
            break
    return n_in, 0.5 * (np.float64(np.float32(lo) * _U8_SCALE) + np.float64(np.float32(hi) * _U8_SCALE))


#: Largest window reach (px) for which :func:`_window_moments` is exact in any summation order.
_EXACT_REACH = 64


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _window_moments(img, ix, iy, spans, s0, s1, bg):
    """Background-subtracted light of a centroid window wholly inside ``img`` and its first moments
    about ``(ix, iy)``: ``sum(wt)``, ``sum(wt dx)``, ``sum(wt dy)`` with ``wt = max(v - bg, 0)``, ``v``
    the float32 pixel on the [0, 1] scale, over the row spans ``spans[s0:s1]`` (dy, first dx, last dx).

    Every term is exact in float64 and so is every partial sum: ``v`` and ``bg`` (a float32 median
    of such pixels, or 0) are float32 numbers in {0} U [2**-9, 1], hence multiples of 2**-32, and so
    are their differences (< 1); times an offset ``|d| <= reach`` and summed over at most
    ``(2 reach + 1)**2`` pixels they stay below ``2**21`` in magnitude for ``reach <=``
    :data:`_EXACT_REACH`, within float64's 53 bits. The sums are therefore the same whatever the order,
    which lets the compiler vectorise them (``reassoc``; no contraction, no reciprocals): the result
    is bit for bit the in-order loop's.
    """
    tot = 0.0
    mx = 0.0
    my = 0.0
    for sp in range(s0, s1):
        dy = spans[sp, 0]
        first = spans[sp, 1]
        seg = img[iy + dy, ix + first: ix + spans[sp, 2] + 1]   # indexed from 0: no negative-index wrap
        for k in range(seg.size):
            wt = max(np.float32(seg[k]) * _U8_SCALE - bg, 0.0)
            tot += wt
            mx += wt * (first + k)
            my += wt * dy
    return tot, mx, my


@numba.njit(cache=True, nogil=True)
def _measure_kernel(img, cand, gid, n_iter, sat_thr, lims, ring_dx, ring_dy, ring_ptr, starts, win_dx, win_dy,
                    win_ptr, spans, span_ptr, reach, core_dx, core_dy, core_ptr, ring_reach, xy, contrast, sectors,
                    sat, core_sat):
    """Compiled per-candidate loop of :func:`_refine_and_measure`.

    Candidate ``i`` (x, y in ``cand[i, :2]``) uses the geometry of group ``g = gid[i]``: the pixel
    offsets ``ring_dx[ring_ptr[g]:ring_ptr[g + 1]]`` (and likewise window and core), the ring's
    sector boundaries ``starts[g]`` (absolute indices) and the centroid run-away limit ``lims[g]``.
    Writes the refined centres ``xy`` (N, 2), ``contrast``, ``sectors`` (N, 8), ``sat``, ``core_sat``.
    Pixels outside the image read as -1: never ring or window light, never saturated. A centroid pass
    depends only on the rounded centre it starts from, so the passes stop once that stops changing,
    and the photometry reuses the first ring when the rounded centre is where it started (the result
    is the same as doing all the work).
    """
    h, w = img.shape
    ring = np.empty(len(ring_dx), np.float64)
    hist = np.empty(256, np.int32)
    core = np.empty(len(core_dx), np.float64)
    for i in range(len(cand)):
        g = gid[i]
        r0, r1, w0, w1, c0, c1 = ring_ptr[g], ring_ptr[g + 1], win_ptr[g], win_ptr[g + 1], core_ptr[g], core_ptr[g + 1]
        x0, y0 = cand[i, 0], cand[i, 1]
        ix0, iy0 = int(np.rint(x0)), int(np.rint(y0))
        n_in, med0 = _ring_median(img, ix0, iy0, ring_dx, ring_dy, r0, r1, ring_reach[g], ring, hist)
        if np.isnan(med0):
            med0 = 0.0
        bg = np.float64(np.float32(med0))
        x, y = x0, y0
        pix, piy = -1 << 30, -1 << 30
        for _ in range(max(1, n_iter)):
            ix, iy = int(np.rint(x)), int(np.rint(y))
            if ix == pix and iy == piy:
                break
            pix, piy = ix, iy
            tot = 0.0
            mx = 0.0
            my = 0.0
            rr = reach[g]
            if rr <= ix < w - rr and rr <= iy < h - rr and rr <= _EXACT_REACH:
                # window wholly inside: row spans, no bounds tests, sums in any order (exact)
                tot, mx, my = _window_moments(img, ix, iy, spans, span_ptr[g], span_ptr[g + 1], bg)
            elif rr <= ix < w - rr and rr <= iy < h - rr:
                for sp in range(span_ptr[g], span_ptr[g + 1]):
                    dy = spans[sp, 0]
                    for dx in range(spans[sp, 1], spans[sp, 2] + 1):
                        wt = max(np.float32(img[iy + dy, ix + dx]) * _U8_SCALE - bg, 0.0)   # branch-free
                        tot += wt
                        mx += wt * dx
                        my += wt * dy
            else:
                for k in range(w0, w1):
                    u, v = ix + win_dx[k], iy + win_dy[k]
                    if 0 <= u < w and 0 <= v < h:
                        wt = max(np.float32(img[v, u]) * _U8_SCALE - bg, 0.0)   # branch-free: marker edges are unpredictable
                        tot += wt
                        mx += wt * win_dx[k]
                        my += wt * win_dy[k]
            nx, ny = x, y
            if tot > 0.0:
                nx, ny = ix + mx / tot, iy + my / tot
            # a centroid that runs away (neighbour or plateau in the window) keeps the DoH peak
            if math.hypot(nx - x0, ny - y0) <= lims[g]:
                x, y = nx, ny
            else:
                x, y = x0, y0
        xy[i, 0], xy[i, 1] = x, y
        # photometry about the refined centre
        ix, iy = int(np.rint(x)), int(np.rint(y))
        bg = med0
        if ix != ix0 or iy != iy0:
            n_in, bg = _ring_median(img, ix, iy, ring_dx, ring_dy, r0, r1, ring_reach[g], ring, hist)
            if np.isnan(bg):
                bg = 0.0
        n_sat = 0
        for k in range(r0, r1):
            if ring[k] >= sat_thr:
                n_sat += 1
        sat[i] = n_sat / max(n_in, 1)
        for s in range(_SECTORS):
            cnt = 0
            acc = 0.0
            for k in range(starts[g, s], starts[g, s + 1]):
                if ring[k] >= 0.0:
                    cnt += 1
                    acc += ring[k]
            sectors[i, s] = (acc / cnt if cnt > 0 else -np.inf) - bg
        _gather(img, ix, iy, core_dx, core_dy, c0, c1, core)
        peak = -np.inf
        n_sat = 0
        for k in range(c0, c1):
            peak = max(peak, core[k])
            if core[k] >= sat_thr:
                n_sat += 1
        contrast[i] = peak - bg
        core_sat[i] = n_sat / (c1 - c0)


@numba.njit(cache=True, nogil=True)
def _median(a):
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


@numba.njit(cache=True, nogil=True)
def _unique_inverse(a):
    """``np.unique(a, return_inverse=True)`` for a 1-D float64 array without NaN: the sorted distinct
    values and, per sample, the index of its value among them."""
    s = np.sort(a)
    n_u = 0
    for i in range(len(s)):
        if i == 0 or s[i] != s[i - 1]:
            s[n_u] = s[i]
            n_u += 1
    uniq = s[:n_u].copy()
    inv = np.searchsorted(uniq, a).astype(np.intp)
    return uniq, inv


def _refine_and_measure(grey: np.ndarray, cand: np.ndarray, params: DetectionParams):
    """Sub-pixel centroids and local photometry per candidate.

    Per candidate the background is the median of a ring about it (robust to the candidate being a
    pixel or two off, as on the coarse pyramid levels); the centroid of the window above that
    background is iterated ``centroid_iterations`` times (a centroid that moves more than
    ``0.5 r + 1`` px from the DoH peak keeps the peak); ring, sectors and core are then laid out
    about the rounded refined centre (<= 0.71 px off) for the photometry. Geometry per measuring
    scale (column 5 of ``cand``), so candidates of one scale share the pixel offsets.

    Returns ``xy`` (N, 2) refined centres, ``contrast`` (N,) peak minus ring median, ``sectors``
    (N, 8) mean of each angular ring sector minus the ring median (-inf for a sector wholly outside
    the image; sector ``k`` spans angles ``-pi + k pi/4 .. -pi + (k+1) pi/4`` of ``atan2(dv, du)``),
    ``sat`` (N,) saturated fraction of the ring,
    ``core_sat`` (N,) saturated fraction of the blob core.
    The ring spans ``1.25 r + 1 .. 1.25 r + 2.5`` px (r = sqrt(2) sigma with the continuous scale):
    just outside the marker edge and, on the densest real frames (r ~4.7 px, pitch 16.8 px), inside
    the dark gap between markers.
    """
    # grey level k is stored as float32(k / 255): compare half a level below to be exact
    sat_thr = float(np.float32((params.saturation_level - 0.5) / 255.0))
    n = len(cand)
    scales, gid = _unique_inverse(cand[:, 5])
    out = (np.empty((n, 2)), np.empty(n), np.empty((n, _SECTORS)), np.empty(n), np.empty(n))
    _measure_kernel(grey, cand, gid, int(params.centroid_iterations), sat_thr,
                    *_offset_tables(tuple(scales.tolist()), params), *out)
    return out


def _offset_tables(scales: tuple[float, ...], params: DetectionParams):
    """The :func:`_group_offsets` of every measuring scale, concatenated for :func:`_measure_kernel`:
    run-away limits (G,), ring dx, dy, pointers (G + 1,), sector starts (G, 9) as absolute indices,
    window dx, dy, pointers, window row spans (S, 3) with pointers and each window's reach (G,),
    core dx, dy, pointers, and each ring's reach (G,). Cached per set of scales (a stream of frames
    sees the same few)."""
    key = (scales, params.centroid_radius_factor)
    hit = _TABLES.get(key)
    if hit is not None:
        return hit
    radii = [float(np.sqrt(2) * sc) for sc in scales]
    groups = [_group_offsets(r, params) for r in radii]
    ptr = lambda k: np.concatenate([[0], np.cumsum([len(gr[k]) for gr in groups])]).astype(np.intp)  # noqa: E731
    cat = lambda k: np.concatenate([gr[k] for gr in groups]).astype(np.intp)                          # noqa: E731
    ring_ptr = ptr(0)
    starts = np.stack([gr[2] + ring_ptr[j] for j, gr in enumerate(groups)]).astype(np.intp)
    # the window as row spans (dy, first dx, last dx), in the offsets' own row-major order
    spans = []
    for gr in groups:
        dys = np.unique(gr[4])
        spans.append(np.array([[dy, gr[3][gr[4] == dy].min(), gr[3][gr[4] == dy].max()] for dy in dys], np.intp))
    span_ptr = np.concatenate([[0], np.cumsum([len(sp) for sp in spans])]).astype(np.intp)
    reach = np.array([int(max(np.abs(gr[3]).max(), np.abs(gr[4]).max())) for gr in groups], np.intp)
    ring_reach = np.array([int(max(np.abs(gr[0]).max(initial=0), np.abs(gr[1]).max(initial=0))) for gr in groups],
                          np.intp)
    hit = (np.array([0.5 * r + 1.0 for r in radii]), cat(0), cat(1), ring_ptr, starts,
           cat(3), cat(4), ptr(3), np.concatenate(spans), span_ptr, reach, cat(5), cat(6), ptr(5), ring_reach)
    if len(_TABLES) > 64:
        _TABLES.clear()
    _TABLES[key] = hit
    return hit


_TABLES: dict[tuple, tuple] = {}


def _ring_spread(xy: np.ndarray, radius: np.ndarray, sectors: np.ndarray, peers: np.ndarray,
                 examine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brightest ring sector (minus the ring median) per candidate, not counting sectors that look at
    a touching marker; and whether the candidate touches one.

    A marker squeezed against its neighbours (pins crowding under a steep flank) has bright ring
    sectors too, but that light is another marker's: sectors whose centre direction lies within
    45 deg of a ``peers`` candidate (one that passed the contrast, shape, saturation and upper size
    tests) closer than the two rings' reach (``1.25 r + 2.5 + r_peer``) are left out. Glare stays
    rejected: a bright region that is not itself a marker-sized blob explains no sector. At least half
    the sectors must remain, else the candidate keeps its plain brightest sector. Only candidates with
    ``examine`` set are looked at (the others keep their plain spread and are not ``crowded``).

    Returns
    -------
    spread : (N,) brightest unexplained sector minus the ring median
    crowded : (N,) bool, a peer touches the candidate's ring
    """
    spread = sectors.max(axis=1)
    crowded = np.zeros(len(xy), dtype=bool)
    idx = np.nonzero(peers)[0]
    if len(idx) < 2 or not examine.any():
        return spread, crowded
    tree = cKDTree(xy[idx])
    reach = _RING_IN * radius + 2.5
    centres = -np.pi + (np.arange(_SECTORS) + 0.5) * (2 * np.pi / _SECTORS)
    for i in np.nonzero(examine)[0]:
        near = [idx[j] for j in tree.query_ball_point(xy[i], reach[i] + radius.max()) if idx[j] != i]
        near = [j for j in near if np.hypot(*(xy[j] - xy[i])) <= reach[i] + radius[j]]
        if not near:
            continue
        crowded[i] = True
        d = xy[near] - xy[i]
        ang = np.arctan2(d[:, 1], d[:, 0])
        off = np.abs((centres[None, :] - ang[:, None] + np.pi) % (2 * np.pi) - np.pi)
        masked = (off < np.pi / 4).any(axis=0)
        if masked.sum() <= _SECTORS // 2:
            spread[i] = sectors[i, ~masked].max()
    return spread, crowded


def _split_centroids(grey: np.ndarray, xy: np.ndarray, radius: np.ndarray, which: np.ndarray,
                     peers: np.ndarray, params: DetectionParams) -> np.ndarray:
    """Centroids of touching markers with each neighbour's light excluded.

    The plain centroid window (``centroid_radius_factor`` x r) of a marker squeezed against another
    takes in the neighbour's edge and is pulled toward it (measured ~1.5 px for a 1 px gap). For the
    candidates in ``which`` the window is split Voronoi-wise: pixels nearer to a ``peers`` centre than
    to this one are left out; background = median of the window's remaining pixels outside 1.25 r.
    Two re-centred passes, as for isolated markers. Returns the updated (N, 2) centres.
    """
    out = xy.copy()
    if not which.any():
        return out
    idx = np.nonzero(peers)[0]
    tree = cKDTree(xy[idx])
    h, w = grey.shape
    for i in np.nonzero(which)[0]:
        r = float(radius[i])
        r_win = params.centroid_radius_factor * r + 0.5
        nb = [idx[j] for j in tree.query_ball_point(xy[i], 2 * r_win) if idx[j] != i]
        c = xy[i].copy()
        for _ in range(max(1, params.centroid_iterations)):
            x0, x1 = int(max(0, np.floor(c[0] - r_win))), int(min(w - 1, np.ceil(c[0] + r_win)))
            y0, y1 = int(max(0, np.floor(c[1] - r_win))), int(min(h - 1, np.ceil(c[1] + r_win)))
            gx, gy = np.meshgrid(np.arange(x0, x1 + 1, dtype=np.float64), np.arange(y0, y1 + 1, dtype=np.float64))
            d2 = (gx - c[0]) ** 2 + (gy - c[1]) ** 2
            own = d2 <= r_win * r_win
            for j in nb:
                own &= d2 < (gx - xy[j, 0]) ** 2 + (gy - xy[j, 1]) ** 2
            v = (grey[y0:y1 + 1, x0:x1 + 1] * _U8_SCALE).astype(np.float64)
            ring = own & (d2 >= (_RING_IN * r) ** 2)
            bg = float(np.median(v[ring])) if ring.any() else 0.0
            wts = np.where(own, np.maximum(v - bg, 0.0), 0.0)
            tot = wts.sum()
            if tot <= 0:
                break
            new = np.array([(wts * gx).sum() / tot, (wts * gy).sum() / tot])
            if np.hypot(*(new - xy[i])) > 0.5 * r + 1.0:
                break
            c = new
        out[i] = c
    return out


def _inside_hull(xy: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(N,) bool: ``xy`` inside the marker field: the convex hull of ``ref`` grown by half the median
    nearest-neighbour spacing of ``ref`` away from its centroid (an outer-ring marker that failed the
    strict tests sits on the hull's edge, not inside it). False everywhere for < 3 points or a
    degenerate hull."""
    from scipy.spatial import Delaunay, QhullError

    if len(ref) < 3:
        return np.zeros(len(xy), bool)
    spacing = float(np.median(cKDTree(ref).query(ref, k=2)[0][:, 1]))
    c = ref.mean(axis=0)
    r = np.maximum(np.hypot(*(ref - c).T), 1e-9)[:, None]
    grown = c + (ref - c) * (1.0 + 0.5 * spacing / r)
    try:
        return Delaunay(grown).find_simplex(xy) >= 0
    except QhullError:
        return np.zeros(len(xy), bool)


def _ring_background(grey: np.ndarray, xy: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Median of the background ring (as the photometry's: 1.25 r + 1 .. 1.25 r + 2.5 px about the
    rounded centre) per centre, on the [0, 1] scale; NaN where the ring is wholly outside the image."""
    h, w = grey.shape
    out = np.full(len(xy), np.nan)
    for i, ((u, v), r) in enumerate(zip(xy, radius)):
        dx, dy = _group_offsets(float(r), DetectionParams())[:2]
        x, y = int(np.rint(u)) + dx, int(np.rint(v)) + dy
        ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        if ok.any():
            out[i] = float(np.median(grey[y[ok], x[ok]])) / 255.0
    return out


def _spacing_suppress(xy: np.ndarray, response: np.ndarray, fraction: float) -> np.ndarray:
    """Keep mask: of two centres closer than ``fraction`` x the median nearest-neighbour spacing the
    weaker response is dropped (strongest first, so a dropped centre never removes another)."""
    tree = cKDTree(xy)
    d, _ = tree.query(xy, k=2)
    radius = fraction * float(np.median(d[:, 1]))
    keep = np.ones(len(xy), bool)
    for i in np.argsort(-response, kind="stable"):
        if not keep[i]:
            continue
        for j in tree.query_ball_point(xy[i], radius):
            if j != i and keep[j] and np.hypot(*(xy[j] - xy[i])) < radius:
                keep[j] = False
    return keep


def detect_markers(image: np.ndarray, *, params: DetectionParams = DetectionParams()) -> Blobs:
    """Detect bright circular markers in one camera view.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
        One view (grey or BGR), any size; e.g. ``StereoFrame.left``.
    params : DetectionParams
        Scales, thresholds and rejection rules.

    Returns
    -------
    Blobs
        ``xy_px`` (N, 2) float64 sub-pixel centres (u, v), pixel-centre convention of
        :mod:`pipeline.types`; ``sigma_px`` (N,) detection scale (radius ~ sqrt(2) sigma);
        ``response`` (N,) scale-normalised DoH. Sorted by ``v`` then ``u``. Empty images, blank or
        saturated images give ``Blobs.empty()``.

    Raises
    ------
    DataError
        ``image`` is not a uint8 grey/BGR array.

    Notes
    -----
    Markers below ~2 px radius (sigma < 1.4) or above ~12 px are not found with the default scales.
    Centre accuracy on noise-free anti-aliased discs of radius >= 3 px is a few hundredths of a pixel
    (tests/test_detection.py). Dark-on-bright blobs are ignored by design.
    """
    grey = to_grey(image)
    if grey.size == 0 or min(grey.shape) < 8:
        return Blobs.empty()
    cand_all = _candidates(grey, params)
    cand = _suppress(cand_all, params.min_separation_px)
    if len(cand) == 0:
        return Blobs.empty()
    xy, contrast, sectors, sat, core_sat = _refine_and_measure(grey, cand, params)
    debris = np.zeros(len(cand), bool)
    if params.rejections and params.debris_size_ratio is not None:
        # debris (specks far smaller than the typical marker) is suppressed apart from the markers, so
        # that a speck on a marker cannot shadow it; it is measured still, as a blob that may light a
        # neighbour's ring (see _ring_spread), and never kept
        typical = ((contrast >= params.min_contrast) & (cand[:, 4] <= params.max_elongation)
                   & (sat <= params.max_saturated_fraction)
                   & (sectors.max(axis=1) <= params.isolation * np.maximum(contrast, 1e-6)))
        if typical.sum() >= 5:
            small_all = cand_all[:, 2] < float(np.median(cand[typical, 2])) / params.debris_size_ratio
            parts = [_suppress(cand_all[~small_all], params.min_separation_px),
                     _suppress(cand_all[small_all], params.min_separation_px)]
            cand = np.concatenate(parts)
            debris = np.arange(len(cand)) >= len(parts[0])
            xy, contrast, sectors, sat, core_sat = _refine_and_measure(grey, cand, params)
    keep = contrast >= params.min_contrast
    if params.rejections:
        keep &= cand[:, 4] <= params.max_elongation
        keep &= sat <= params.max_saturated_fraction
        limit = params.isolation * np.maximum(contrast, 1e-6)
        isolated = sectors.max(axis=1) <= limit
        if (keep & isolated & ~debris).sum() >= 5:
            # outliers against the typical marker of this image: size (a marker squeezed between
            # touching neighbours reads smaller: down to 1/ratio**2), and saturation where markers
            # are not saturated (LED glare is; exposure-clipped markers all are)
            med = float(_median(cand[keep & isolated & ~debris, 2]))
            big_ok = cand[:, 2] <= params.max_size_ratio * med
            small = cand[:, 2] < med / params.max_size_ratio
            inside = np.zeros(len(cand), bool)
            if params.isolation_inside is not None or debris.any():
                # the marker field: the convex hull of the markers that pass the strict tests
                inside = _inside_hull(xy, xy[keep & isolated & big_ok & ~small & ~debris])
            if params.isolation_inside is not None:
                limit = np.where(inside, params.isolation_inside * np.maximum(contrast, 1e-6), limit)
            # debris explains a lit ring sector only within the marker field (specks at the edge of
            # glare outside it must not excuse the glare)
            peers = keep & big_ok & (~debris | inside)
            spread, crowded = _ring_spread(xy, np.sqrt(2) * cand[:, 5], sectors, peers, keep & (~isolated | small))
            keep &= (spread <= limit) & big_ok
            keep &= ~small | (crowded & (cand[:, 2] >= med / params.max_size_ratio ** 2))
            if params.debris_size_ratio is not None:
                keep &= (cand[:, 2] >= med / params.debris_size_ratio) & ~debris
            if params.max_background_ratio is not None and keep.any():
                idx = np.nonzero(keep)[0]
                bg = _ring_background(grey, xy[idx], np.sqrt(2) * cand[idx, 5])
                keep[idx[~(bg <= params.max_background_ratio * contrast[idx])]] = False
            # (debris touching a marker is excluded from its centroid as a touching marker is)
            xy = _split_centroids(grey, xy, np.sqrt(2) * cand[:, 5], keep & crowded, (keep & big_ok) | (peers & debris),
                                  params)
            if _median(core_sat[keep]) < 0.5:
                keep &= core_sat <= 0.3
        else:
            keep &= isolated & ~debris
    h, w = grey.shape
    b = params.border_px
    keep &= (xy[:, 0] >= b) & (xy[:, 0] <= w - 1 - b) & (xy[:, 1] >= b) & (xy[:, 1] <= h - 1 - b)
    xy, cand = xy[keep], cand[keep]
    if params.min_spacing_fraction is not None and len(xy) >= 3:
        keep = _spacing_suppress(xy, cand[:, 3], params.min_spacing_fraction)
        xy, cand = xy[keep], cand[keep]
    order = np.lexsort((xy[:, 0], xy[:, 1]))
    return Blobs(xy[order], cand[order, 2], cand[order, 3])
