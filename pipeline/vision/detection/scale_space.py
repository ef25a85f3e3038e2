"""Scale space: scale-normalised determinant of Hessian on the pyramid levels, and its candidates."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from pipeline.vision.detection import candidates
from pipeline.vision.detection.candidates import RADIUS_PER_SIGMA
from pipeline.vision.detection.images import CACHE_ENTRIES, Workspace
from pipeline.vision.detection.params import DetectionParams
from pipeline.vision.detection.peaks import doh_peaks, peak_kernel
from pipeline.vision.detection.pyramid import pyramid_level


#: Gaussian kernels reach this many sigmas each side (OpenCV's own size for float images, so the fused
#: kernels reproduce GaussianBlur + 3-tap differences).
_TRUNCATE_SIGMAS = 4
#: A pyramid level smaller than this (px, either side) has no room for peaks inside the border: its
#: scale is skipped.
_MIN_LEVEL_SIDE_PX = 5
#: The blur applied on a level is at least this fraction of the scale's variance (the box averaging
#: of the reduction never stands in for more than three quarters of the blur).
_MIN_OWN_VARIANCE_FRACTION = 0.25


def hessian_kernels(sigma: float, norm: float):
    """1-D kernels (smooth, second difference, first difference) of a Gaussian of ``sigma`` (level px)
    convolved with the 3-tap differences, scaled by ``norm**2`` / ``norm`` so that the Hessian comes
    out scale-normalised. Same result as GaussianBlur followed by the 3-tap filters (OpenCV's own
    kernel size for float images), in 3 instead of 4 image passes."""
    key = (sigma, norm)
    hit = _KERNELS.get(key)
    if hit is None:
        ksize = int(round(sigma * _TRUNCATE_SIGMAS * 2 + 1)) | 1
        g = cv2.getGaussianKernel(ksize, sigma, cv2.CV_64F).ravel()
        gxx = np.convolve(g, [1.0, -2.0, 1.0]) * norm**2
        gx = np.convolve(g, [0.5, 0.0, -0.5]) * norm  # correlation with [-0.5, 0, 0.5] after g
        g0 = np.concatenate([[0.0], g, [0.0]])
        hit = _KERNELS[key] = tuple(k.astype(np.float32) for k in (g0, gxx, gx))
    return hit


_KERNELS: dict[tuple, tuple] = {}


def hessian(level: np.ndarray, sigma: float, norm_sigma: float, out: list[np.ndarray]) -> None:
    """Scale-normalised Hessian entries Lxx, Lyy, Lxy of one pyramid level into ``out``.

    ``sigma`` is the blur applied here; ``norm_sigma`` the total scale, in level px, used to normalise
    (``norm_sigma**2`` times the second derivatives). Each entry is one separable OpenCV filter with
    the Gaussian and the 3-tap difference fused (:func:`hessian_kernels`).
    """
    g0, gxx, gx = hessian_kernels(float(sigma), float(norm_sigma))
    cv2.sepFilter2D(level, -1, gxx, g0, dst=out[0])
    cv2.sepFilter2D(level, -1, g0, gxx, dst=out[1])
    cv2.sepFilter2D(level, -1, gx, gx, dst=out[2])


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
    """What :func:`find_candidates` does per scale on an image of this shape: the pyramid level of each
    scale, its blur, normalising scale and border (level px), where its maps sit in the packed buffers,
    and the per-scale arrays of :func:`peak_kernel`. A function of the image shape and the scales only,
    so it is worked out once per (shape, scales, border) and kept; building it computes the levels
    into ``cache``. None when no scale has a level of at least ``_MIN_LEVEL_SIDE_PX``."""
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
        level, fx, fy = pyramid_level(grey, int(j), cache)
        levels.append((level, fx, fy) if min(level.shape) >= _MIN_LEVEL_SIDE_PX else None)
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
            # blur on top of the box averaging (a box of f px adds (f**2 - 1) / 12 px**2 of variance to
            # the pixel's own) so that the total scale is s_full
            s_blur = math.sqrt(max(s_full**2 - max(f * f - 1, 0.0) / 12.0, _MIN_OWN_VARIANCE_FRACTION * s_full**2)) / f
            b = max(1, int(math.ceil(params.border_px / min(fx, fy))))  # >= 1: neighbours stay on the level
            steps.append((float(s_blur), float(s_full / f), b, int(offs[i_s]), int(offs[i_s + 1]), level.shape))
        plan = ([int(j) for j in level_of], steps, total, offs, hs, ws, fxs, fys, log_s)
    if len(_PLANS) > CACHE_ENTRIES:
        _PLANS.clear()
    _PLANS[key] = (plan,)
    return plan


_PLANS: dict[tuple, tuple] = {}


def find_candidates(grey: np.ndarray, params: DetectionParams) -> np.ndarray:
    """Scale-space maxima: the (N, COLUMNS) candidate record of :mod:`.candidates` (position, continuous
    scale, response, elongation, measuring scale).

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
        return candidates.empty()
    level_of, steps, total, offs, hs, ws, fxs, fys, log_s = plan
    packs = [Workspace.get(f"pack_{q}", (total,)) for q in ("doh", "lxx", "lyy", "lxy")]
    peaks = Workspace.get("pack_peaks", (total,), np.intp)
    n_peaks = 0
    threshold = float(params.threshold)
    for i_s, step in enumerate(steps):
        if step is None:
            continue
        s_blur, norm, b, o0, o1, shp = step
        level = pyramid_level(grey, level_of[i_s], cache)[0]
        views = [p[o0:o1].reshape(shp) for p in packs]
        hessian(level, s_blur, norm, views[1:])
        n_peaks = doh_peaks(*views[1:], views[0], threshold, b, o0, peaks, n_peaks)
    if n_peaks == 0:
        return candidates.empty()
    return peak_kernel(peaks[:n_peaks], *packs, offs, hs, ws, fxs, fys, log_s)


#: Half-side (px) of the window about a candidate in which :func:`scale_below_lowest` runs the scale space
#: again; a multiple of 8 so the window's pyramid levels start on whole pixels of the image's.
_RESIZE_HALF_PX = 32


def scale_below_lowest(grey: np.ndarray, cand: np.ndarray, which: np.ndarray, params: DetectionParams) -> np.ndarray:
    """The scales of the candidates ``which`` (indices), each re-measured where it sits at the lowest scale
    of a narrowed scale space (others as they are).

    A scale space narrowed to the markers' size (:meth:`DetectionParams.for_marker_radius`) cannot size a
    blob whose response peaks at its lowest scale: there is no finer scale for the parabola, so the
    scale stays at the lowest, about one grid step (1.41) below the markers' own and just under the size
    test's limit (``max_size_ratio`` 1.4). A pin seen edge-on at the edge of a view or on the far flank
    of a narrow press (0.72-0.78 of its neighbours' scale in the full scale space) would be rejected as
    small where the full scale space keeps it. Each such candidate's window (:data:`_RESIZE_HALF_PX`)
    is searched again at the grid's scale below the lowest, the lowest and the next, and the candidate
    takes the scale of the peak found there within half its radius. The full scale space's own lowest
    is the detector's floor: nothing to re-measure."""
    sig = sorted(params.sigmas_px)
    out = cand[which, candidates.SIGMA].copy()
    finer = [s_ for s_ in DetectionParams().sigmas_px if s_ < sig[0] - 1e-9]
    if not finer or len(sig) < 2:
        return out
    lo = sig[0]
    local = replace(params, sigmas_px=(max(finer), lo, sig[1]))
    h, w = grey.shape
    side = 2 * _RESIZE_HALF_PX + 8                 # one window shape: its plan and buffers are reused
    for r, i in enumerate(which):
        if cand[i, candidates.SIGMA] > lo * (1 + 1e-9):
            continue
        x0 = min(max(0, (int(cand[i, candidates.X]) - _RESIZE_HALF_PX) // 8 * 8), max(0, w - side))
        y0 = min(max(0, (int(cand[i, candidates.Y]) - _RESIZE_HALF_PX) // 8 * 8), max(0, h - side))
        found = find_candidates(np.ascontiguousarray(grey[y0:y0 + side, x0:x0 + side]), local)
        if len(found) == 0:
            continue
        d = np.hypot(found[:, candidates.X] + x0 - cand[i, candidates.X],
                     found[:, candidates.Y] + y0 - cand[i, candidates.Y])
        k = int(np.argmin(d))
        if d[k] <= 0.5 * RADIUS_PER_SIGMA * lo:
            out[r] = found[k, candidates.SIGMA]
    return out
