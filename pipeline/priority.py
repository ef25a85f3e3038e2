"""The frame path's share of a loaded machine (the scheduling priority of the thread that processes frames),
and how fast an idle CPU wakes for it (the kernel's CPU latency request).

A frame is a few milliseconds of single-threaded work (:mod:`pipeline.threads` holds every pool at one
thread). On a machine whose cores are all busy with other processes the kernel's fair scheduler gives the
frame's thread only its share of a core: measured on 2 cores with two processes spinning, every stage ran at
about half speed (circular217 4.7 -> 8.9 ms median). A sensor host that must keep the frame rate gives the
frame thread a larger share by lowering its niceness, as real-time robot stacks do for their sensor
drivers; Linux's completely fair scheduler weighs nice -10 about nine times nice 0.

:func:`frame_priority` asks for a niceness of the calling thread (on Linux niceness is per thread, so the
caller's other threads, and processes it starts later, keep theirs) and says what is in force. Lowering it
below the current value needs root or ``CAP_SYS_NICE``; a refusal is a clear error, never silently ignored.

A frame's two views run on two threads, which hand the interpreter's lock to each other some forty times a
view, and the right view's thread sleeps between frames: every hand-over to a sleeping thread waits for its
CPU to wake. An idle CPU halts, and a halted CPU of a virtual machine is woken through the hypervisor, which
took 10-145 us per wake-up on the 2-core reference machine. :func:`cpu_latency` holds a Linux PM QoS
request (``/dev/cpu_dma_latency``, as ``tuned``'s latency-performance profile does) that no CPU take longer
than the given microseconds to wake; at 0 an idle CPU polls instead of halting, at the cost of the idle
core's power. Writing the request needs root (or a udev rule granting the device); a refusal is a clear
error.
"""

from __future__ import annotations

import os
import struct
from contextlib import contextmanager

from pipeline.errors import UserError

__all__ = ["frame_priority", "current_niceness", "cpu_latency", "NICE_MIN", "NICE_MAX", "PM_QOS_DEVICE"]

NICE_MIN, NICE_MAX = -20, 19
PM_QOS_DEVICE = "/dev/cpu_dma_latency"   # Linux PM QoS CPU latency: a request holds while the file is open


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


@contextmanager
def cpu_latency(max_us: int | None, device: str | None = None):
    """Run the block with a request that every CPU wake within ``max_us`` microseconds (0: idle CPUs poll),
    released afterwards; ``None`` asks nothing. Yields the limit in force for the whole system while the
    block runs (the strictest of all requests, as the kernel reads it back; the value asked where the device
    may be written but not read), or None when nothing was asked. ``device``: the PM QoS file (default
    :data:`PM_QOS_DEVICE`)."""
    device = PM_QOS_DEVICE if device is None else device
    if max_us is None:
        yield None
        return
    max_us = int(max_us)
    if max_us < 0:
        raise UserError(f"CPU wake-up latency {max_us} us: must be 0 or more")
    readable = True
    try:
        try:
            fd = os.open(device, os.O_RDWR)
        except PermissionError:          # a udev rule may grant writing only
            fd, readable = os.open(device, os.O_WRONLY), False
    except FileNotFoundError:
        raise UserError(f"no {device} here: this system has no PM QoS CPU latency request (Linux only); "
                        "run without --cpu-latency") from None
    except PermissionError:
        raise UserError(f"the OS refused a CPU latency request ({device}): it needs root or write access to "
                        "the device (e.g. a udev rule), or run without --cpu-latency") from None
    try:
        os.write(fd, struct.pack("=i", max_us))
        in_force = max_us
        if readable:
            os.lseek(fd, 0, os.SEEK_SET)
            in_force = struct.unpack("=i", os.read(fd, 4))[0]
        yield in_force
    finally:
        os.close(fd)                     # closing the file releases the request
