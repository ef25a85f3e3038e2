"""sweep-scale: how fast the one executor runs real cells, here and (projected) on a cluster.

The cell is the Gaussian grid's unit of work (``gaussian.press_cell``: a σ² = 10 mm² press of
hexagon127 at one rotation, rendered, reconstructed by the unchanged pipeline and scored). The same
cells run on four engines: local processes with 1 and 2 workers, and a local Dask cluster (127.0.0.1)
with 1 and 2 workers. Per engine: wall time including start-up, cells per hour, the mean time inside a
cell, and the engine's overhead per cell (its round trip for an empty cell, measured on 40 of them).
Scaling efficiency is the 2-worker rate over twice the 1-worker rate.

The projection of the full paper grid — every built-in design pressed by the five Gaussians and the
five sines in three rotations and scanning the 31 terrain taps — multiplies the grid's cell count by
the mean cell time measured here for each kind (one sine cell and one terrain tap are timed too) and
divides by the workers, scaled by the measured 2-worker efficiency. It is a projection, not a run:
nodes are assumed to be like this one (2 cores), with the same efficiency between nodes as between
two local workers, and shared storage that keeps up.
"""

from __future__ import annotations

import math
import os
import time
from typing import NamedTuple

import numpy as np

from benchmarks.registry import Context, Result, register

ENGINES = ("local1", "local2", "cluster1", "cluster2")
TERRAIN_TAPS = 31          # the full scan: nine regions (benchmarks.terrain, --sensor twin)
GRID_PER_DESIGN = {"gaussian": 5 * 3, "sine": 5 * 3, "terrain": TERRAIN_TAPS}
PROJECTED_NODES = (1, 32)
WORKERS_PER_NODE = 2       # this machine's cores


def empty_cell(i: int) -> int:
    """A cell that does nothing: its round trip is the engine's own cost."""
    return i


def _engine(kind: str, workers: int):
    """(engine, close) for one configuration; the Dask cluster is started here, on 127.0.0.1."""
    from benchmarks.executor import DaskEngine, LocalEngine

    if kind == "local":
        return LocalEngine(workers), lambda: None
    from distributed import LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None, silence_logs=50)
    engine = DaskEngine(cluster.scheduler_address)
    engine.client.wait_for_workers(workers)

    def close():
        engine.close()
        cluster.close()

    return engine, close


@register(
    "sweep-scale",
    tags=("full-only",),
    metrics={
        **{f"cells_per_hour_{e}": "1/h" for e in ENGINES},
        **{f"wall_s_{e}": "s" for e in ENGINES},
        **{f"startup_s_{e}": "s" for e in ENGINES},
        **{f"overhead_ms_per_cell_{e}": "ms" for e in ENGINES},
        **{f"overhead_fraction_{e}": "1" for e in ENGINES},
        "scaling_efficiency_local": "1",
        "scaling_efficiency_cluster": "1",
        "cell_s_gaussian": "s",
        "cell_s_sine": "s",
        "cell_s_terrain": "s",
        "paper_grid_cells": "1",
        **{f"projected_paper_grid_h_{n}node{'s' if n > 1 else ''}": "h" for n in PROJECTED_NODES},
    },
    requires=("benchmarks.executor", "twin.simulate", "pipeline.runner"),
)
def run(ctx: Context) -> Result:
    """Cells per hour on 1 and 2 local workers and a local Dask cluster; projected paper-grid wall time."""
    from pipeline.design import load_design

    n_cells = int(ctx.param("cells", 6))
    design = load_design("hexagon127")
    jobs = [(design, 10.0, 360.0 * k / n_cells, ctx.seed, f"sweep-scale/{k}") for k in range(n_cells)]
    out = Result(designs=[design])
    engines = _available_engines(out)
    timings = []
    for name in engines:
        timings.append(_time_engine(name, jobs))
        _report_engine(out, timings[-1], n_cells)
    eff_local, eff_cluster = _scaling(out, timings, n_cells)
    cell_s = _cell_times(ctx, timings)
    n_designs = _stereo_design_count()
    grid = {k: v * n_designs for k, v in GRID_PER_DESIGN.items()}
    eff = _project_paper_grid(out, grid, cell_s, eff_local, eff_cluster)
    out.tables["engines"] = [t.row for t in timings]
    out.tables["paper_grid"] = [{"kind": k, "cells": v, "cell_s": cell_s[k]} for k, v in grid.items()]
    _notes(out, timings, n_designs, sum(grid.values()), eff)
    out.figures.append(_plot(ctx, timings))
    return out


class _EngineTiming(NamedTuple):
    """One engine's run of the Gaussian cells."""

    name: str
    wall_s: float           # the cells' wall time plus the engine's start-up
    startup_s: float
    cell_s: float           # mean time inside a cell
    overhead_ms: float      # round trip of an empty cell on warm workers
    cell_metrics: list      # each cell's rms_vs_true_skin_mm (equal on every engine: same seeds)
    row: dict               # the "engines" table row


def _available_engines(out: Result) -> list[str]:
    """The engines this install can run (the Dask ones need distributed); a note when some cannot."""
    import importlib.util

    engines = [e for e in ENGINES if e.startswith("local") or importlib.util.find_spec("distributed") is not None]
    if len(engines) < len(ENGINES):
        out.notes.append("Dask distributed is not installed (pip install 'stereotactip[cluster]'): local engines only.")
    return engines


def _time_engine(name: str, jobs: list) -> _EngineTiming:
    """Start the engine, run the cells on it, then 40 empty cells on warm workers; close it."""
    from benchmarks.executor import run_cells
    from benchmarks.experiments import gaussian

    kind, workers = name[:-1], int(name[-1])
    t0 = time.perf_counter()
    engine, close = _engine(kind, workers)
    try:
        startup = time.perf_counter() - t0
        t1 = time.perf_counter()
        outs = run_cells(gaussian.press_cell, jobs, engine=engine, progress=False)
        wall = time.perf_counter() - t1 + startup
        failed = [o.error for o in outs if not o.ok]
        if failed:
            raise RuntimeError(f"{name}: {len(failed)} cell(s) failed: {failed[0].splitlines()[0]}")
        cell_s = float(np.mean([o.wall_s for o in outs]))
        # the engine's own cost per cell: empty cells on warm workers
        run_cells(empty_cell, [(i,) for i in range(workers)], engine=engine, progress=False)
        t2 = time.perf_counter()
        run_cells(empty_cell, [(i,) for i in range(40)], engine=engine, progress=False)
        overhead_ms = (time.perf_counter() - t2) / 40 * 1000.0
    finally:
        close()
    n_cells = len(jobs)
    row = {"engine": name, "workers": workers, "cells": n_cells, "wall_s": wall, "startup_s": startup,
           "cells_per_hour": n_cells / wall * 3600.0, "mean_cell_s": cell_s, "overhead_ms_per_cell": overhead_ms,
           "load_average_1min_after": os.getloadavg()[0]}
    cell_metrics = [o.result[0]["rms_vs_true_skin_mm"] for o in outs]
    return _EngineTiming(name, wall, startup, cell_s, overhead_ms, cell_metrics, row)


def _report_engine(out: Result, t: _EngineTiming, n_cells: int) -> None:
    """Rate, wall time, start-up and per-cell overhead of one engine."""
    out.metric(f"cells_per_hour_{t.name}", n_cells / t.wall_s * 3600.0, "1/h")
    out.metric(f"wall_s_{t.name}", t.wall_s, "s")
    out.metric(f"startup_s_{t.name}", t.startup_s, "s")
    out.metric(f"overhead_ms_per_cell_{t.name}", t.overhead_ms, "ms")
    out.metric(f"overhead_fraction_{t.name}", t.overhead_ms / 1000.0 / t.cell_s, "1")


def _scaling(out: Result, timings: list[_EngineTiming], n_cells: int) -> tuple[float, float]:
    """Whether every engine gave the same cells, and the 2-worker scaling efficiencies (local, cluster)."""
    first = timings[0].cell_metrics
    same = all(np.array_equal(t.cell_metrics, first, equal_nan=True) for t in timings)
    out.notes.append(f"The {n_cells} cells gave {'identical' if same else 'DIFFERENT'} metrics on every engine.")
    wall = {t.name: t.wall_s for t in timings}
    eff_local = wall["local1"] / wall["local2"] / 2.0
    eff_cluster = wall["cluster1"] / wall["cluster2"] / 2.0 if "cluster2" in wall else math.nan
    out.metric("scaling_efficiency_local", eff_local, "1")
    out.metric("scaling_efficiency_cluster", eff_cluster, "1")
    return eff_local, eff_cluster


def _cell_times(ctx: Context, timings: list[_EngineTiming]) -> dict[str, float]:
    """Seconds per cell of each kind: the Gaussian cells' mean over the engines; one sine cell and one terrain
    tap timed in this process (a warm process, as on a busy worker)."""
    from benchmarks.executor import InlineEngine, run_cells
    from benchmarks.experiments import sine
    from benchmarks.terrain import plan_jobs, run_tap
    from pipeline.design import load_design

    cell_gauss = float(np.mean([t.cell_s for t in timings]))
    sine_out = run_cells(sine.press_cell, [(load_design("hexagon127"), 2, 0.0, ctx.seed, "sweep-scale/sine")],
                         engine=InlineEngine(), progress=False)[0]
    if not sine_out.ok:
        raise RuntimeError(f"the timed sine cell failed: {sine_out.error.splitlines()[0]}")
    tap_dir = ctx.out_dir / "sweep_scale_tap"
    (tap_dir / "taps").mkdir(parents=True, exist_ok=True)
    tap = plan_jobs(["english_channel"], tap_dir, sensor="twin", seed=ctx.seed, max_taps=1)["english_channel"][0]
    t0 = time.perf_counter()
    run_tap(tap)
    return {"gaussian": cell_gauss, "sine": sine_out.wall_s, "terrain": time.perf_counter() - t0}


def _stereo_design_count() -> int:
    """How many built-in designs are stereo modules (the paper grid runs on each)."""
    from pipeline.design import list_designs, load_design

    return len([n for n in list_designs() if not load_design(n).monocular])


def _project_paper_grid(out: Result, grid: dict[str, int], cell_s: dict[str, float], eff_local: float,
                        eff_cluster: float) -> float:
    """Cell times and the projected wall time of the paper grid (cells per kind) on 1 and 32 nodes; returns the
    efficiency used."""
    out.metric("cell_s_gaussian", cell_s["gaussian"], "s")
    out.metric("cell_s_sine", cell_s["sine"], "s")
    out.metric("cell_s_terrain", cell_s["terrain"], "s")
    cpu_s = grid["gaussian"] * cell_s["gaussian"] + grid["sine"] * cell_s["sine"] + grid["terrain"] * cell_s["terrain"]
    out.metric("paper_grid_cells", sum(grid.values()), "1")
    eff = min(max(eff_cluster if math.isfinite(eff_cluster) else eff_local, 1e-3), 1.0)
    for n in PROJECTED_NODES:
        workers = n * WORKERS_PER_NODE
        hours = cpu_s / (workers * eff) / 3600.0
        out.metric(f"projected_paper_grid_h_{n}node{'s' if n > 1 else ''}", hours, "h")
    return eff


def _notes(out: Result, timings: list[_EngineTiming], n_designs: int, grid_cells: int, eff: float) -> None:
    """What the projection assumes, the machine's load during the runs, and what each engine's time includes."""
    out.notes.append(
        f"Projection, not a run: {grid_cells} cells ({n_designs} built-in designs × (15 Gaussian + 15 sine "
        f"press cells + {TERRAIN_TAPS} terrain taps)) × the cell times measured here, on nodes of "
        f"{WORKERS_PER_NODE} workers at the measured 2-worker cluster efficiency {eff:.2f}; start-up "
        "and storage are not included.")
    loads = ", ".join(f"{t.row['engine']} {t.row['load_average_1min_after']:.1f}" for t in timings)
    out.notes.append(f"Machine: {os.cpu_count()} cores; 1-minute load average after each engine's run: {loads}. "
                     "A load above the core count means other jobs shared the cores, and the 2-worker rates and "
                     "the scaling efficiency then say more about that load than about the engines.")
    out.notes.append("local1 runs the cells in this process; local2 spawns its two worker processes for each list of "
                     "cells (their imports count in its wall time and in its per-cell overhead on 40 empty cells); "
                     "the Dask workers stay up between lists, their start-up is startup_s.")


def _plot(ctx: Context, timings: list[_EngineTiming]):
    """Cells per hour by engine."""
    from benchmarks.results import COLUMN_IN, paper_style, save_figure

    with paper_style() as plt:
        fig, ax = plt.subplots(figsize=(COLUMN_IN, 2.2))
        ax.bar([t.name for t in timings], [t.row["cells_per_hour"] for t in timings], color="0.45")
        ax.set_ylabel("cells per hour")
        ax.set_title("Gaussian press cells (σ² = 10 mm², hexagon127)")
        return save_figure(fig, ctx.figure_path("sweep_scale"))
