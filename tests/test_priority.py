"""The frame thread's scheduling priority (pipeline.priority): asked for, in force inside the block, restored
after it, confined to the calling thread, and refused with a clear error where the OS refuses. Whether a lower
niceness buys a larger share of a loaded machine is measured by `stereotactip bench latency --param nice=N
--param background_procs=N`, not asserted here. Likewise the CPU wake-up latency request: held in the block,
released after it, refused clearly (its effect: `bench latency --param cpu_latency=0`)."""

from __future__ import annotations

import os
import struct
import threading

import pytest

from pipeline.errors import UserError
from pipeline.priority import PM_QOS_DEVICE, cpu_latency, current_niceness, frame_priority


def _in_thread(fn):
    """Run ``fn`` in a thread of its own (niceness is per thread on Linux, so the test's own stays as it is)."""
    out: dict = {}

    def run():
        try:
            out["value"] = fn()
        except BaseException as exc:          # handed back to the test
            out["error"] = exc

    t = threading.Thread(target=run)
    t.start()
    t.join()
    if "error" in out:
        raise out["error"]
    return out["value"]


def test_a_raised_niceness_holds_in_the_block_and_only_in_the_calling_thread():
    main_before = current_niceness()
    if main_before > 16:
        pytest.skip(f"the tests run at niceness {main_before}: no niceness three above it to ask for (the OS caps it at 19)")

    def body():
        before = current_niceness()
        with frame_priority(before + 3) as inside:
            seen = (inside, current_niceness(), os.getpriority(os.PRIO_PROCESS, threading.main_thread().native_id))
        return before, seen, current_niceness()

    before, (inside, now, main_inside), after = _in_thread(body)
    assert inside == now == before + 3
    assert main_inside == main_before                    # the other threads keep theirs
    if os.geteuid() == 0:
        assert after == before                           # restored (lowering back needs the privilege)
    assert current_niceness() == main_before


def test_no_niceness_changes_nothing():
    def body():
        before = current_niceness()
        with frame_priority(None) as inside:
            return before, inside, current_niceness()

    before, inside, now = _in_thread(body)
    assert before == inside == now


@pytest.mark.skipif(os.geteuid() != 0, reason="lowering the niceness needs root or CAP_SYS_NICE")
def test_a_lowered_niceness_is_granted_to_root_and_restored():
    def body():
        before = current_niceness()
        with frame_priority(before - 5) as inside:
            pass
        return before, inside, current_niceness()

    before, inside, after = _in_thread(body)
    assert inside == before - 5 and after == before


def test_out_of_range_and_refused_niceness_are_clear_errors(monkeypatch):
    with pytest.raises(UserError, match="outside -20..19"):
        with frame_priority(-21):
            pass

    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    with pytest.raises(UserError, match="CAP_SYS_NICE"):
        with frame_priority(-10):
            pass


# --- the CPU wake-up latency request ----------------------------------------------------------------------------

def _device_value(path=PM_QOS_DEVICE) -> int:
    fd = os.open(path, os.O_RDONLY)
    try:
        return struct.unpack("=i", os.read(fd, 4))[0]
    finally:
        os.close(fd)


def test_a_cpu_latency_request_is_written_as_the_kernel_reads_it_and_held_only_in_the_block(tmp_path):
    """The request is the 4-byte native integer the kernel's PM QoS device takes, written when the block
    starts; the value yielded is what the device reads back. Checked on a stand-in file (the device
    itself below); None asks nothing."""
    dev = tmp_path / "cpu_dma_latency"
    dev.write_bytes(b"\xff\xff\xff\x7f")
    with cpu_latency(7, device=str(dev)) as in_force:
        assert in_force == 7 and _device_value(str(dev)) == 7
    with cpu_latency(None, device=str(dev)) as in_force:
        assert in_force is None
    assert dev.read_bytes() == struct.pack("=i", 7)


def test_a_cpu_latency_request_that_cannot_be_made_is_a_clear_error(tmp_path, monkeypatch):
    with pytest.raises(UserError, match="must be 0 or more"):
        with cpu_latency(-1, device=str(tmp_path / "x")):
            pass
    with pytest.raises(UserError, match="Linux only"):
        with cpu_latency(0, device=str(tmp_path / "missing")):
            pass

    dev = tmp_path / "write_only"
    dev.write_bytes(struct.pack("=i", 2_000_000_000))
    real_open = os.open

    def write_only(path, flags, *a):      # a device a udev rule lets the user write but not read
        if flags & os.O_ACCMODE != os.O_WRONLY:
            raise PermissionError(13, "Permission denied")
        return real_open(path, flags, *a)

    monkeypatch.setattr(os, "open", write_only)
    with cpu_latency(3, device=str(dev)) as in_force:
        assert in_force == 3
    assert dev.read_bytes() == struct.pack("=i", 3)

    def refuse(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "open", refuse)
    with pytest.raises(UserError, match="needs root"):
        with cpu_latency(0, device=str(tmp_path / "x")):
            pass


@pytest.mark.skipif(not os.access(PM_QOS_DEVICE, os.W_OK), reason=f"no writable {PM_QOS_DEVICE} here (Linux PM QoS; "
                    "root): the request is checked on a stand-in file above")
def test_the_kernel_holds_a_zero_wake_up_latency_while_the_block_runs_and_drops_it_after():
    """On the real device: while the block runs the kernel's limit for the whole system is 0 us (idle CPUs
    poll); afterwards it is back to what it was. Whether that shortens frames is measured by `stereotactip
    bench latency --param cpu_latency=0`, not asserted here."""
    before = _device_value()
    with cpu_latency(0) as in_force:
        assert in_force == 0 and _device_value() == 0
    assert _device_value() == before
