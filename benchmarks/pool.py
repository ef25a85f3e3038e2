"""Worker processes for sweeps and scans that stop cleanly.

:func:`run_parallel` runs jobs in spawned worker processes and hands each result (or exception) to a
callback as it finishes. What it guarantees:

* Ctrl-C (SIGINT) or SIGTERM of the driver stops the run within seconds: queued jobs are cancelled,
  running ones are terminated, every worker is joined (no orphan keeps a core and ~0.5 GB), and the
  interrupt is re-raised. Jobs that finished before it have already been handed to the callback (and
  the sweep's and the scan's workers write their own result files atomically as they finish).
* Workers ignore SIGINT (a terminal's Ctrl-C reaches the whole process group; only the driver
  decides) and watch their driver: if it dies without cleaning up (SIGKILL, a crash), each worker
  exits on its own (Linux ``PR_SET_PDEATHSIG``, and a poll of the parent pid as a fallback).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from typing import Any, Callable, Iterator, Sequence

__all__ = ["run_parallel", "init_worker", "terminate_as_interrupt", "PARENT_POLL_S"]

#: How often a worker checks that its driver is still alive (fallback to PR_SET_PDEATHSIG), s.
PARENT_POLL_S = 1.0
_PR_SET_PDEATHSIG = 1


def _watch_parent(driver_pid: int) -> None:
    """Exit this worker when the driver process is gone."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass
    if os.getppid() != driver_pid:      # the driver died before the prctl took effect
        os._exit(1)

    def poll() -> None:
        while True:
            time.sleep(PARENT_POLL_S)
            if os.getppid() != driver_pid:
                os._exit(1)

    threading.Thread(target=poll, name="parent-watch", daemon=True).start()


def init_worker(driver_pid: int, single_thread: bool = True) -> None:
    """Initializer of every worker: ignore SIGINT, default SIGTERM, watch the driver, one thread each."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _watch_parent(driver_pid)
    try:
        # tqdm's default lock is a multiprocessing semaphore; a worker terminated mid-job never releases
        # it, and the resource tracker warns about it at exit. Workers draw no shared bars: a thread lock.
        from tqdm import tqdm

        tqdm.set_lock(threading.RLock())
    except ImportError:  # pragma: no cover
        pass
    if single_thread:
        # several workers on a few cores: keep each single-threaded so they do not oversubscribe
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        try:
            import cv2

            cv2.setNumThreads(1)
        except ImportError:  # pragma: no cover
            pass


class Terminated(KeyboardInterrupt):
    """SIGTERM received: handled like Ctrl-C (stop, clean up, exit)."""


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` (a KeyboardInterrupt) in the main thread,
    so the clean-up of a Ctrl-C also runs for a ``kill``. A no-op outside the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated(f"signal {signum}")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _kill_pool(pool: ProcessPoolExecutor, timeout_s: float = 5.0) -> None:
    """Cancel queued jobs, terminate the workers and join them (SIGKILL after ``timeout_s``)."""
    procs = list(getattr(pool, "_processes", {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = time.monotonic() + timeout_s
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)
    # the executor's manager thread notices the dead workers and releases the queues' semaphores
    # (otherwise multiprocessing's resource tracker warns about leaked semaphores at exit)
    manager = getattr(pool, "_executor_manager_thread", None)
    if manager is not None:
        with contextlib.suppress(Exception):
            manager.join(max(1.0, deadline - time.monotonic()))
    _lock_wakeup(pool)


def _lock_wakeup(pool: ProcessPoolExecutor) -> None:
    """Make the executor's wake-up pipe safe to poke at interpreter exit.

    At exit ``concurrent.futures.process`` wakes every executor's manager thread through its wake-up pipe
    without the executor's shutdown lock, while a manager thread still winding down after its workers were
    killed closes that pipe under the lock: under load the write can meet the closed descriptor and the
    interpreter prints "Exception ignored ... OSError: [Errno 9] Bad file descriptor" on the way out (seen
    once in the interrupt test, 2026-11-27, Python 3.11). The check-and-write is put under the same lock
    that guards the close, so it sees the pipe open or knows it closed."""
    wake = getattr(pool, "_executor_manager_thread_wakeup", None)
    lock = getattr(pool, "_shutdown_lock", None)
    if wake is None or lock is None or not callable(getattr(wake, "wakeup", None)):
        return
    unlocked = wake.wakeup

    def wakeup() -> None:
        with lock:
            unlocked()

    wake.wakeup = wakeup


def run_parallel(fn: Callable[..., Any], jobs: Sequence[tuple], *, workers: int,
                 on_done: Callable[[int, Any, BaseException | None], None]) -> None:
    """Run ``fn(*jobs[i])`` in ``workers`` spawned processes; ``on_done(i, result, error)`` per job as
    it finishes (``error`` is the exception a job raised, ``result`` then None).

    ``fn`` must be importable by the workers (a module-level function). On KeyboardInterrupt or
    SIGTERM the pool is torn down (see the module docstring) and the interrupt re-raised.
    """
    with terminate_as_interrupt():
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                                   initializer=init_worker, initargs=(os.getpid(),))
        try:
            pending = {pool.submit(fn, *args): i for i, args in enumerate(jobs)}
            while pending:
                # a timeout keeps the main thread returning to Python so that signals are handled promptly
                done, _ = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = pending.pop(fut)
                    try:
                        result, error = fut.result(), None
                    except Exception as exc:  # noqa: BLE001 - a failed job is reported, the run goes on
                        result, error = None, exc
                    on_done(i, result, error)
        except BaseException:
            _kill_pool(pool)
            raise
        pool.shutdown(wait=True)
