"""Parallel runs stop cleanly: Ctrl-C / SIGTERM within seconds with queued jobs cancelled and no worker
left behind; the workers of a SIGKILLed driver exit on their own; finished jobs are kept."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.pool import PARENT_POLL_S

REPO = Path(__file__).resolve().parents[1]
N_JOBS, N_WORKERS = 6, 2
#: A stopped run must be gone this quickly: the driver polls for signals every 0.5 s and gives
#: terminated workers 5 s before SIGKILL (they die at once on SIGTERM); 10 s leaves 2x.
STOP_WITHIN_S = 10.0

DRIVER = r'''
import os, sys, time
from pathlib import Path
from benchmarks.pool import run_parallel

def job(i, folder):
    from tqdm import tqdm
    bar = tqdm(total=1, file=open(os.devnull, "w"))   # as the experiments' progress bars do
    Path(folder, f"started_{i}").write_text(str(os.getpid()))
    if i == 0:
        return i            # finishes at once: must be reported before the interrupt
    time.sleep(300)         # the rest would keep a core busy for minutes
    return i

if __name__ == "__main__":
    import faulthandler, signal
    faulthandler.register(signal.SIGUSR1, all_threads=True)   # the test asks for every thread's stack on a hang
    folder = sys.argv[1]
    Path(folder, "sigint_at_start").write_text(repr(signal.getsignal(signal.SIGINT)))
    # a run started from a terminal gets Ctrl-C; one started in the background of a script inherits SIGINT
    # ignored (as the test suite does when a CI job runs it that way): the driver is a foreground run
    signal.signal(signal.SIGINT, signal.default_int_handler)
    def done(i, result, error):
        Path(folder, f"done_{i}").write_text(repr(result))
    try:
        run_parallel(job, [(i, folder) for i in range(%d)], workers=%d, on_done=done)
    except KeyboardInterrupt:
        Path(folder, "interrupted").write_text("yes")
        sys.exit(130)
''' % (N_JOBS, N_WORKERS)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False
    return state not in ("Z", "X")


def _wait_for(cond, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def _stderr(tmp_path) -> str:
    return (tmp_path / "stderr.txt").read_text(errors="replace")[-2000:]


@pytest.fixture
def cleanup():
    """Processes a test started; any still alive at teardown are killed (a failing test must not
    leave sleepers behind)."""
    pids: list[int] = []
    yield pids
    for pid in pids:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def _start(tmp_path, cleanup):
    script = tmp_path / "driver.py"
    script.write_text(DRIVER)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    with open(tmp_path / "stderr.txt", "wb") as err:
        proc = subprocess.Popen([sys.executable, str(script), str(tmp_path)], env=env,
                                stdout=subprocess.DEVNULL, stderr=err)
    cleanup.append(proc.pid)
    started = lambda: sorted(tmp_path.glob("started_*"))
    ok = _wait_for(lambda: len(started()) == N_WORKERS + 1 and (tmp_path / "done_0").exists(), 90)
    if not ok:
        proc.kill()
        proc.wait()
        pytest.fail(f"workers did not start: {_stderr(tmp_path)}")
    time.sleep(0.3)   # let both sleepers settle into their job
    pids = [int(p.read_text()) for p in started() if p.name != "started_0"]
    cleanup.extend(pids)
    assert len(pids) == N_WORKERS and all(_alive(p) for p in pids)
    return proc, pids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc to see the workers")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_stops_the_run_in_seconds_and_leaves_no_worker(sig, tmp_path, cleanup):
    proc, pids = _start(tmp_path, cleanup)
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        rc = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)     # faulthandler: every thread's stack into stderr.txt
        time.sleep(1.0)
        proc.kill()           # reap it here, or its Popen warns in whichever later test collects it
        proc.wait()
        state = {f.name: f.read_text() for f in tmp_path.iterdir() if f.name in ("interrupted", "sigint_at_start")}
        pytest.fail(f"the driver did not stop within 60 s of {sig.name} ({state}): {_stderr(tmp_path)}")
    elapsed = time.monotonic() - t0
    assert rc == 130 and (tmp_path / "interrupted").exists(), _stderr(tmp_path)
    assert elapsed < STOP_WITHIN_S, f"took {elapsed:.1f} s to stop"
    assert (tmp_path / "done_0").exists()                               # the finished job was kept
    assert len(list(tmp_path.glob("started_*"))) == N_WORKERS + 1       # queued jobs never started
    assert _wait_for(lambda: not any(_alive(p) for p in pids), 5.0), "worker processes left running"
    assert "Traceback" not in _stderr(tmp_path) and "leaked" not in _stderr(tmp_path)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc to see the workers")
def test_workers_of_a_killed_driver_exit_on_their_own(tmp_path, cleanup):
    proc, pids = _start(tmp_path, cleanup)
    proc.kill()                       # no clean-up in the driver at all
    proc.wait(timeout=30)
    assert _wait_for(lambda: not any(_alive(p) for p in pids), PARENT_POLL_S + 5.0), \
        "workers outlived their driver"
