"""Latency benchmark: raw stereo frame -> reconstructed skin, per stage, on one core.

Frames are analytic (:mod:`pipeline.synthetic`): a Gaussian press whose depth sweeps 0-3 mm over
the run, so every frame differs. The paper reports 283 ms per frame (MATLAB/Python, Ryzen 7 5800X);
the goal here is <= 5 ms median.

Stages are the runner's: ``detect`` (both views), ``match`` (DTRC), ``stereo_check``, ``triangulate``,
``refraction``, ``surface``, and ``total``. With the exact model the stereo check's ray tracing IS the
refraction correction (the runner reuses its cloud), so its time is under ``stereo_check`` and
``refraction`` is ~0.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from pipeline.design import load_design
from pipeline.runner import Reconstructor
from pipeline.synthetic import gaussian_press_markers, nominal_calibration, synth_stereo_frame

__all__ = ["run_latency", "PAPER_LATENCY_MS", "GOAL_MEDIAN_MS"]

PAPER_LATENCY_MS = 283.0
GOAL_MEDIAN_MS = 5.0


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"median_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95)), "mean_ms": float(a.mean()),
            "max_ms": float(a.max())}


def _busy_processes(n: int) -> list:
    """``n`` processes spinning on a core each: a stated background load."""
    import subprocess
    import sys

    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def run_latency(design_names: tuple[str, ...] = ("hexagon127", "circular217_dome"), n_frames: int = 200,
                out_dir: str | Path | None = None, *, refraction: str = "exact", seed: int = 0,
                n_distinct_frames: int = 20, progress: bool = True, background_procs: int = 0) -> dict:
    """Time the whole runner per stage on synthetic frames (the runner holds BLAS, OpenMP and
    OpenCV at one thread per frame: :mod:`pipeline.threads`).

    Parameters
    ----------
    design_names : designs to time
    n_frames : frames processed per design (the first, warm-up frame is excluded from the statistics)
    out_dir : if given, writes ``out_dir/latency.json``
    n_distinct_frames : distinct synthetic frames rendered (press depths 0-3 mm), cycled through
    background_procs : processes spinning on a core each while the frames are timed (a stated
        background load; 0 = none)

    Returns
    -------
    dict with, per design, median / p95 / mean / max per stage and in total (ms), matched-marker counts,
    and the machine description.
    """
    from tqdm import tqdm

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(seed)
    result: dict = {"paper_ms": PAPER_LATENCY_MS, "goal_median_ms": GOAL_MEDIAN_MS, "n_frames": n_frames,
                    "refraction": refraction, "seed": seed, "opencv_threads": 1,
                    "background_procs": int(background_procs),
                    "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                                "cpu_count": os.cpu_count(), "opencv": cv2.__version__, "numpy": np.__version__},
                    "designs": {}}
    load = _busy_processes(int(background_procs))
    try:
        for name in design_names:
            design = load_design(name)
            calib = nominal_calibration(design)
            depths = np.linspace(0.0, 3.0, n_distinct_frames)
            frames = [synth_stereo_frame(design, calib, gaussian_press_markers(design, float(d), sigma_mm=4.0),
                                         rng=rng, index=k) for k, d in enumerate(depths)]
            rec = Reconstructor(design, calib, refraction=refraction)
            stages: dict[str, list[float]] = {}
            matched = []
            rec.process(frames[0])  # warm-up: caches, first-call imports
            for k in tqdm(range(n_frames), desc=f"latency {name}", disable=not progress, leave=False):
                res = rec.process(frames[k % len(frames)])
                for stage, ms in res.timings_ms.items():
                    stages.setdefault(stage, []).append(ms)
                matched.append(res.n_matched)
            result["designs"][name] = {
                "markers": design.marker_count,
                "matched_min": int(min(matched)), "matched_median": float(np.median(matched)),
                "stages": {s: _stats(v) for s, v in stages.items()},
            }
    finally:
        cv2.setNumThreads(threads)
        for proc in load:
            proc.terminate()
            proc.wait()
    result["timestamp"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        from pipeline.atomic import atomic_write_json

        atomic_write_json(out / "latency.json", result, indent=1)
    return result
