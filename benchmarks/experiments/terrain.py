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
        "invalid_taps": "1",
        "unreconstructed_taps": "1",
        "invalid_regions": "1",
        "skin_penetration_max_mm": "mm",
        "rms_err_mm_mean_all": "mm",
        "rms_err_reachable_mm_mean_all": "mm",
        "resolved_fraction_all": "1",
    },
    requires=("benchmarks.terrain", "twin.terrain", "pipeline.geometry.merge"),
)
def run(ctx: Context) -> Result:
    """World-relief tap scan (nine regions; quick: two small ones): merged reconstruction vs the DEM."""
    from benchmarks.terrain import DESIGN_NAME, run_scan
    from pipeline.design import load_design

    # the quick variant too runs every tap through the twin (MuJoCo skin, renderer) and the vision pipeline, so
    # the CI gate sees what a scan measures; '--param sensor=ideal' gives the geometry-and-merge-only back end
    sensor = str(ctx.param("sensor", "twin"))
    regions = ctx.param("regions", "all")
    from benchmarks.terrain import _design

    scan_dir = ctx.out_dir / "terrain_scan"
    # the 'ideal' back end has no cameras: what the pipeline is told about the sensor does not enter
    setup = ctx.sensor_setup(_design()) if sensor == "twin" else None
    rec = run_scan(scan_dir, regions=regions, sensor=sensor, quick=ctx.quick, workers=ctx.param("workers", None),
                   seed=ctx.seed, progress=ctx.progress, engine=ctx.engine, setup=setup)
    all_regs = rec["regions"]
    # a region with a physically invalid tap (twin.validity) is counted and kept out of the scores
    regs = {k: m for k, m in all_regs.items() if m.get("physics_valid", True)}
    n_invalid_taps = int(sum(m.get("n_taps_invalid", 0) for m in all_regs.values()))
    out = Result(designs=[load_design(DESIGN_NAME)], setups=[setup.provenance] if setup is not None else [])
    def over_valid(key: str, fn) -> float:
        vals = [float(m[key]) for m in regs.values()]
        return float(fn(vals)) if vals else float("nan")

    out.metric("rms_err_mm_mean", over_valid("rms_err_mm", np.mean), "mm")
    out.metric("rms_err_mm_max", over_valid("rms_err_mm", np.max), "mm")
    out.metric("rms_err_reachable_mm_mean", over_valid("rms_err_reachable_mm", np.mean), "mm")
    out.metric("max_abs_err_mm", over_valid("max_abs_err_mm", np.max), "mm")
    resolved = [bool(m["resolved"]) for m in regs.values()]
    out.metric("resolved_fraction", float(np.mean(resolved)) if resolved else float("nan"), "1")
    # the same scores over every region, physically invalid ones included: not a measurement of the scan
    # (the skin passed into the relief), but what the vision pipeline made of the twin's frames, so a
    # regression of the pipeline on taps stays visible while the twin's contact cannot give valid taps
    out.metric("rms_err_mm_mean_all", float(np.mean([m["rms_err_mm"] for m in all_regs.values()])), "mm")
    out.metric("rms_err_reachable_mm_mean_all",
               float(np.mean([m["rms_err_reachable_mm"] for m in all_regs.values()])), "mm")
    out.metric("resolved_fraction_all", float(np.mean([bool(m["resolved"]) for m in all_regs.values()])), "1")
    out.metric("regions", len(all_regs), "1")
    out.metric("taps", rec["n_taps"], "1")
    out.metric("invalid_taps", n_invalid_taps, "1")
    failed = [t for m in all_regs.values() for t in m.get("unreconstructed_taps", [])]
    out.metric("unreconstructed_taps", len(failed), "1")
    out.metric("invalid_regions", len(all_regs) - len(regs), "1")
    pens = [float(m["penetration_max_mm"]) for m in all_regs.values()
            if m.get("physics_checked") and np.isfinite(m.get("penetration_max_mm", np.nan))]
    out.metric("skin_penetration_max_mm", max(pens) if pens else float("nan"), "mm")
    out.tables["regions"] = [{"region": k, **{kk: vv for kk, vv in m.items() if np.isscalar(vv)}}
                             for k, m in all_regs.items()]
    if len(regs) < len(all_regs):
        out.notes.append(f"{len(all_regs) - len(regs)} of {len(all_regs)} region(s) physically invalid "
                         f"({n_invalid_taps} tap(s): " + "; ".join(
                             f"{k}: {', '.join(m.get('invalid_reasons', []))}" for k, m in all_regs.items()
                             if not m.get("physics_valid", True)) + "); kept out of the scores above.")
    if failed:
        out.notes.append(f"{len(failed)} tap(s) gave a frame the pipeline could not reconstruct; their regions are "
                         "merged and scored from the other taps (lower coverage): " + "; ".join(failed) + ".")
    out.notes.append(f"Tap back end: '{sensor}' ({'MuJoCo skin + renderer + pipeline' if sensor == 'twin' else 'ideal conforming skin at the marker x-y: scan geometry and merge only'}); "
                     f"outputs of benchmarks.terrain in terrain_scan/.")
    if setup is not None:
        out.notes.append(calibration_note([setup]))
    elif ctx.calibration != "oracle":
        out.notes.append(f"Calibration mode '{ctx.calibration}' has no effect here: the '{sensor}' tap back end "
                         "uses no cameras (run with --param sensor=twin for the twin's cameras and stack).")
    out.findings.append(Finding("the scan reproduces each region's characteristic features (paper Fig. 12)",
                                ", ".join(f"{k}: {'resolved' if m['resolved'] else 'NOT resolved'}"
                                          + ("" if m.get("physics_valid", True) else " (physically invalid, not scored)")
                                          for k, m in all_regs.items()),
                                bool(all(resolved)) if len(regs) == len(all_regs) else None))
    for png in sorted(scan_dir.glob("*.png")):
        out.figures.append(png)
    return out
