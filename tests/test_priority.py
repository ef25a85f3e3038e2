"""The frame thread's scheduling priority (pipeline.priority): asked for, in force inside the block, restored
after it, confined to the calling thread, and refused with a clear error where the OS refuses. Whether a lower
niceness buys a larger share of a loaded machine is measured by `stereotactip bench latency --param nice=N
--param background_procs=N`, not asserted here."""

from __future__ import annotations

import os
import threading

import pytest

from pipeline.errors import UserError
from pipeline.priority import current_niceness, frame_priority


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
