"""``stereotactip fit-twin``: the stages of :mod:`benchmarks.tactip_fit` run in order, each cached.

Every stage's result is kept in ``OUT.cache/<stage>.json`` keyed by its inputs, so an interrupted fit
resumes; the fitted design is written to OUT (TOML) with a summary in ``OUT.fit.json``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from benchmarks.tactip_fit import (CAM_KEYS, FITTED_POSITION_PARAMETERS, LAYOUT_SEPARATIONS_MM, FitContext,
                                   apply_params, camera_vector, fit_appearance, fit_camera_all, fit_camera_reference,
                                   fit_layout, fit_physics)
from benchmarks.tactip_fit_skin import PHYSICS_STEPS
from pipeline.design import load_design, to_toml
from pipeline.io.atomic import atomic_write_json, atomic_write_text
from twin.tactip import check_monocular
from benchmarks.tapdata import digest

__all__ = ["fit_twin", "register", "cmd_fit", "PHYSICS_STAGE", "CAMERA_ALL_STAGE"]

#: what the physics stage fits and scores (part of its cache key: a cached result of another version is
#: recomputed, not reused)
PHYSICS_STAGE = ("tilt frame on positions; pin rotation, bending, depth offset, tilt pivot (coarse grid to 36 mm, "
                 "parabolic refine) on displacements; tilt frame re-searched on the most tilted taps' displacements, "
                 "depth offset after it")

#: what the all-taps camera stage does (part of its cache key)
CAMERA_ALL_STAGE = "reference ids re-taken from the fitted twin before (and after) the camera fit on every training tap"


def _cached(cache: Path, name: str, key: str, fn):
    path = cache / f"{name}.json"
    if path.is_file():
        data = json.loads(path.read_text())
        if data.get("key") == key:
            return data["value"], True
    value = fn()
    cache.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, {"key": key, "value": value}, indent=1)
    return value, False


def fit_twin(frames, targets, design_name, out: Path, *, progress: bool = True, log=print,
             skip_unlabelled: bool = False) -> dict:
    """Fit the monocular twin to labelled real taps, stage by stage (pin spacing, camera from the reference
    tap, skin and tap physics, camera from every training tap, appearance), each stage cached; write the
    fitted design TOML to ``out`` and the summary to ``OUT.fit.json``. Returns the summary."""
    from tqdm import tqdm

    design = load_design(design_name)
    check_monocular(design)
    ctx = FitContext(frames, targets, design, progress=progress, skip_unlabelled=skip_unlabelled, log=log)
    t0 = time.time()
    log(f"fit-twin: {len(ctx.frames)} frames, {len(ctx.train)} train / {len(ctx.held)} held out "
        f"(every {4}th frame by index held out: {', '.join(ctx.frames[i].path.name for i in ctx.held)}); "
        f"reference (shallowest training tap): {ctx.frames[ctx.ref].path.name}")
    bar = tqdm(total=len(LAYOUT_SEPARATIONS_MM) + 5 + PHYSICS_STEPS + 6, desc="fit-twin", unit="step", disable=not progress)
    st = _Stages(Path(str(out) + ".cache"), ctx.key(), bar, log)
    twin0 = design.twin_params()
    s0 = _layout_stage(st, ctx, twin0)
    design = apply_params(design, {"separation_mm": s0["separation_mm"]})
    ctx = ctx.with_design(design)
    s1 = _camera_reference_stage(st, ctx, design, twin0, s0)
    d1 = apply_params(design, s1["cam"])  # (design carries the fitted spacing)
    s23 = _physics_stage(st, ctx, d1, twin0, s1)
    twin = s23["twin"]      # carries the fitted pin rotation; the pins keep the design's height
    s4 = _camera_all_stage(st, ctx, d1, twin, s1)
    d4 = apply_params(design, s4["cam"])
    s5 = _appearance_stage(st, ctx, d4, twin, s4)
    bar.close()
    fitted = apply_params(d4, twin=s5["twin"], name=design.name + "_fitted")
    train_rms, held_rms = _write_fitted(out, ctx, fitted, s5["twin"])
    phys = s23["report"]
    summary = {
        "design": design.name, "out": str(out), "frames": len(ctx.frames),
        "train": [ctx.frames[i].path.name for i in ctx.train], "held_out": [ctx.frames[i].path.name for i in ctx.held],
        "reference": ctx.frames[ctx.ref].path.name, "camera": s4["report"], "physics": {
            "values": {k: twin[k] for k in ("bending_ratio", "depth_offset_mm", "tilt_frame_deg", "tilt_mirror",
                                            "pin_rotation", "tilt_pivot_mm")},
            "sd": phys["sd"], "rms_px_search": phys["rms_px_search"]},
        "appearance": {"values": {k: s5["twin"][k] for k in ("marker_grey", "marker_shading", "background_grey",
                                                              "edge_px", "noise_grey", "marker_scale")},
                       "report": s5["report"]},
        "residuals": {"train_rms_px": train_rms, "held_out_rms_px": held_rms},
        "separation_mm": s0["separation_mm"], "pin_height_mm": design.pins.height_mm,
        "fitted_parameters": FITTED_POSITION_PARAMETERS + 5, "seconds": time.time() - t0,
    }
    atomic_write_json(Path(str(out) + ".fit.json"), summary, indent=1)
    _log_summary(log, summary, s4["report"], twin, phys, out)
    return summary


class _Stages(NamedTuple):
    """What every stage shares: the cache folder, the key of the frames and design, the progress bar, the log."""

    cache: Path
    base_key: str
    bar: Any
    log: Callable


def _layout_stage(st: _Stages, ctx: FitContext, twin0: dict) -> dict:
    """Stage 0: the pin spacing on the dome that best explains the reference tap."""
    def fit():
        sep, scores = fit_layout(ctx, twin0, st.bar)
        return {"separation_mm": sep, "scores": scores}

    s0, hit = _cached(st.cache, "0_layout", st.base_key, fit)
    if hit:
        st.bar.update(len(LAYOUT_SEPARATIONS_MM))
    st.log(f"  pin spacing on the dome{' (cached)' if hit else ''}: {s0['separation_mm']:.2f} mm "
           f"(scores " + ", ".join(f"{b:.1f}: {a:.2f}" for a, b in s0["scores"]) + ")")
    return s0


def _camera_reference_stage(st: _Stages, ctx: FitContext, design, twin0: dict, s0: dict) -> dict:
    """Stage 1: the camera from the reference tap; its matched markers become the reference that identifies
    every real frame (set on ``ctx``)."""
    def fit():
        d, ref_xy, rep = fit_camera_reference(ctx, twin0)
        return {"cam": dict(zip(CAM_KEYS, map(float, camera_vector(d)))), "ref_xy": ref_xy.tolist(), "report": rep}

    s1, hit = _cached(st.cache, "1_camera_reference", digest(st.base_key, s0["separation_mm"]), fit)
    st.bar.update(1)
    ctx.set_reference(np.asarray(s1["ref_xy"], dtype=np.float64))
    ident = [int(np.isfinite(x[:, 0]).sum()) for x in ctx.real_xy]
    st.log(f"  camera from the reference tap{' (cached)' if hit else ''}: {s1['report']['matched']} markers matched, "
           f"RMS {s1['report']['rms_px']:.2f} px; identified per frame: min {min(ident)}, median "
           f"{int(np.median(ident))} of {design.marker_count}")
    return s1


def _physics_stage(st: _Stages, ctx: FitContext, d1, twin0: dict, s1: dict) -> dict:
    """Stages 2-3: skin bending and the tap's depth offset and tilt frame, with the reference camera."""
    def fit():
        tw, rep = fit_physics(ctx, d1, twin0, st.bar)
        return {"twin": tw, "report": rep}

    s23, hit = _cached(st.cache, "2_physics", digest(st.base_key, s1["cam"], PHYSICS_STAGE), fit)
    if hit:
        st.bar.update(PHYSICS_STEPS)
    return s23


def _camera_all_stage(st: _Stages, ctx: FitContext, d1, twin: dict, s1: dict) -> dict:
    """Stage 4: the camera refitted on every training tap with the fitted physics."""
    def fit():
        d, rep = fit_camera_all(ctx, d1, twin)
        return {"cam": rep["values"], "report": rep, "ref_xy": ctx.ref_xy.tolist()}

    s4, hit = _cached(st.cache, "4_camera_all", digest(st.base_key, s1["cam"], twin, CAMERA_ALL_STAGE), fit)
    st.bar.update(1)
    ctx.set_reference(np.asarray(s4["ref_xy"], dtype=np.float64))
    ids = s4["report"]["reference_ids"]
    st.log(f"  reference ids re-taken with the fitted skin and tap{' (cached)' if hit else ''}: {ids['fitted']} "
           f"markers (stage 1: {ids['first']}){', camera fitted again after them' if ids['refits'] else ''}")
    return s4


def _appearance_stage(st: _Stages, ctx: FitContext, d4, twin: dict, s4: dict) -> dict:
    """Stage 5: marker and background appearance from the real frames' image statistics."""
    def fit():
        tw, rep = fit_appearance(ctx, d4, twin)
        return {"twin": tw, "report": rep}

    s5, _ = _cached(st.cache, "5_appearance", digest(st.base_key, s4["cam"], twin), fit)
    st.bar.update(1)
    return s5


def _write_fitted(out: Path, ctx: FitContext, fitted, twin: dict) -> tuple[float, float]:
    """Write the fitted design (TOML, its residuals in the header); returns (train, held-out) pin-tip RMS px."""
    train_rms = ctx.rms(fitted, ctx.train, twin)
    held_rms = ctx.rms(fitted, ctx.held, twin)
    out.parent.mkdir(parents=True, exist_ok=True)
    header = (f"# Fitted by `stereotactip fit-twin` from {len(ctx.frames)} labelled frames "
              f"({len(ctx.train)} train, {len(ctx.held)} held out).\n"
              f"# Pin-tip RMS (projected twin vs identified real markers): train {train_rms:.2f} px, "
              f"held out {held_rms:.2f} px.\n")
    atomic_write_text(out, header + to_toml(fitted))
    return train_rms, held_rms


def _log_summary(log, summary: dict, c: dict, twin: dict, phys: dict, out: Path) -> None:
    """The fitted values with their uncertainties and the residuals, on the console."""
    train_rms, held_rms = summary["residuals"]["train_rms_px"], summary["residuals"]["held_out_rms_px"]
    log("camera (value ± 1 sd):")
    for k in CAM_KEYS:
        log(f"  {k:12s} {c['values'][k]:10.4f} ± {c['sd'][k]:.4f}")
    log(f"  reprojection RMS {c['rms_px']:.2f} px over {c['n_obs']} marker observations "
        f"({'converged' if c['converged'] else 'NOT CONVERGED: ' + c['message']})")
    log("skin and tap:")
    log(f"  bending_ratio   {twin['bending_ratio']:.4g} (log10 sd {phys['sd']['log10_bending_ratio']:.3f})")
    log(f"  depth_offset_mm {twin['depth_offset_mm']:.3f} ± {phys['sd']['depth_offset_mm']:.3f}")
    log(f"  tilt_frame_deg  {twin['tilt_frame_deg']:.1f} ± {phys['sd']['tilt_frame_deg']:.1f}, "
        f"second tilt {'mirrored' if twin['tilt_mirror'] else 'as labelled'}")
    if "tilt_frame_refit" in phys:
        rf = phys["tilt_frame_refit"]
        log(f"                  (first fit {phys['tilt_frame_first_deg']:.1f}; re-searched with the fitted skin and "
            f"pivot on the {len(rf['frame_names'])} most tilted taps: displacement RMS {rf['rms_px_before']:.3f} -> "
            f"{rf['rms_px']:.3f} px)")
    log(f"  pin_rotation    {twin['pin_rotation']:.3f} ± {phys['sd']['pin_rotation']:.3f} "
        f"(pins {summary['pin_height_mm']:.2f} mm, the design's) "
        f"(displacement RMS on the search taps {phys['displacement_rms_px_search']:.2f} px)")
    log(f"  tilt_pivot_mm   {twin['tilt_pivot_mm']:.1f} above the dome's centre (scored: " + ", ".join(
        f"{h:g} mm: offset {o:.2f}, {e:.3f} px" for h, o, e in phys.get("tilt_pivot_scores", [])) + ")")
    log("appearance: " + ", ".join(f"{k} {v:.3g}" for k, v in summary["appearance"]["values"].items()))
    log(f"residuals: train {train_rms:.2f} px, held out {held_rms:.2f} px (pin-tip RMS); wrote {out}")
    if not c["converged"]:
        log("warning: the camera fit did not converge; the fitted file is a partial result")


def register(sub) -> None:
    p = sub.add_parser("fit-twin", help="fit a monocular TacTip twin (camera, skin, appearance) to labelled real taps")
    p.add_argument("frames", help="folder (or image) of real frames")
    p.add_argument("--targets", required=True, help="targets CSV (pose_3 depth mm, pose_4/pose_5 tilt deg)")
    p.add_argument("--design", default="tactip331", help="monocular design name or TOML path")
    p.add_argument("--out", required=True, help="fitted design TOML to write")
    p.add_argument("--skip-unlabelled", action="store_true", help="leave out frames without a targets row "
                   "(named on the console) instead of refusing them")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_fit)


def cmd_fit(args) -> int:
    fit_twin(args.frames, args.targets, args.design, Path(args.out), progress=not args.no_progress,
             skip_unlabelled=args.skip_unlabelled)
    return 0
