"""The pipeline's own view worker (pipeline.threads.both_views) and the runner on it: the two views of a
frame give the same result on two threads as on one, a busy or missing worker never stalls a frame, errors
reach the caller, and the worker runs at the caller's niceness. How much time it saves is measured by
`stereotactip bench latency --param view_threads=1|2`, not asserted here."""

from __future__ import annotations

import multiprocessing
import threading

import numpy as np
import pytest

from pipeline.design import load_design
from pipeline.priority import current_niceness, frame_priority
from pipeline.runner import Reconstructor, RunnerError
from pipeline.threads import ViewPolicy, _worker, both_views
from synth_frames import gaussian_press_markers, nominal_calibration, synth_stereo_frame


def _where(view, arg):
    return view, arg, threading.get_ident()


def test_both_views_returns_left_then_right_and_checks_its_thread_count():
    (lv, la, lt), (rv, ra, _) = both_views(_where, "L", "R")
    assert (lv, la, rv, ra) == (0, "L", 1, "R")
    assert lt == threading.get_ident()                   # the left view always runs on the caller
    assert [r[:2] for r in both_views(_where, "L", "R", threads=1)] == [(0, "L"), (1, "R")]
    assert all(r[2] == threading.get_ident() for r in both_views(_where, "L", "R", threads=1))
    with pytest.raises(ValueError, match="view threads"):
        both_views(_where, "L", "R", threads=3)


def test_a_busy_worker_does_not_hold_the_frame():
    """With the worker held by other work, the caller takes the right view back and runs it itself."""
    release = threading.Event()
    blocker = _worker().submit(release.wait, 30)
    try:
        (_, _, lt), (_, _, rt) = both_views(_where, "L", "R")
        assert lt == rt == threading.get_ident()
    finally:
        release.set()
    assert blocker.result(timeout=30)


def test_waited_is_reported_and_zero_when_the_caller_ran_the_right_view():
    release = threading.Event()
    blocker = _worker().submit(release.wait, 30)
    waited: list = []
    try:
        both_views(_where, "L", "R", waited=waited)
    finally:
        release.set()
    blocker.result(timeout=30)
    assert waited == [0.0]
    both_views(lambda view, _: threading.Event().wait(0.05 * view), None, None, waited=waited)
    assert len(waited) == 2 and 0.0 <= waited[1] < 5.0


def test_a_worker_that_keeps_the_frame_waiting_is_set_aside_for_a_while():
    policy = ViewPolicy(2)
    assert policy.next() == 2
    for _ in range(10):                                  # the right view ends with the left: stays on two threads
        policy.record(own_s=1e-3, waited_s=0.1e-3)
        assert policy.next() == 2
    for k in range(10):                                  # the caller waits as long as its own view took
        policy.record(own_s=1e-3, waited_s=1e-3)
        if policy.next() == 1:
            break
    assert k <= 3, "a worker that doubles the views' time is not set aside"
    assert [policy.next() for _ in range(ViewPolicy.SERIAL_FRAMES - 1)] == [1] * (ViewPolicy.SERIAL_FRAMES - 1)
    assert policy.next() == 2                            # then measured anew
    assert all(ViewPolicy(1).next() == 1 for _ in range(5))
    with pytest.raises(ValueError):
        ViewPolicy(0)


def _boom(view, arg):
    if view == arg:
        raise RuntimeError(f"view {view} failed")
    return view


@pytest.mark.parametrize("failing", [0, 1])
def test_an_error_in_either_view_reaches_the_caller(failing):
    with pytest.raises(RuntimeError, match=f"view {failing} failed"):
        both_views(_boom, failing, failing)
    assert both_views(_boom, -1, -1) == (0, 1)           # the worker survives it


def test_the_worker_runs_at_the_callers_niceness():
    out = {}

    def body():
        if current_niceness() > 16:
            out["skip"] = True
            return
        with frame_priority(current_niceness() + 3) as nice:
            out["want"] = nice
            out["got"] = both_views(lambda view, _: current_niceness(), None, None)

    t = threading.Thread(target=body)
    t.start()
    t.join()
    if out.get("skip"):
        pytest.skip("the tests run at a niceness above 16: none three above it to ask for")
    assert out["got"] == (out["want"], out["want"])


def _in_child(queue):
    queue.put(both_views(lambda view, arg: (view, arg), "L", "R"))


def test_a_forked_child_makes_its_own_worker():
    both_views(_where, "L", "R")                          # the parent's worker exists before the fork
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_in_child, args=(queue,))
    child.start()
    try:
        assert queue.get(timeout=60) == ((0, "L"), (1, "R"))
    finally:
        child.join(timeout=60)
    assert child.exitcode == 0


def _frames(design, calib):
    """A press from rest to 3 mm with a hidden patch in the first frame (the rest-pattern reading) and a few
    blobs dropped from one view later on (the previous frame's help): every path the views take."""
    rng = np.random.default_rng(3)
    rest = design.rest_markers_mm()
    r = np.hypot(*rest[:, :2].T)
    frames = [synth_stereo_frame(design, calib, rest[r > 0.35 * r.max()], rng=rng, index=0)]
    for k, depth in enumerate((0.5, 1.5, 3.0), start=1):
        truth = gaussian_press_markers(design, depth, sigma_mm=3.0, lateral=0.3)
        frames.append(synth_stereo_frame(design, calib, truth[rng.random(len(truth)) > 0.03], rng=rng, index=k))
    return frames


@pytest.mark.parametrize("name", ["hexagon127", "circular217_dome"])
def test_the_runner_gives_the_same_result_on_one_and_two_view_threads(name):
    design = load_design(name)
    calib = nominal_calibration(design)
    frames = _frames(design, calib)
    one, two = Reconstructor(design, calib, view_threads=1), Reconstructor(design, calib, view_threads=2)
    for frame in frames:
        a, b = one.process(frame), two.process(frame)
        assert len(a.corrected) >= 0.5 * design.marker_count
        np.testing.assert_array_equal(a.corrected.ids, b.corrected.ids)
        np.testing.assert_array_equal(a.corrected.xyz_mm, b.corrected.xyz_mm)
        np.testing.assert_array_equal(a.matches.left_px, b.matches.left_px)
        assert a.unmatched_reasons == b.unmatched_reasons
        assert b.timings_ms["views"] <= b.timings_ms["total"]
    with pytest.raises(RunnerError, match="view threads"):
        Reconstructor(design, calib, view_threads=4)


def test_one_thread_holds_every_pool_at_one_and_restores_the_callers_counts():
    """Inside the block OpenCV and every BLAS pool threadpoolctl finds run one thread; afterwards each is back at
    the caller's count, also when the block raises, and a pool the caller had at one thread stays there."""
    import cv2

    from pipeline.threads import _controller, one_thread

    libs = _controller().lib_controllers
    assert libs, "no BLAS pool found: numpy and scipy load OpenBLAS"
    cv_before, blas_before = cv2.getNumThreads(), [lib.get_num_threads() for lib in libs]
    try:
        cv2.setNumThreads(2)
        libs[0].set_num_threads(1)
        for lib in libs[1:]:
            lib.set_num_threads(2)
        with one_thread():
            assert cv2.getNumThreads() == 1
            assert [lib.get_num_threads() for lib in libs] == [1] * len(libs)
        assert cv2.getNumThreads() == 2
        assert [lib.get_num_threads() for lib in libs] == [1] + [2] * (len(libs) - 1)
        with pytest.raises(RuntimeError, match="inside"):
            with one_thread():
                raise RuntimeError("inside")
        assert cv2.getNumThreads() == 2 and [lib.get_num_threads() for lib in libs][1:] == [2] * (len(libs) - 1)
    finally:
        cv2.setNumThreads(cv_before)
        for lib, n in zip(libs, blas_before):
            lib.set_num_threads(n)
