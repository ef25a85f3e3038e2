"""twin: speed and fidelity of the digital twin itself (wraps ``benchmarks.twin_bench.run_twin_bench``).

``run_twin_bench`` presses a σ² = 10 mm² Gaussian 5 mm into the default sensor three times (MuJoCo
skin with the design's friction; model compiled for the first press, copied from the per-process cache after;
the path followed to the captured pose), the same press frictionless solved directly and along the followed
path for comparison, both Gaussians (σ² = 10 and 5/3) on the contact meshes, and renders 20 stereo frames of
the pressed state; it reports seconds per press, milliseconds per stereo frame and the skin-to-indenter gap
over the contact points. Its
raw ``twin.json`` is kept in ``OUT/twin_bench/`` (``OUT/twin.json`` is this experiment's record).
Speed is machine-dependent (2 shared cores here): the CI gate holds the press and frame times in units of a
fixed reference job timed between them, with only a loose sanity bound on the seconds; the gap is
physics and is gated tightly.
"""

from __future__ import annotations

import numpy as np

from benchmarks.registry import Context, Finding, Result, register


@register(
    "twin",
    tags=("quick",),
    metrics={
        "press_s_median": "s",
        "model_build_s_median": "s",
        "frame_ms_median": "ms",
        "gap_max_mm": "mm",
        "gap_rms_mm": "mm",
        "settle_converged_fraction": "1",
        "mesh_dofs": "1",
        "friction": "1",
        "frictionless_direct_press_s": "s",
        "followed_press_s": "s",
        "direct_vs_followed_marker_max_mm": "mm",
        "penetration_max_mm": "mm",
        "penetration_p99_mm": "mm",
        "penetration_vertex_max_mm": "mm",
        "contact_force_n": "N",
        "sharp_press_s": "s",
        "sharp_penetration_max_mm": "mm",
        "face_contact_press_s": "s",
        "face_contact_penetration_max_mm": "mm",
        "face_contact_apex_beyond_tip_mm": "mm",
        "face_contact_sharp_press_s": "s", "face_contact_sharp_penetration_max_mm": "mm",
        "axis_mesh_press_s": "s", "axis_mesh_penetration_max_mm": "mm", "axis_mesh_apex_beyond_tip_mm": "mm",
        "axis_mesh_sharp_press_s": "s", "axis_mesh_sharp_penetration_max_mm": "mm",
        "reference_ms_median": "ms", "physics_reference_ms_min": "ms", "press_over_reference": "1", "frame_over_reference": "1",
    },
    requires=("benchmarks.twin_bench", "twin.physics", "twin.render"),
)
def run(ctx: Context) -> Result:
    """Digital twin: seconds per 5 mm press, ms per stereo frame, skin-indenter gap in contact."""
    from pipeline.design import load_design
    from benchmarks.twin_bench import run_twin_bench

    raw = run_twin_bench(ctx.out_dir / "twin_bench", quick=ctx.quick, progress=ctx.progress)
    ref_ms = float(raw["reference_ms_median"])
    out = Result(designs=[load_design(raw["design"])])
    out.metric("press_s_median", raw["press_s_median"], "s")
    out.metric("model_build_s_median", raw["model_build_s_median"], "s")
    frame_ms = raw.get("frame_ms_median")
    out.metric("frame_ms_median", float("nan") if frame_ms is None else frame_ms, "ms")
    # machine-independent speed (what the CI gate holds): the fastest press in units of the fastest run of a
    # fixed MuJoCo job timed between the presses (benchmarks.twin_bench.physics_reference_ms), the fastest frame
    # in units of the fastest run of the pipeline's reference job timed between the frames
    # (benchmarks.latency.reference_workload_ms). Fastest against fastest: a process sharing the cores only adds
    # time, to either, so the minima are the uncontended speeds and their ratio holds on a loaded machine.
    out.metric("reference_ms_median", ref_ms, "ms")
    phys_ms = float(raw["physics_reference_ms_min"])
    out.metric("physics_reference_ms_min", phys_ms, "ms")
    out.metric("press_over_reference", 1e3 * raw["press_s_min"] / phys_ms, "1")
    frame_min = raw.get("frame_ms_min")
    out.metric("frame_over_reference", float("nan") if frame_min is None
               else frame_min / float(raw["frame_reference_ms_min"]), "1")
    out.metric("gap_max_mm", raw["gap_max_mm"], "mm")
    out.metric("gap_rms_mm", raw["gap_rms_mm"], "mm")
    out.metric("settle_converged_fraction", float(np.mean(raw["settle_converged"])), "1")
    out.metric("mesh_dofs", raw["mesh_dofs"], "1")
    out.metric("friction", raw["friction"], "1")
    out.metric("frictionless_direct_press_s", raw["frictionless_direct_press_s"], "s")
    out.metric("followed_press_s", raw["followed_press_s"], "s")
    out.metric("direct_vs_followed_marker_max_mm", raw["direct_vs_followed_marker_max_mm"], "mm")
    for k, unit in (("penetration_max_mm", "mm"), ("penetration_p99_mm", "mm"), ("penetration_vertex_max_mm", "mm"),
                    ("contact_force_n", "N"), ("sharp_press_s", "s"), ("sharp_penetration_max_mm", "mm"),
                    ("face_contact_press_s", "s"), ("face_contact_penetration_max_mm", "mm"),
                    ("face_contact_apex_beyond_tip_mm", "mm"), ("face_contact_sharp_press_s", "s"),
                    ("face_contact_sharp_penetration_max_mm", "mm"), ("axis_mesh_press_s", "s"),
                    ("axis_mesh_penetration_max_mm", "mm"), ("axis_mesh_apex_beyond_tip_mm", "mm"),
                    ("axis_mesh_sharp_press_s", "s"), ("axis_mesh_sharp_penetration_max_mm", "mm")):
        out.metric(k, raw[k], unit)
    out.notes.append("Penetration: the outer skin's vertices, face centroids, edge midpoints and the indenter's 0.1 mm "
                     "samples against the indenter's true surface (twin.validity); gap: at the vertices MuJoCo sees "
                     f"touching only. σ² = 10 frame: {'valid' if raw['physics_valid'] else 'INVALID: ' + '; '.join(raw['physics_reasons'])}; "
                     f"σ² = 5/3 frame: {'valid' if raw['sharp_physics_valid'] else 'invalid'} "
                     f"({raw['sharp_penetration_max_mm']:.2f} mm).")
    out.tables["presses"] = [{"press_s": p, "model_build_s": b, "model_from_cache": bool(mc), "direct": bool(dr),
                              "settle_steps": s, "converged": bool(c)}
                             for p, b, mc, dr, s, c in zip(raw["press_s_all"], raw["model_build_s_all"],
                                                          raw["model_from_cache"], raw["press_direct"],
                                                          raw["settle_steps"], raw["settle_converged"])]
    out.notes.append(f"Presses carry the design's friction (μ = {raw['friction']:g}) and follow the path to the "
                     f"captured pose. Frictionless, the captured pose is solved directly (twin.physics.SkinSim.solve_at) "
                     f"in {raw['frictionless_direct_press_s']:.2f} s; along the followed path it took "
                     f"{raw['followed_press_s']:.2f} s ({raw['followed_steps']} steps) and its markers differ from the "
                     f"direct equilibrium by at most {raw['direct_vs_followed_marker_max_mm']:.4f} mm.")
    goals = raw.get("goals", {})
    out.notes.append(f"Twin goals on the reference machine (benchmarks.twin_bench): press ≤ {goals.get('press_s')} s, "
                     f"gap ≤ {goals.get('gap_max_mm')} mm, ≤ {goals.get('frame_ms')} ms per frame. "
                     f"MuJoCo warnings: {raw.get('mujoco_warnings')}. Raw output: twin_bench/twin.json.")
    if raw.get("render_note"):
        out.notes.append(raw["render_note"])
    for key, metric, unit in (("press_s", "press_s_median", "s"), ("gap_max_mm", "gap_max_mm", "mm"),
                              ("frame_ms", "frame_ms_median", "ms"), ("sharp_press_s", "sharp_press_s", "s"),
                              ("penetration_max_mm", "penetration_max_mm", "mm"),
                              ("penetration_max_mm", "sharp_penetration_max_mm", "mm"),
                              ("face_contact_press_s", "face_contact_press_s", "s"),
                              ("face_contact_sharp_press_s", "face_contact_sharp_press_s", "s"),
                              ("penetration_max_mm", "face_contact_penetration_max_mm", "mm"),
                              ("penetration_max_mm", "face_contact_sharp_penetration_max_mm", "mm"),
                              ("axis_mesh_press_s", "axis_mesh_press_s", "s"),
                              ("axis_mesh_sharp_press_s", "axis_mesh_sharp_press_s", "s"),
                              ("penetration_max_mm", "axis_mesh_penetration_max_mm", "mm"),
                              ("penetration_max_mm", "axis_mesh_sharp_penetration_max_mm", "mm")):
        if key in goals:
            v = out.metrics[metric][0]
            out.findings.append(Finding(f"twin goal: {metric} ≤ {goals[key]:g} {unit}", f"{v:.3g} {unit} measured",
                                        None if not np.isfinite(v) else bool(v <= goals[key])))
    return out
