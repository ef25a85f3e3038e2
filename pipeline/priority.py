"""The frame path's share of a loaded machine: the scheduling priority of the thread that processes frames.

A frame is a few milliseconds of single-threaded work (:mod:`pipeline.threads` holds every pool at one
thread). On a machine whose cores are all busy with other processes the kernel's fair scheduler gives the
frame's thread only its share of a core: measured on 2 cores with two processes spinning, every stage ran at
about half speed (circular217 4.7 -> 8.9 ms median). A sensor host that must keep the frame rate gives the
frame thread a larger share by lowering its niceness, as real-time robot stacks do for their sensor
drivers; Linux's completely fair scheduler weighs nice -10 about nine times nice 0.

:func:`frame_priority` asks for a niceness of the calling thread (on Linux niceness is per thread, so the
caller's other threads, and processes it starts later, keep theirs) and says what is in force. Lowering it
below the current value needs root or ``CAP_SYS_NICE``; a refusal is a clear error, never silently ignored.
"""

from __future__ import annotations

import os
from contextlib import contextmanager

from pipeline.errors import UserError

__all__ = ["frame_priority", "current_niceness", "NICE_MIN", "NICE_MAX"]

NICE_MIN, NICE_MAX = -20, 19


def current_niceness() -> int:
    """The calling thread's niceness."""
    return os.getpriority(os.PRIO_PROCESS, 0)


def _set(nice: int) -> None:
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except PermissionError:
        raise UserError(f"the OS refused niceness {nice} for the frame thread (it is {current_niceness()}): "
                        "lowering it needs root or CAP_SYS_NICE (e.g. `sudo setcap cap_sys_nice+ep` on the "
                        "Python binary), or run without --nice") from None


@contextmanager
def frame_priority(nice: int | None):
    """Run the block with the calling thread at niceness ``nice`` (``NICE_MIN`` .. ``NICE_MAX``; lower runs
    sooner), restoring the previous niceness afterwards; ``None`` changes nothing. Yields the niceness in
    force."""
    if nice is None:
        yield current_niceness()
        return
    nice = int(nice)
    if not NICE_MIN <= nice <= NICE_MAX:
        raise UserError(f"niceness {nice} is outside {NICE_MIN}..{NICE_MAX}")
    before = current_niceness()
    _set(nice)
    try:
        yield current_niceness()
    finally:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, before)
        except PermissionError:          # back to a lower niceness than it was lowered from: keep the raised one
            pass
