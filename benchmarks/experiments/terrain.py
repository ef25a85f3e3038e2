"""terrain: the world-relief tap scan (paper Sec. VI), wrapping ``benchmarks.terrain.run_scan``.

``benchmarks.terrain`` does the scan, merge and scoring and writes its own outputs (taps,
height maps, PLY, panels, ``terrain.json``) into ``OUT/terrain_scan/``; this wrapper records its
region metrics with units in the common JSON format and links its figures.
"""

from __future__ import annotations

import numpy as np

from benchmarks.experiments._common import calibration_note
from benchmarks.registry import Context, Finding, Result, register


@register(
    "terrain",
    tags=("quick", "paper"),
    metrics={
        "rms_err_mm_mean": "mm",
        "rms_err_mm_max": "mm",
        "rms_err_reachable_mm_mean": "mm",
        "max_abs_err_mm": "mm",
        "resolved_fraction": "1",
        "regions": "1",
        "taps": "1",
    },
    requires=("benchmarks.terrain", "twin.terrain", "pipeline.merge"),
)
def run(ctx: Context) -> Result:
    """World-relief tap scan (nine regions; quick: two small ones): merged reconstruction vs the DEM."""
    from benchmarks.terrain import DESIGN_NAME, run_scan
    from pipeline.design import load_design

    sensor = str(ctx.param("sensor", "twin", quick="ideal"))
    regions = ctx.param("regions", "all")
    from benchmarks.terrain import _design

    scan_dir = ctx.out_dir / "terrain_scan"
    # the 'ideal' back end has no cameras: what the pipeline is told about the sensor does not enter
    setup = ctx.sensor_setup(_design()) if sensor == "twin" else None
    rec = run_scan(scan_dir, regions=regions, sensor=sensor, quick=ctx.quick, workers=ctx.param("workers", None),
                   seed=ctx.seed, progress=ctx.progress, engine=ctx.engine, setup=setup)
    regs = rec["regions"]
    out = Result(designs=[load_design(DESIGN_NAME)], setups=[setup.provenance] if setup is not None else [])
    rms = np.array([m["rms_err_mm"] for m in regs.values()], dtype=float)
    out.metric("rms_err_mm_mean", float(np.mean(rms)), "mm")
    out.metric("rms_err_mm_max", float(np.max(rms)), "mm")
    out.metric("rms_err_reachable_mm_mean", float(np.mean([m["rms_err_reachable_mm"] for m in regs.values()])), "mm")
    out.metric("max_abs_err_mm", float(max(m["max_abs_err_mm"] for m in regs.values())), "mm")
    resolved = [bool(m["resolved"]) for m in regs.values()]
    out.metric("resolved_fraction", float(np.mean(resolved)), "1")
    out.metric("regions", len(regs), "1")
    out.metric("taps", rec["n_taps"], "1")
    out.tables["regions"] = [{"region": k, **{kk: vv for kk, vv in m.items() if np.isscalar(vv)}} for k, m in regs.items()]
    out.notes.append(f"Tap back end: '{sensor}' ({'MuJoCo skin + renderer + pipeline' if sensor == 'twin' else 'ideal conforming skin at the marker x-y: scan geometry and merge only'}); "
                     f"outputs of benchmarks.terrain in terrain_scan/.")
    if setup is not None:
        out.notes.append(calibration_note([setup]))
    elif ctx.calibration != "oracle":
        out.notes.append(f"Calibration mode '{ctx.calibration}' has no effect here: the '{sensor}' tap back end "
                         "uses no cameras (run with --param sensor=twin for the twin's cameras and stack).")
    out.findings.append(Finding("the scan reproduces each region's characteristic features (paper Fig. 12)",
                                ", ".join(f"{k}: {'resolved' if m['resolved'] else 'NOT resolved'}" for k, m in regs.items()),
                                bool(all(resolved))))
    for png in sorted(scan_dir.glob("*.png")):
        out.figures.append(png)
    return out
