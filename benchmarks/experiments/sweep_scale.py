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
    from benchmarks.executor import InlineEngine, run_cells
    from benchmarks.experiments import gaussian, sine
    from pipeline.design import list_designs, load_design

    n_cells = int(ctx.param("cells", 6))
    design = load_design("hexagon127")
    jobs = [(design, 10.0, 360.0 * k / n_cells, ctx.seed, f"sweep-scale/{k}") for k in range(n_cells)]
    out = Result(designs=[design])
    rows = []
    values = {}
    import importlib.util

    engines = [e for e in ENGINES if e.startswith("local") or importlib.util.find_spec("distributed") is not None]
    if len(engines) < len(ENGINES):
        out.notes.append("Dask distributed is not installed (pip install 'stereotactip[cluster]'): local engines only.")
    for name in engines:
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
        values[name] = {"wall": wall, "cell_s": cell_s}
        rate = n_cells / wall * 3600.0
        out.metric(f"cells_per_hour_{name}", rate, "1/h")
        out.metric(f"wall_s_{name}", wall, "s")
        out.metric(f"startup_s_{name}", startup, "s")
        out.metric(f"overhead_ms_per_cell_{name}", overhead_ms, "ms")
        out.metric(f"overhead_fraction_{name}", overhead_ms / 1000.0 / cell_s, "1")
        rows.append({"engine": name, "workers": workers, "cells": n_cells, "wall_s": wall, "startup_s": startup,
                     "cells_per_hour": rate, "mean_cell_s": cell_s, "overhead_ms_per_cell": overhead_ms,
                     "load_average_1min_after": os.getloadavg()[0]})
        # equal metrics on every engine: the same seeds give the same cells
        values[name]["metrics"] = [o.result[0]["rms_vs_true_skin_mm"] for o in outs]
    same = all(np.array_equal(values[e]["metrics"], values[engines[0]]["metrics"], equal_nan=True) for e in engines)
    out.notes.append(f"The {n_cells} cells gave {'identical' if same else 'DIFFERENT'} metrics on every engine.")
    eff_local = values["local1"]["wall"] / values["local2"]["wall"] / 2.0
    eff_cluster = values["cluster1"]["wall"] / values["cluster2"]["wall"] / 2.0 if "cluster2" in values else math.nan
    out.metric("scaling_efficiency_local", eff_local, "1")
    out.metric("scaling_efficiency_cluster", eff_cluster, "1")

    # one cell of each other kind, timed in this process (a warm process, as on a busy worker)
    cell_gauss = float(np.mean([values[e]["cell_s"] for e in engines]))
    sine_out = run_cells(sine.press_cell, [(load_design("hexagon127"), 2, 0.0, ctx.seed, "sweep-scale/sine")],
                         engine=InlineEngine(), progress=False)[0]
    if not sine_out.ok:
        raise RuntimeError(f"the timed sine cell failed: {sine_out.error.splitlines()[0]}")
    cell_sine = sine_out.wall_s
    from benchmarks.terrain import plan_jobs, run_tap

    tap_dir = ctx.out_dir / "sweep_scale_tap"
    (tap_dir / "taps").mkdir(parents=True, exist_ok=True)
    tap = plan_jobs(["english_channel"], tap_dir, sensor="twin", seed=ctx.seed, max_taps=1)["english_channel"][0]
    t0 = time.perf_counter()
    run_tap(tap)
    cell_terrain = time.perf_counter() - t0
    out.metric("cell_s_gaussian", cell_gauss, "s")
    out.metric("cell_s_sine", cell_sine, "s")
    out.metric("cell_s_terrain", cell_terrain, "s")
    n_designs = len([n for n in list_designs() if not load_design(n).monocular])  # the stereo modules
    grid = {k: v * n_designs for k, v in GRID_PER_DESIGN.items()}
    cpu_s = grid["gaussian"] * cell_gauss + grid["sine"] * cell_sine + grid["terrain"] * cell_terrain
    out.metric("paper_grid_cells", sum(grid.values()), "1")
    eff = min(max(eff_cluster if math.isfinite(eff_cluster) else eff_local, 1e-3), 1.0)
    for n in PROJECTED_NODES:
        workers = n * WORKERS_PER_NODE
        hours = cpu_s / (workers * eff) / 3600.0
        out.metric(f"projected_paper_grid_h_{n}node{'s' if n > 1 else ''}", hours, "h")
    out.tables["engines"] = rows
    out.tables["paper_grid"] = [{"kind": k, "cells": v, "cell_s": {"gaussian": cell_gauss, "sine": cell_sine,
                                                                    "terrain": cell_terrain}[k]} for k, v in grid.items()]
    out.notes.append(
        f"Projection, not a run: {sum(grid.values())} cells ({n_designs} built-in designs × (15 Gaussian + 15 sine "
        f"press cells + {TERRAIN_TAPS} terrain taps)) × the cell times measured here, on nodes of "
        f"{WORKERS_PER_NODE} workers at the measured 2-worker cluster efficiency {eff:.2f}; start-up "
        "and storage are not included.")
    loads = ", ".join(f"{r['engine']} {r['load_average_1min_after']:.1f}" for r in rows)
    out.notes.append(f"Machine: {os.cpu_count()} cores; 1-minute load average after each engine's run: {loads}. "
                     "A load above the core count means other jobs shared the cores, and the 2-worker rates and "
                     "the scaling efficiency then say more about that load than about the engines.")
    out.notes.append("local1 runs the cells in this process; local2 spawns its two worker processes for each list of "
                     "cells (their imports count in its wall time and in its per-cell overhead on 40 empty cells); "
                     "the Dask workers stay up between lists, their start-up is startup_s.")
    from benchmarks.results import COLUMN_IN, paper_style, save_figure

    with paper_style() as plt:
        fig, ax = plt.subplots(figsize=(COLUMN_IN, 2.2))
        ax.bar([r["engine"] for r in rows], [r["cells_per_hour"] for r in rows], color="0.45")
        ax.set_ylabel("cells per hour")
        ax.set_title("Gaussian press cells (σ² = 10 mm², hexagon127)")
        out.figures.append(save_figure(fig, ctx.figure_path("sweep_scale")))
    return out
