"""The right view coded in a worker process (pipeline.view_process): the same frames as on one thread, also when
the worker dies mid-stream, and a CLI run with it."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.latency import _with_defects
from pipeline.design import load_design
from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration, synth_stereo_frame
from pipeline.runner import Reconstructor


def _sequence(name: str, defects: float, n: int = 8, seed: int = 3):
    design = load_design(name)
    calib = nominal_calibration(design)
    rng = np.random.default_rng(seed)
    frames = []
    for k, depth in enumerate(np.r_[np.linspace(0.0, 3.0, n - 2), 1.5, 0.0]):
        xyz = gaussian_press_markers(design, float(depth), sigma_mm=4.0)
        frame = synth_stereo_frame(design, calib, xyz, rng=rng, index=k)
        frames.append(_with_defects(frame, design, calib, xyz, defects, rng) if defects else frame)
    return design, calib, frames


def _same(a, b) -> None:
    assert np.array_equal(a.matches.ids, b.matches.ids)
    assert np.array_equal(a.matches.left_px, b.matches.left_px)
    assert np.array_equal(a.matches.right_px, b.matches.right_px)
    assert np.array_equal(a.corrected.xyz_mm, b.corrected.xyz_mm)
    assert a.unmatched_reasons == b.unmatched_reasons


@pytest.mark.parametrize("name,defects", [("circular217_dome", 0.03), ("hexagon127", 0.05), ("square121", 0.0)])
def test_the_worker_process_codes_what_the_runner_would(name, defects):
    """Every frame of a pressed sequence with missing and spurious blobs in both views: the same ids, pixels,
    points and reasons with the right view coded in the worker as on one thread, the worker used throughout
    (no fallback), and sensible: most markers matched."""
    design, calib, frames = _sequence(name, defects)
    here = Reconstructor(design, calib, view_threads=1)
    there = Reconstructor(design, calib, view_threads=1, view_process=True)
    try:
        for frame in frames:
            a, b = here.process(frame), there.process(frame)
            assert there.view_process_error is None
            assert there._right._proc is not None
            _same(a, b)
            assert a.n_matched >= 0.85 * design.marker_count
    finally:
        there.close()


def test_a_worker_that_dies_mid_stream_is_replaced_by_the_runner():
    """Killing the worker between frames: the next frame is coded in the runner's process, says why, and every
    frame still equals the one-thread run (the runner's tracker holds the same state)."""
    design, calib, frames = _sequence("hexagon127", 0.03)
    here = Reconstructor(design, calib, view_threads=1)
    there = Reconstructor(design, calib, view_threads=1, view_process=True)
    try:
        for k, frame in enumerate(frames):
            if k == 4:
                proc = there._right._proc._proc
                proc.kill()
                proc.wait()
            _same(here.process(frame), there.process(frame))
        assert there._right._proc is None
        assert "view worker" in there.view_process_error
    finally:
        there.close()


def test_reconstruct_cli_with_the_view_process(tmp_path):
    """``reconstruct --view-process`` on recorded frames with defects writes the same markers, frame by frame,
    as ``--view-threads 1``."""
    import argparse

    import cv2

    from pipeline.cli import geometry as cli_geometry

    design, calib, frames = _sequence("hexagon127", 0.03, n=5)
    calib.save_yaml(tmp_path / "calib.yaml")
    src = tmp_path / "frames"
    src.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(src / f"frame_{k:04d}.png"), f.image)
    parser = argparse.ArgumentParser()
    cli_geometry.register(parser.add_subparsers(dest="command", required=True))
    for tag, extra in (("thread", ["--view-threads", "1"]), ("process", ["--view-process"])):
        args = parser.parse_args(["reconstruct", str(src), "--calib", str(tmp_path / "calib.yaml"), "--design",
                                  "hexagon127", "--out", str(tmp_path / tag), *extra])
        assert args.func(args) == 0
    for k in range(len(frames)):
        name = f"markers_{k:04d}.csv"
        assert (tmp_path / "thread" / name).read_bytes() == (tmp_path / "process" / name).read_bytes(), name


def test_the_worker_reads_a_view_from_the_shared_buffer_and_a_larger_one_as_bytes():
    """A strided right half of a stereo frame goes through the buffer both processes map; an image larger than
    that buffer goes over the socket as bytes. The worker's blobs equal the detector's in this process either way,
    and a buffer written again for the next view is read anew (the worker detects each view where it lies, and
    answers before the runner writes the next one)."""
    import os

    import pipeline.view_process as vp
    from pipeline.vision.detection import DetectionParams, detect_markers

    if not hasattr(os, "memfd_create"):
        pytest.skip("no memfd on this platform: every view goes as bytes")

    design, calib, frames = _sequence("hexagon127", 0.0, n=4)
    big = np.zeros((1000, 1000), np.uint8)
    big[:480, :640] = frames[0].right
    proc = vp.ViewProcess(design, None)
    try:
        assert proc._shared is not None and big.nbytes > vp.SHARED_IMAGE_BYTES
        for image in (frames[1].right, frames[3].right, big):
            assert not image.flags.c_contiguous or image is big
            proc.submit(image, DetectionParams())
            blobs = proc.result()[0]
            here = detect_markers(image)
            assert len(here) > 0.9 * design.marker_count
            assert np.array_equal(blobs.xy_px, here.xy_px)
    finally:
        proc.close()
