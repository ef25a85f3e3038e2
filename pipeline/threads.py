"""The thread pools the per-frame path touches: every library pool held at one thread while a frame is
processed, and one worker of the pipeline's own for the second camera view.

A frame's work is a few milliseconds of small operations: OpenBLAS's worker threads (numpy's and
scipy's builds each have a pool; the skin surface solves a ~220 x 220 system) and OpenCV's pool
(the detection filters) cost more to wake and synchronise than they save, and on a loaded machine
a worker that is not scheduled stalls the whole frame (measured on 2 shared cores: the surface stage
10.1 ms with OpenBLAS's default two threads against 1.6 ms with one). The numba kernels are compiled
without ``parallel``, so they run on the calling thread and have no pool to limit.

:func:`one_thread` limits every BLAS/OpenMP pool loaded in the process (threadpoolctl) and OpenCV's
to one thread for the duration of a ``with`` block and restores them afterwards, so a caller's own
settings outside the pipeline are untouched. Entering and leaving costs ~0.01 ms in a loop.

The two camera views of a stereo frame are detected and identified independently (the identification
reads only earlier frames), so :func:`both_views` runs the right view on one worker thread while the
calling thread does the left: the detection filters (OpenCV) and every numba kernel of the two stages
release the GIL, so the views overlap on two cores. The worker blocks on a queue (it never spins, unlike
a BLAS pool waiting for work), and a view the worker has not started by the time the caller has finished
its own is taken back and run by the caller, so a worker that the scheduler does not run (every core busy)
costs the frame nothing beyond the serial time. ``threads=1`` (``reconstruct --view-threads 1``) keeps
both views on the calling thread.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, TypeVar

__all__ = ["one_thread", "both_views", "default_view_threads", "ViewPolicy", "VIEW_THREADS"]

_CONTROLLER = None
_T = TypeVar("_T")

#: Allowed values of the view-thread count: 1 (both views on the calling thread) or 2 (one worker).
VIEW_THREADS = (1, 2)

_WORKER: ThreadPoolExecutor | None = None
_WORKER_LOCK = threading.Lock()


def default_view_threads() -> int:
    """2 where the process may run on two or more CPUs (its affinity mask), else 1."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):      # not Linux
        n = os.cpu_count() or 1
    return 2 if n >= 2 else 1


def _worker() -> ThreadPoolExecutor:
    global _WORKER
    with _WORKER_LOCK:
        if _WORKER is None:
            _WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="stereotactip-view")
        return _WORKER


def _forget_worker() -> None:
    """After a fork the child has the executor object but not its thread: it makes its own on first use."""
    global _WORKER, _WORKER_LOCK
    _WORKER, _WORKER_LOCK = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_worker)


def _at_niceness(nice: int, fn: Callable[[int, object], _T], view: int, arg: object) -> _T:
    """``fn(view, arg)`` with the worker thread at the caller's niceness (niceness is per thread on Linux:
    a frame thread given a larger share of a loaded machine, ``reconstruct --nice``, lends it to its view)."""
    if os.getpriority(os.PRIO_PROCESS, 0) != nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except PermissionError:     # back up from a lowered niceness without CAP_SYS_NICE: keep it
            pass
    return fn(view, arg)


def both_views(fn: Callable[[int, object], _T], left: object, right: object, *, threads: int = 2,
               waited: list | None = None) -> tuple[_T, _T]:
    """``(fn(0, left), fn(1, right))``, the right view on the shared view worker while the calling thread
    runs the left (``threads=2``), or both in turn on the calling thread (``threads=1``).

    The right view is taken back and run by the caller when the worker has not started it once the left
    is done (so the frame never waits on a worker the scheduler has not run, nor on another caller's
    view queued first). ``fn`` must not share mutable state between the two views. An exception in
    either view propagates to the caller after both have finished. ``waited``, if given, gets the
    seconds the caller then waited for the worker appended (0.0 when it ran the right view itself).
    """
    if threads not in VIEW_THREADS:
        raise ValueError(f"view threads {threads!r}: choose one of {VIEW_THREADS}")
    if threads == 1:
        return fn(0, left), fn(1, right)
    future = _worker().submit(_at_niceness, os.getpriority(os.PRIO_PROCESS, 0), fn, 1, right)
    try:
        a = fn(0, left)
    except BaseException:
        if not future.cancel():
            future.exception()       # let the right view finish before the frame's state is touched again
        raise
    if future.cancel():              # not started: the caller is free now, run it here
        if waited is not None:
            waited.append(0.0)
        return a, fn(1, right)
    t0 = time.perf_counter()
    b = future.result()
    if waited is not None:
        waited.append(time.perf_counter() - t0)
    return a, b


class ViewPolicy:
    """How many threads the next frame's views get: ``threads`` (1 or 2), except while the worker has
    been making the frame wait.

    With a core free the right view ends about when the left does. With the other core busy with
    another process the worker gets a share of it and the caller waits about as long as its own view
    took: no faster than one thread, and the frame's p95 grows with the worker's scheduling. When the
    wait, averaged over the last few frames (weight :data:`WAIT_WEIGHT`), exceeds :data:`WAIT_LIMIT` of
    the caller's own view time, the next :data:`SERIAL_FRAMES` frames run on one thread, then two
    again, which measures anew.
    """

    WAIT_LIMIT = 0.5
    WAIT_WEIGHT = 0.3
    SERIAL_FRAMES = 50

    def __init__(self, threads: int) -> None:
        if threads not in VIEW_THREADS:
            raise ValueError(f"view threads {threads!r}: choose one of {VIEW_THREADS}")
        self.threads = threads
        self._serial = 0
        self._wait = 0.0

    def next(self) -> int:
        """The thread count for the next frame."""
        if self.threads == 1 or self._serial > 0:
            self._serial = max(0, self._serial - 1)
            return 1
        return 2

    def record(self, own_s: float, waited_s: float) -> None:
        """After a frame on two threads: the caller's own view took ``own_s``, then it waited ``waited_s``."""
        self._wait = (1 - self.WAIT_WEIGHT) * self._wait + self.WAIT_WEIGHT * waited_s / max(own_s, 1e-6)
        if self._wait > self.WAIT_LIMIT:
            self._serial, self._wait = self.SERIAL_FRAMES, 0.0
def _controller():
    """One threadpoolctl controller per process, made on first use (after numpy, scipy and OpenCV
    have loaded their libraries, so that it sees every pool)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS before the libraries are listed)
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER


@contextmanager
def one_thread():
    """Run the block with every thread pool the pipeline touches at one thread.

    Each pool threadpoolctl found is read and, where it is not at one thread already, set and afterwards
    set back, through its controller directly: ``ThreadpoolController.limit`` first collects every
    library's full description (versions, architecture, ...), which took half of the 17-21 us this
    costs a frame in a loop (8-11 us now; 55 + 41 us entering and leaving inside the frame loop of
    ``bench latency``, caches cold after the reference job)."""
    import cv2

    previous = cv2.getNumThreads()
    if previous != 1:
        cv2.setNumThreads(1)
    libs = _controller().lib_controllers
    before = [lib.get_num_threads() for lib in libs]
    try:
        for lib, n in zip(libs, before):
            if n != 1:
                lib.set_num_threads(1)
        yield
    finally:
        for lib, n in zip(libs, before):
            if n is not None and n != 1:
                lib.set_num_threads(n)
        if previous != 1:
            cv2.setNumThreads(previous)
