"""The right camera view detected and identified in a worker process, for streams whose views carry defects.

Why a process: a view with a missing or spurious blob is not certified whole in one compiled pass, and most of
its identification is numpy and Python between the compiled kernels. That part holds the GIL, so the view
worker thread of :mod:`pipeline.threads` runs it one view after the other (circular217, 1 % + 1 % defects:
21.7 ms a frame on two threads against 23.7 ms on one), while two processes each run at the speed of one.

The worker keeps its own :class:`~pipeline.vision.dtrc.DTRCTracker` and codes only the right view with it. Its
state stays the runner's own because it is changed by the same calls on the same data, sent in order over one
pipe: after every frame's commit, :meth:`~pipeline.vision.dtrc.DTRCTracker.advance` with the markers it certified
in each view (pixels and ids, ~10 kB on circular217: the whole blobs and completed codings took 0.15-0.25 ms to
pickle and send, on the frame's path), and every :meth:`~pipeline.vision.dtrc.DTRCTracker.forget` (the ids the
stereo check rejects). The
runner's tracker still does all of it too, so when the worker fails the runner codes the right view itself
from then on with nothing lost (:class:`ViewProcessError` says why). The worker is ``python -m
pipeline.view_process`` on a socket pair (not :mod:`multiprocessing`'s spawn, which imports the caller's main
script again). The image is written into a buffer both processes map (an anonymous ``memfd`` handed to the worker
when it starts) and only its shape goes over the socket: a 640 x 480 view sent as bytes took 0.4-0.6 ms to leave,
since the socket's buffer is smaller than the view and each refill waits for the worker to be woken to read it
(where the other CPU has gone idle, a virtual machine wakes it with an interrupt to the host). Without ``memfd``
(not Linux) the image goes as bytes. The blobs and the coding come back pickled (~21 kB a view on circular217).

A clean stream gains nothing (its views overlap on two threads already) and pays the round trip; hence the
runner's ``view_process`` is off by default.
"""

from __future__ import annotations

import mmap
import os
import socket
import subprocess
import sys
import time
import weakref
from multiprocessing.connection import Connection

import numpy as np

from pipeline.errors import UserError

__all__ = ["ViewProcess", "ViewProcessError", "RightView"]


class ViewProcessError(UserError, RuntimeError):
    """The view worker process failed or died; the runner codes the right view itself from then on."""


#: Seconds the runner polls for the worker's view before it sleeps until it comes (a view takes a few ms).
RESULT_SPIN_S = 0.05
#: Bytes of the image buffer the two processes share: one BGR 640 x 480 view (a larger image goes as bytes).
SHARED_IMAGE_BYTES = 640 * 480 * 3


def _shared_buffer(fd: int) -> mmap.mmap:
    """The image buffer of :data:`SHARED_IMAGE_BYTES` on ``fd``, mapped read-write."""
    return mmap.mmap(fd, SHARED_IMAGE_BYTES)


def _serve(conn: Connection, shared: mmap.mmap | None = None) -> None:
    """The worker's loop. First ``(design, rest, temporal)``; then ``("code", shape, dtype, params, niceness,
    in_shared)`` followed, unless ``in_shared`` (the image is then in ``shared``), by the image's bytes ->
    ``("ok", (blobs, coding, t_detect, t_identify))`` or ``("error", text)``; ``("advance", certified)`` and
    ``("forget", ids)`` change the tracker as the runner's own calls do (no reply); ``None`` or a closed socket ends
    it. Each view runs at the niceness of the frame thread that sent it.

    Every thread pool stays at one thread for the worker's whole life (:func:`pipeline.threads.one_thread` around
    the loop, not around each view), and a view in ``shared`` is detected where it lies: the runner writes the
    next view there only once this one is answered, and the detector keeps no reference to its image. Both
    were on the view's path just after the worker is woken, when its CPU runs slowly (measured, circular217:
    the limits entered in ~120 us there against ~20 us in a loop, the 307 kB copy ~125 us against ~8 us; the
    view now starts 260-290 us after the runner has sent it, against 410-450 us, in three runs alternating)."""
    import cv2

    from pipeline.threads import one_thread
    from pipeline.vision.detection import detect_markers
    from pipeline.vision.dtrc import DTRCTracker

    cv2.setNumThreads(1)
    design, rest, temporal = conn.recv()
    tracker = DTRCTracker(design, temporal=temporal, rest=rest)
    broken = None
    try:
        with one_thread():
            while True:
                msg = conn.recv()
                if msg is None:
                    return
                kind = msg[0]
                try:
                    if kind == "code":
                        _, shape, dtype, params, nice, in_shared = msg
                        raw = shared if in_shared else conn.recv_bytes()
                        if broken is not None:
                            conn.send(("error", broken))
                            continue
                        image = np.frombuffer(raw, np.dtype(dtype), count=int(np.prod(shape))).reshape(shape)
                        if nice != os.getpriority(os.PRIO_PROCESS, 0):
                            try:                   # the frame thread's niceness (``reconstruct --nice``)
                                os.setpriority(os.PRIO_PROCESS, 0, nice)
                            except OSError:
                                pass
                        t0 = time.perf_counter()
                        blobs = detect_markers(image, params=params)
                        t1 = time.perf_counter()
                        coding = tracker.code_view(1, blobs)
                        conn.send(("ok", (blobs, coding, t1 - t0, time.perf_counter() - t1)))
                    elif kind == "advance":
                        tracker.advance(msg[1])
                    elif kind == "forget":
                        tracker.forget(msg[1])
                except Exception as exc:          # reported at the next request; the runner then stops using it
                    text = f"view worker: {kind} failed: {type(exc).__name__}: {exc}"
                    if kind == "code":
                        conn.send(("error", text))
                    broken = broken or text
    except (EOFError, OSError, KeyboardInterrupt):
        return


def _stop(proc: subprocess.Popen, conn: Connection) -> None:
    try:
        conn.send(None)
    except (OSError, ValueError):
        pass
    try:
        proc.wait(timeout=2.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    conn.close()


class ViewProcess:
    """A worker process that detects and identifies the right view (see the module notes).

    ``submit(image, params)`` starts a view, ``result()`` waits for it: ``(blobs, (coding, read_from_rest),
    t_detect_s, t_identify_s)`` as :meth:`pipeline.runner.Reconstructor._view` returns them. ``advance`` (with
    the runner's tracker's ``certified``) must follow every commit of the runner's tracker, ``forget`` every
    ``forget``. ``close()`` (or dropping the object) stops the process. A fresh interpreter, not a fork: a fork of
    a process running BLAS, OpenCV or numba threads may inherit their locks held; it loads the compiled kernels
    from numba's cache."""

    def __init__(self, design, rest, *, temporal: bool = True) -> None:
        mine, theirs = socket.socketpair()
        # the worker imports this very package (the checkout the caller runs, installed or not)
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])]))
        fds = [theirs.fileno()]
        self._shared = None
        try:
            if hasattr(os, "memfd_create"):
                fds.append(os.memfd_create("stereotactip-view"))
                os.ftruncate(fds[1], SHARED_IMAGE_BYTES)
                self._shared = _shared_buffer(fds[1])
            self._proc = subprocess.Popen([sys.executable, "-m", "pipeline.view_process", *map(str, fds)],
                                          pass_fds=fds, env=env)
        finally:
            theirs.close()
            for fd in fds[1:]:
                os.close(fd)           # the two mappings stay valid
        self._conn = Connection(mine.detach())
        self._finalizer = weakref.finalize(self, _stop, self._proc, self._conn)
        self._send((design, rest, temporal))

    def submit(self, image: np.ndarray, params) -> None:
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        if self._shared is not None and image.nbytes <= SHARED_IMAGE_BYTES:
            # written in place (a view of a stereo frame is strided: copied row by row into the buffer)
            np.copyto(np.frombuffer(self._shared, image.dtype, count=image.size).reshape(image.shape), image)
            self._send(("code", image.shape, image.dtype.str, params, nice, True))
        else:
            image = np.ascontiguousarray(image)
            self._send(("code", image.shape, image.dtype.str, params, nice, False), raw=image.reshape(-1).data)

    def result(self):
        try:
            # polled, not slept on, for up to RESULT_SPIN_S: a process asleep in recv is woken through the
            # scheduler (on a virtual machine, an interrupt through the host: ~0.1-0.4 ms measured here)
            deadline = time.perf_counter() + RESULT_SPIN_S
            while not self._conn.poll(0) and time.perf_counter() < deadline:
                pass
            kind, payload = self._conn.recv()
        except (EOFError, OSError) as exc:
            raise ViewProcessError(f"view worker: the process ended ({exc or 'pipe closed'})") from None
        if kind != "ok":
            raise ViewProcessError(payload)
        return payload

    def advance(self, certified) -> None:
        self._send(("advance", certified))

    def forget(self, ids: np.ndarray) -> None:
        self._send(("forget", np.asarray(ids)))

    def _send(self, msg, raw=None) -> None:
        """Send ``msg`` (pickled), then ``raw`` bytes if given."""
        try:
            self._conn.send(msg)
            if raw is not None:
                self._conn.send_bytes(raw)
        except (OSError, ValueError) as exc:
            raise ViewProcessError(f"view worker: cannot reach the process ({exc})") from None

    def close(self) -> None:
        self._finalizer()


class RightView:
    """The runner's right view: coded by a :class:`ViewProcess` while it works, by the runner's own ``view``
    function from the first failure on (``error`` says why; the runner's tracker holds the same state, so
    nothing is lost). ``both`` returns both views' :meth:`~pipeline.runner.Reconstructor._view` results;
    ``repeat(call, *args)`` repeats a tracker call (``"advance"``, ``"forget"``) in the worker."""

    def __init__(self, design, rest) -> None:
        self.error: str | None = None
        self._proc: ViewProcess | None = ViewProcess(design, rest)

    def both(self, view, left_image, right_image, params):
        if self._proc is None:
            return view(0, left_image), view(1, right_image)
        try:
            self._proc.submit(right_image, params)
        except Exception as exc:
            self._drop(exc)
            return view(0, left_image), view(1, right_image)
        try:
            a = view(0, left_image)
        except BaseException:
            self._drop(RuntimeError("the left view failed while the worker coded the right"))
            raise
        try:
            return a, self._proc.result()
        except Exception as exc:
            self._drop(exc)
            return a, view(1, right_image)

    def repeat(self, call: str, *args) -> None:
        if self._proc is not None:
            try:
                getattr(self._proc, call)(*args)
            except Exception as exc:
                self._drop(exc)

    def _drop(self, exc: Exception) -> None:
        self.error = str(exc)
        self.close()

    def close(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            try:
                proc.close()
            except Exception:
                pass


if __name__ == "__main__":
    _serve(Connection(int(sys.argv[1])), _shared_buffer(int(sys.argv[2])) if len(sys.argv) > 2 else None)
