"""The thread pools the per-frame path touches, held at one thread while a frame is processed.

A frame's work is a few milliseconds of small operations: OpenBLAS's worker threads (numpy's and
scipy's builds each have a pool; the skin surface solves a ~220 x 220 system) and OpenCV's pool
(the detection filters) cost more to wake and synchronise than they save, and on a loaded machine
a worker that is not scheduled stalls the whole frame (measured on 2 shared cores: the surface stage
10.1 ms with OpenBLAS's default two threads against 1.6 ms with one). The numba kernels are compiled
without ``parallel``, so they run on the calling thread and have no pool to limit.

:func:`one_thread` limits every BLAS/OpenMP pool loaded in the process (threadpoolctl) and OpenCV's
to one thread for the duration of a ``with`` block and restores them afterwards, so a caller's own
settings outside the pipeline are untouched. Entering and leaving costs ~0.05 ms.
"""

from __future__ import annotations

from contextlib import contextmanager

__all__ = ["one_thread"]

_CONTROLLER = None


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
    """Run the block with every thread pool the pipeline touches at one thread."""
    import cv2

    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with _controller().limit(limits=1):
            yield
    finally:
        cv2.setNumThreads(previous)
