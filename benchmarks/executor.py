"""One executor for every job made of independent cells: cells → run_cell → summarise → plot.

A sweep over designs, the terrain taps and the presses of the Gaussian and sine grids are all lists of
cells that do not depend on one another. :func:`run_cells` runs such a list on an :class:`Engine` and
hands each cell's outcome back in cell order; the caller summarises and plots. What it guarantees:

* **Engines.** :class:`LocalEngine` (default: spawned processes on all cores, :mod:`benchmarks.pool`:
  Ctrl-C / SIGTERM stop within seconds, workers of a killed driver exit on their own),
  :class:`InlineEngine` (this process, one cell after another) and :class:`DaskEngine` (an existing
  Dask distributed cluster, ``--cluster tcp://HOST:8786``; the optional ``cluster`` extra). Each cell is
  a module-level function and picklable arguments, so every engine runs the same code.
* **Same seeds, same results.** A cell's random streams come from its own arguments (the experiments
  derive them from the root seed and the cell's name), never from which worker runs it or when, so a
  run on one core, on all cores and on a cluster gives identical metrics.
* **Faults.** A cell that raises is an outcome with its error (type, message, the last frames of the
  traceback) and the other cells go on. A worker that dies mid-cell (killed, out of memory) makes the
  engine run that cell again (Dask reschedules the tasks of a lost worker; the local engine reruns the
  cells of its broken pool in a fresh one); after :data:`ALLOWED_FAILURES` lost workers a cell is
  recorded as failed. Resumable callers key each
  finished cell by a digest of its inputs (``benchmarks.sweep.cell_key``, ``benchmarks.terrain.TapJob.key``)
  and store it as it finishes, so a driver killed mid-run resumes with no cell lost or computed twice.
* **Nesting.** A cell that itself runs an experiment made of cells (a sweep cell running the Gaussian
  grid) runs those inline: the workers are already busy with the outer cells.
* **Progress.** One bar: cells done / failed / remaining and an ETA.
"""

from __future__ import annotations

import os
import sys
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from pipeline.errors import UserError

__all__ = ["Engine", "InlineEngine", "LocalEngine", "DaskEngine", "Outcome", "run_cells", "make_engine",
           "default_engine", "in_cell", "ClusterUnavailable", "CLUSTER_INSTALL_HINT", "ALLOWED_FAILURES"]

#: How many workers may die while running one cell before it is recorded as failed (the local engine's
#: fresh pools; on Dask it is the scheduler's ``distributed.scheduler.allowed-failures``, default 3).
ALLOWED_FAILURES = 3
#: What to install for ``--cluster`` (printed when the extra is missing).
CLUSTER_INSTALL_HINT = "pip install 'stereotactip[cluster]'  (Dask distributed)"
#: Set in a process while it runs a cell: nested cell lists run inline there.
_IN_CELL_ENV = "STEREOTACTIP_IN_CELL"


class ClusterUnavailable(UserError, RuntimeError):
    """``--cluster`` was given but the cluster engine is not installed or cannot be reached."""


def in_cell() -> bool:
    """True inside a running cell (then nested cells run inline)."""
    return os.environ.get(_IN_CELL_ENV) == "1"


def _run_one(fn: Callable[..., Any], args: tuple) -> tuple[Any, float]:
    """Run one cell where the engine placed it; returns (result, wall time in s)."""
    old = os.environ.get(_IN_CELL_ENV)
    os.environ[_IN_CELL_ENV] = "1"
    t0 = time.perf_counter()
    try:
        return fn(*args), time.perf_counter() - t0
    finally:
        if old is None:
            os.environ.pop(_IN_CELL_ENV, None)
        else:
            os.environ[_IN_CELL_ENV] = old


def _describe(exc: BaseException) -> str:
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__, limit=-6))
    return f"{type(exc).__name__}: {exc}\n{tb}"


@dataclass
class Outcome:
    """What one cell gave: ``result`` (None when it failed), ``error`` (None when it ran), wall time."""

    index: int
    result: Any = None
    error: str | None = None
    wall_s: float | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


class Engine:
    """Runs cells; ``name`` and ``workers`` describe it for records and progress bars."""

    name = "engine"
    workers = 1

    def run(self, fn: Callable[..., Any], jobs: Sequence[tuple], take: Callable[[Outcome], None]) -> None:
        """Run ``fn(*jobs[i])`` for every job; ``take(outcome)`` in this thread as each one finishes."""
        raise NotImplementedError

    def describe(self) -> str:
        return f"{self.name} ({self.workers} worker{'s' if self.workers != 1 else ''})"

    def close(self) -> None:
        pass


class InlineEngine(Engine):
    """This process, one cell after another (one worker, or a cell inside a cell)."""

    name = "inline"

    def run(self, fn, jobs, take):
        for i, args in enumerate(jobs):
            t0 = time.perf_counter()
            try:
                result, wall = _run_one(fn, args)
            except Exception as exc:  # noqa: BLE001 - a failed cell is an outcome, the run goes on
                take(Outcome(i, None, _describe(exc), time.perf_counter() - t0))
            else:
                take(Outcome(i, result, None, wall))


class LocalEngine(Engine):
    """Spawned worker processes on this machine (:func:`benchmarks.pool.run_parallel`)."""

    name = "local"

    def __init__(self, workers: int | None = None):
        self.workers = max(1, int(workers or os.cpu_count() or 1))

    def run(self, fn, jobs, take):
        if self.workers == 1 or len(jobs) <= 1:
            InlineEngine().run(fn, jobs, take)
            return
        from concurrent.futures.process import BrokenProcessPool

        from benchmarks.pool import run_parallel

        # A worker that dies (killed, out of memory) breaks Python's process pool: every cell not yet
        # finished comes back as BrokenProcessPool. Those cells run again in a fresh pool, up to
        # ALLOWED_FAILURES times, as a cluster reschedules the cells of a lost worker.
        pending = list(range(len(jobs)))
        for attempt in range(ALLOWED_FAILURES + 1):
            lost: list[int] = []

            def done(k: int, res: Any, error: BaseException | None) -> None:
                i = pending[k]
                if isinstance(error, BrokenProcessPool) and attempt < ALLOWED_FAILURES:
                    lost.append(i)
                elif error is not None:
                    take(Outcome(i, None, _describe(error), None))
                else:
                    take(Outcome(i, res[0], None, res[1]))

            run_parallel(_run_one, [(fn, jobs[i]) for i in pending], workers=min(self.workers, len(pending)),
                         on_done=done)
            if not lost:
                return
            pending = sorted(lost)


class DaskEngine(Engine):
    """An existing Dask distributed cluster (scheduler address ``tcp://HOST:PORT``).

    Every worker must be able to import this project at the same version (cells name their code by
    module). Files a cell writes itself (per-cell figures, terrain tap files) land on the worker's
    file system, so the output folder should be shared; the records and tables are written here.
    """

    name = "dask"

    def __init__(self, address: str, *, timeout_s: float = 20.0):
        try:
            from distributed import Client
        except ImportError:
            raise ClusterUnavailable(f"--cluster needs the cluster extra: {CLUSTER_INSTALL_HINT}") from None
        try:
            self.client = Client(address, timeout=timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise ClusterUnavailable(f"--cluster {address}: no Dask scheduler answered ({exc})") from None
        self.address = address
        self.workers = max(1, sum(self.client.nthreads().values()))

    def run(self, fn, jobs, take):
        from distributed import as_completed

        # pure=False: each submission is its own task; retries=0: a cell that raises is reported at once
        # (the tasks of a lost worker are rescheduled by the scheduler, which is not a retry)
        futures = {self.client.submit(_run_one, fn, args, pure=False, retries=0): i for i, args in enumerate(jobs)}
        try:
            with self.client.as_current():
                done = as_completed(list(futures))
            for fut in done:
                i = futures[fut]
                try:
                    value, wall = fut.result()
                except Exception as exc:  # noqa: BLE001 - incl. KilledWorker after ALLOWED_FAILURES deaths
                    take(Outcome(i, None, _describe(exc), None))
                else:
                    take(Outcome(i, value, None, wall))
                fut.release()
        except BaseException:
            self.client.cancel(list(futures))
            raise

    def describe(self) -> str:
        return f"dask at {self.address} ({self.workers} worker thread{'s' if self.workers != 1 else ''})"

    def close(self) -> None:
        self.client.close()


def make_engine(cluster: str | None = None, workers: int | None = None) -> Engine:
    """The engine for a command line: ``--cluster ADDRESS`` → :class:`DaskEngine`, else local."""
    if cluster:
        return DaskEngine(cluster)
    if workers is not None and workers < 1:
        raise UserError(f"--workers {workers}: must be >= 1")
    return LocalEngine(workers)


def default_engine() -> Engine:
    """Inline inside a cell, else local on all cores."""
    return InlineEngine() if in_cell() else LocalEngine()


def _bar(total: int, initial: int, desc: str, progress: bool):
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc=desc, disable=not progress, dynamic_ncols=True, unit="cell",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}]{postfix}",
                file=sys.stderr)


def run_cells(fn: Callable[..., Any], jobs: Sequence[tuple], *, engine: Engine | None = None,
              on_done: Callable[[Outcome], None] | None = None, desc: str = "cells", progress: bool = True,
              already_done: int = 0) -> list[Outcome]:
    """Run ``fn(*jobs[i])`` for every job on ``engine``; the outcomes in job order.

    ``on_done(outcome)`` runs in this process as each cell finishes (store a resumable cell there).
    ``already_done`` counts cells reused from an earlier run (the bar starts there). The bar shows
    cells done / failed / remaining and an ETA.
    """
    engine = engine or default_engine()
    jobs = list(jobs)
    outcomes: list[Outcome | None] = [None] * len(jobs)
    bar = _bar(already_done + len(jobs), already_done, desc, progress)
    failed = 0

    def take(o: Outcome) -> None:
        nonlocal failed
        if outcomes[o.index] is not None:
            return
        outcomes[o.index] = o
        failed += not o.ok
        if on_done is not None:
            on_done(o)
        bar.set_postfix_str(f"failed {failed}, remaining {len(jobs) - sum(x is not None for x in outcomes)}",
                            refresh=False)
        bar.update()

    try:
        if jobs:
            engine.run(fn, jobs, take)
    finally:
        bar.close()
    missing = [i for i, o in enumerate(outcomes) if o is None]
    if missing:  # pragma: no cover - every engine reports every job
        raise RuntimeError(f"executor lost {len(missing)} cell(s)")
    return outcomes  # type: ignore[return-value]
