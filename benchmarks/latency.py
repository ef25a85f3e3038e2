"""Latency benchmark of the pipeline: raw stereo frame -> reconstructed skin, per stage.

Frames are analytic (:mod:`pipeline.io.synthetic`): a Gaussian press whose depth sweeps 0-3 mm over
the run, so every frame differs. The paper reports 283 ms per frame (MATLAB/Python, Ryzen 7 5800X);
the goal here is <= 5 ms median.

Stages are the runner's: ``detect`` (both views), ``match`` (DTRC), ``stereo_check``, ``triangulate``,
``refraction``, ``surface``, and ``total``. With the exact model the stereo check's ray tracing IS the
refraction correction (the runner reuses its cloud), so its time is under ``stereo_check`` and
``refraction`` is ~0.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from pipeline.design import load_design
from pipeline.priority import cpu_latency, frame_priority
from pipeline.runner import Reconstructor
from pipeline.threads import default_view_threads
from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration, synth_stereo_frame

__all__ = ["run_latency", "reference_workload_ms", "PAPER_LATENCY_MS", "GOAL_MEDIAN_MS"]

PAPER_LATENCY_MS = 283.0
GOAL_MEDIAN_MS = 5.0


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"median_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95)), "mean_ms": float(a.mean()),
            "max_ms": float(a.max())}


_REF_IMAGE = np.random.default_rng(12345).integers(0, 256, (480, 640), dtype=np.uint8)
_REF_MATRIX = np.random.default_rng(54321).standard_normal((96, 96))


def reference_workload_ms(repeats: int = 1) -> float:
    """Wall time (ms, median of ``repeats``) of a fixed single-threaded job of the kind the pipeline does: a
    scale-space Hessian of one 640×480 view (two Gaussian blurs and second derivatives) and a small
    dense solve.

    Timed interleaved with the frames, it is the machine's speed and load at that moment, so latency in
    units of it (``median_total_ms / median reference``) compares across machines and loads where an
    absolute time does not: the CI gate on speed is a ratio against it.
    """
    from pipeline.threads import one_thread

    times = []
    with one_thread():
        for _ in range(max(1, int(repeats))):
            t0 = time.perf_counter()
            img = _REF_IMAGE.astype(np.float32)
            for sigma in (1.5, 3.0):
                g = cv2.GaussianBlur(img, (0, 0), sigma)
                dxx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3)
                dyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
                dxy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
                _ = float((dxx * dyy - dxy * dxy).max())
            np.linalg.solve(_REF_MATRIX + 96 * np.eye(96), np.ones(96))
            times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def _busy_processes(n: int) -> list:
    """``n`` processes spinning on a core each: a stated background load."""
    import subprocess
    import sys

    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _with_defects(frame, design, calib, xyz: np.ndarray, rate: float, rng: np.random.Generator):
    """``frame`` with, in each view, ``rate`` of the markers hidden (painted over with the background) and as
    many spurious bright discs (a third of a separation across, at least 0.7 separations from every marker)
    placed over the pattern: the blobs a real view loses to glare and dust and gains from reflections."""
    import cv2

    from pipeline.geometry.refraction import project_through_stack
    from pipeline.io.synthetic import BACKGROUND_GREY, MARKER_GREY
    from pipeline.types import StereoFrame
    from pipeline.vision.nearest import nearest_other_distances

    n = int(round(rate * len(xyz)))
    views = [frame.left.copy(), frame.right.copy()]
    for view, px in zip(views, project_through_stack(xyz, calib, design)):
        sep = float(np.median(nearest_other_distances(np.ascontiguousarray(px, np.float64))))
        for i in rng.choice(len(px), n, replace=False):
            cv2.circle(view, (int(round(px[i, 0])), int(round(px[i, 1]))), int(round(0.45 * sep)), BACKGROUND_GREY, -1)
        lo, hi, added = px.min(axis=0), px.max(axis=0), 0
        while added < n:
            q = rng.uniform(lo, hi)
            if np.hypot(*(px - q).T).min() > 0.7 * sep:
                cv2.circle(view, (int(round(q[0])), int(round(q[1]))), max(1, int(round(sep / 6))), MARKER_GREY, -1,
                           cv2.LINE_AA)
                added += 1
    return StereoFrame.from_pair(views[0], views[1], index=frame.index, timestamp_s=frame.timestamp_s,
                                 source="synthetic")


def _time_design(design, n_frames: int, refraction: str, rng: np.random.Generator, n_distinct_frames: int,
                 progress: bool, view_threads: int | None = None, defects: float = 0.0,
                 view_process: bool = False) -> dict:
    """One design's timing in :func:`run_latency`: ``n_frames`` synthetic press frames through a fresh
    runner, each preceded by the reference job, after one warm-up frame."""
    from tqdm import tqdm

    calib = nominal_calibration(design)
    depths = np.linspace(0.0, 3.0, n_distinct_frames)
    frames = []
    for k, d in enumerate(depths):
        xyz = gaussian_press_markers(design, float(d), sigma_mm=4.0)
        frame = synth_stereo_frame(design, calib, xyz, rng=rng, index=k)
        frames.append(_with_defects(frame, design, calib, xyz, defects, rng) if defects > 0 else frame)
    rec = Reconstructor(design, calib, refraction=refraction, view_threads=view_threads, view_process=view_process)
    stages: dict[str, list[float]] = {}
    matched = []
    reference = []
    rec.process(frames[0])  # warm-up: caches, first-call imports
    reference_workload_ms()
    for k in tqdm(range(n_frames), desc=f"latency {design.name}", disable=not progress, leave=False):
        reference.append(reference_workload_ms())     # interleaved: the machine's speed at this moment
        res = rec.process(frames[k % len(frames)])
        for stage, ms in res.timings_ms.items():
            stages.setdefault(stage, []).append(ms)
        matched.append(res.n_matched)
    if rec.view_process_error:
        raise RuntimeError(f"latency {design.name}: {rec.view_process_error}")
    rec.close()
    return {
        "markers": design.marker_count,
        "matched_min": int(min(matched)), "matched_median": float(np.median(matched)),
        "stages": {s: _stats(v) for s, v in stages.items()},
        "reference_ms": _stats(reference),
        "total_over_reference": float(np.median(stages["total"]) / np.median(reference)),
    }


def run_latency(design_names: tuple[str, ...] = ("hexagon127", "circular217_dome"), n_frames: int = 200,
                out_dir: str | Path | None = None, *, refraction: str = "exact", seed: int = 0,
                n_distinct_frames: int = 20, progress: bool = True, background_procs: int = 0,
                nice: int | None = None, view_threads: int | None = None, defects: float = 0.0,
                view_process: bool = False, cpu_latency_us: int | None = None) -> dict:
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
    nice : the frames are processed at this niceness (:func:`pipeline.priority.frame_priority`; None: the
        process's own); the spinning processes keep theirs
    view_threads : 1 or 2 (the runner's ``view_threads``; None: its default, 2 on two or more CPUs)
    view_process : the right view in a worker process (the runner's ``view_process``), not on a thread
    cpu_latency_us : while the frames are timed, every CPU is asked to wake within this many microseconds
        (:func:`pipeline.priority.cpu_latency`; 0: idle CPUs poll; None: the system's own)
    defects : fraction of the markers hidden, and as many spurious blobs added, in each view of each frame
        (:func:`_with_defects`; 0 = clean frames)

    Returns
    -------
    dict with, per design, median / p95 / mean / max per stage and in total (ms), matched-marker counts,
    and the machine description.
    """
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(seed)
    result: dict = {"paper_ms": PAPER_LATENCY_MS, "goal_median_ms": GOAL_MEDIAN_MS, "n_frames": n_frames,
                    "refraction": refraction, "seed": seed, "opencv_threads": 1,
                    "background_procs": int(background_procs), "defects": float(defects),
                    "view_threads": default_view_threads() if view_threads is None else int(view_threads),
                    "view_process": bool(view_process),
                    "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                                "cpu_count": os.cpu_count(), "opencv": cv2.__version__, "numpy": np.__version__},
                    "designs": {}}
    load = _busy_processes(int(background_procs))
    try:
        with frame_priority(nice) as niceness, cpu_latency(cpu_latency_us) as wake_us:
            result["niceness"], result["cpu_latency_us"] = niceness, wake_us
            for name in design_names:
                result["designs"][name] = _time_design(load_design(name), n_frames, refraction, rng,
                                                       n_distinct_frames, progress, view_threads, float(defects),
                                                       bool(view_process))
    finally:
        cv2.setNumThreads(threads)
        for proc in load:
            proc.terminate()
            proc.wait()
    result["timestamp"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        from pipeline.io.atomic import atomic_write_json

        atomic_write_json(out / "latency.json", result, indent=1)
    return result
