"""The numba warm-up: every compiled kernel of the pipeline's common path, and of frames with missing and
spurious blobs, compiled (or loaded from numba's cache) before the first real frame needs it."""

from __future__ import annotations

import time

import numpy as np

from pipeline.runner import Reconstructor
from pipeline.types import Blobs

__all__ = ["compile_kernels"]


def compile_kernels() -> float:
    """Run the whole chain on analytic frames so that numba compiles (or loads from its cache) every kernel of
    the common path and of frames with missing blobs; returns the seconds it took: ~30-35 s after an install on
    the 2-core reference machine, well under a second from the cache. ``make setup`` calls it so that the first
    real frame does not pay."""
    from pipeline.design import DEFAULT_DESIGN, load_design
    from pipeline.vision.detection.detect import compile_crowded_kernels, detect_markers
    from pipeline.vision.dtrc import code_rings
    from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration, synth_stereo_frame

    t0 = time.perf_counter()
    design = load_design(DEFAULT_DESIGN)
    calib = nominal_calibration(design)
    rec = Reconstructor(design, calib)
    for depth in (0.0, 2.0):
        frame = synth_stereo_frame(design, calib, gaussian_press_markers(design, depth))
        rec.process(frame)            # strided half-frame views, as from a camera
    # a single contiguous view (the detect command); then without its three middle markers and with a spurious
    # blob far out, alone and in two frames in a row (the frame-to-frame map, its lost-neighbours test, the
    # carried places, re-acquisition: a real sensor's frames lose a blob now and then)
    b, right = detect_markers(np.ascontiguousarray(frame.left)), detect_markers(np.ascontiguousarray(frame.right))
    k = np.argsort(np.hypot(*(b.xy_px - b.xy_px.mean(axis=0)).T))[3:]
    defects = Blobs(np.vstack([b.xy_px[k], [[2.0, 2.0]]]), b.sigma_px[np.r_[k, 0]], b.response[np.r_[k, 0]])
    for view in (b, defects):
        code_rings(view, design)
    for _ in range(2):
        rec.identify(defects, right)
    compile_crowded_kernels()         # touching and overlapping pins, which these frames do not show
    return time.perf_counter() - t0
