"""The digital twin's own benchmark (``stereotactip bench twin``): seconds per press, milliseconds per stereo
frame, the skin–indenter gap and face-level penetration, on the default design and the contact meshes
(wrapped with units and gates by ``benchmarks/experiments/twin.py``). The presses are the twin's own: with the
design's friction (``[twin] friction``), so they follow the path to the captured pose. One frictionless press is
timed beside them through the direct quasi-static solve, which only frictionless contact allows, and checked
against the same press along the followed path."""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline.design import DEFAULT_DESIGN

__all__ = ["run_twin_bench"]


def _timed_press(design, indenter, mesh, depth_mm: float = 5.0):
    """One press to ``depth_mm`` on its default path (model set-up included): seconds, settle stats, truth."""
    from twin import robot
    from twin.physics import SkinSim

    t0 = time.perf_counter()
    sim = SkinSim(design, indenter, mesh=mesh)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(depth_mm))
    return time.perf_counter() - t0, stats, truth


def _apex_beyond_tip_mm(truth, depth_mm: float) -> float:
    """How far the outer-skin vertex on the axis lies beyond the tip at ``depth_mm`` (mm; < 0: short of it)."""
    v = truth.skin_vertices_mm
    return float(-depth_mm - v[np.argmin(np.hypot(v[:, 0], v[:, 1])), 2])


N_PRESS = 3                 # default-path presses timed (the first compiles the model, the others copy it)
N_FRAMES = 20               # stereo frames timed after one warm-up

# A fixed MuJoCo job of the kind a press is (a 3-D elastic flex pressed by a rigid body: the discrete
# integrator, the CG solver, contacts), written here rather than built by the twin so that a change to the
# twin's model does not move it. Press time in units of it compares across machines and loads where the
# pipeline's reference job (OpenCV and a dense solve) does not: in units of that job the same press measured
# 632-1113 in runs on 2-core hosts (this machine on three days and the CI host), 69-84 in units of this one
# (2026-11-27, quiet, beside a process spinning on a core, and in the fresh-clone CI run).
_PHYSICS_REFERENCE_XML = """
<mujoco model="physics_reference">
  <option integrator="discrete" solver="CG" timestep="0.002" gravity="0 0 0" tolerance="1e-6"/>
  <worldbody>
    <body name="indenter" mocap="true" pos="0 0 0.0115">
      <geom type="sphere" size="0.004"/>
    </body>
    <flexcomp name="gel" type="grid" dim="3" count="9 9 4" spacing="0.0025 0.0025 0.0025" pos="0 0 0.00375"
              radius="0.0002" mass="0.5">
      <pin gridrange="0 0 0 8 8 0"/>
      <edge equality="false"/>
      <elasticity young="2e5" poisson="0.3" damping="0.005"/>
      <contact selfcollide="none" condim="3"/>
    </flexcomp>
  </worldbody>
</mujoco>"""
PHYSICS_REFERENCE_STEPS = 30    # the sphere reaches the gel at step 0 and presses 1.5 mm into it by step 30
_PHYSICS_REFERENCE: list = []   # the compiled model and its data, once per process


def physics_reference_ms(repeats: int = 3) -> float:
    """Wall time (ms, fastest of ``repeats``) of :data:`PHYSICS_REFERENCE_STEPS` steps of a fixed MuJoCo
    job: a 9x9x4-vertex elastic grid, its base pinned, pressed by a sphere (~30 contacts). The fastest
    run is the machine's uncontended speed: another process can only add time to a run."""
    import mujoco as mj

    if not _PHYSICS_REFERENCE:
        model = mj.MjModel.from_xml_string(_PHYSICS_REFERENCE_XML)
        _PHYSICS_REFERENCE.extend((model, mj.MjData(model)))
    model, data = _PHYSICS_REFERENCE
    times = []
    for _ in range(max(1, int(repeats))):
        mj.mj_resetData(model, data)
        t0 = time.perf_counter()
        for k in range(PHYSICS_REFERENCE_STEPS):
            data.mocap_pos[0, 2] = 0.0115 - 0.002 * min(1.0, k / 40)
            mj.mj_step(model, data)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(min(times))


DEPTH_MM = 5.0
GOALS = {"press_s": 3.0, "sharp_press_s": 6.0, "gap_max_mm": 0.1, "frame_ms": 50.0,
         "face_contact_press_s": 3.0, "face_contact_sharp_press_s": 6.0,
         "axis_mesh_press_s": 3.0, "axis_mesh_sharp_press_s": 6.0,
         "penetration_max_mm": 0.05}


def run_twin_bench(out_dir, quick: bool = False, progress: bool = True) -> dict:
    """Twin speed and fidelity: s per 5 mm press, ms per stereo frame, skin–indenter gap (σ²=10 Gaussian).

    A press is model set-up (compiled for the first press, copied from the cache after) plus
    :func:`twin.robot.execute` of a 5 mm press with the design's friction (the path followed to the captured
    pose). The same press frictionless is timed twice for comparison, solved directly at the captured pose and
    along the followed path, and the largest marker difference between the two equilibria recorded. Writes ``out_dir/twin.json`` and returns the same
    dict. Goals on the 2-core reference machine: press ≤ 3 s with gap ≤ 0.1 mm; ≤ 50 ms per stereo frame.
    """
    from pipeline.design import load_design
    from pipeline.io.atomic import atomic_write_json
    from twin.indenters import make_indenter

    design = load_design(DEFAULT_DESIGN)
    ind = make_indenter("gaussian", h_mm=5.0, sigma2_mm2=10.0)
    sharp_ind = make_indenter("gaussian", h_mm=5.0, sigma2_mm2=5.0 / 3.0)
    default = _default_presses(design, ind, progress)
    followed = _frictionless_presses(design, ind)
    result = {**_press_fields(design, default, followed),
              **_contact_mesh_fields(design, ind, sharp_ind),
              "goals": dict(GOALS)}
    frames = _frame_timing(design, default.truth, progress)
    result.update(frames.fields)
    ref_ms = default.reference_ms + frames.reference_ms
    result["reference_ms_median"] = float(np.median(ref_ms))
    result["reference_ms_all"] = [float(v) for v in ref_ms]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "twin.json", result)
    return result


class _DefaultPresses(NamedTuple):
    """The default-path presses: per press its timings and settle stats; the last press's sim state and truth."""

    press_s: list
    build_s: list
    settle_steps: list
    converged: list
    direct: list
    cached: list
    gaps: np.ndarray        # the last press's skin–indenter gap (mm)
    warnings: list          # the last press's MuJoCo warnings
    truth: object           # the last press's truth
    reference_ms: list      # the reference job timed before each press (the machine's speed then)
    physics_reference_ms: list  # the physics reference job timed before each press


def _default_presses(design, ind, progress: bool = True) -> _DefaultPresses:
    """Press ``ind`` 5 mm into ``design`` :data:`N_PRESS` times on the default path with the design's friction
    (robot.execute: the path followed to the captured pose), timing model set-up and press."""
    from tqdm import tqdm

    from benchmarks.latency import reference_workload_ms
    from twin import robot
    from twin.physics import SkinSim

    press_s, build_s, settle_steps, converged, direct, cached, ref_ms, phys_ms = [], [], [], [], [], [], [], []
    for _ in tqdm(range(N_PRESS), desc="bench twin: presses", disable=not progress):
        ref_ms.append(reference_workload_ms(repeats=5))
        phys_ms.append(physics_reference_ms())
        t0 = time.perf_counter()
        sim = SkinSim(design, ind)
        t1 = time.perf_counter()
        (_, stats, truth), = robot.execute(sim, robot.press_motion(DEPTH_MM))
        press_s.append(time.perf_counter() - t0)
        build_s.append(t1 - t0)
        settle_steps.append(stats.steps)
        converged.append(stats.converged)
        direct.append(stats.direct)
        cached.append(sim.model_from_cache)
        gaps = sim.gap_mm()
        warn = sim.warnings()
    return _DefaultPresses(press_s, build_s, settle_steps, converged, direct, cached, gaps, warn, truth, ref_ms,
                           phys_ms)


class _FrictionlessPresses(NamedTuple):
    """The same press frictionless: solved directly at the captured pose, and along the followed path (1 mm/s
    profile, contact increments, lag limit)."""

    direct_s: float
    direct_truth: object
    seconds: float          # the followed path
    truth: object
    gaps: np.ndarray
    steps: int
    mesh_dofs: int


def _frictionless_presses(design, ind) -> _FrictionlessPresses:
    """The press frictionless, solved directly and along the followed path, for comparison."""
    from twin import robot
    from twin.physics import SkinSim

    t0 = time.perf_counter()
    sim = SkinSim(design, ind, friction=0.0)
    (_, _, direct_truth), = robot.execute(sim, robot.press_motion(DEPTH_MM))
    direct_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim = SkinSim(design, ind, friction=0.0)
    (_, _, truth), = robot.execute(sim, robot.press_motion(DEPTH_MM), direct=False)
    seconds = time.perf_counter() - t0
    return _FrictionlessPresses(direct_s, direct_truth, seconds, truth, sim.gap_mm(), int(sim.steps_taken),
                                int(sim.model.nv))


def _press_fields(design, default: _DefaultPresses, followed: _FrictionlessPresses) -> dict:
    """The σ² = 10 press's speed, settle statistics, gap, penetration and the frictionless direct-vs-followed
    agreement."""
    from twin.physics import resolve_friction

    gaps, f_gaps, val = default.gaps, followed.gaps, default.truth.validity
    return {
        "units": {"press_s": "s", "frame_ms": "ms", "gap": "mm"},
        "design": design.name, "indenter": {"name": "gaussian", "h_mm": 5.0, "sigma2_mm2": 10.0}, "depth_mm": DEPTH_MM,
        "friction": resolve_friction(design, None),
        "press_s_median": float(np.median(default.press_s)), "press_s_min": float(np.min(default.press_s)),
        "press_s_all": default.press_s,
        "physics_reference_ms_min": float(np.min(default.physics_reference_ms)),
        "physics_reference_ms_all": [float(v) for v in default.physics_reference_ms],
        "press_direct": default.direct, "model_from_cache": default.cached,
        "model_build_s_median": float(np.median(default.build_s)), "model_build_s_all": default.build_s,
        "settle_steps": default.settle_steps,
        "settle_converged": default.converged, "mesh_dofs": followed.mesh_dofs,
        "gap_max_mm": float(np.max(np.abs(gaps))) if len(gaps) else float("nan"),
        "gap_rms_mm": float(np.sqrt(np.mean(gaps**2))) if len(gaps) else float("nan"),
        "gap_points": int(len(gaps)), "mujoco_warnings": default.warnings,
        "frictionless_direct_press_s": followed.direct_s,
        "followed_press_s": followed.seconds, "followed_steps": followed.steps,
        "followed_gap_max_mm": float(np.max(np.abs(f_gaps))) if len(f_gaps) else float("nan"),
        "direct_vs_followed_marker_max_mm": float(np.max(np.linalg.norm(
            followed.direct_truth.marker_xyz_mm - followed.truth.marker_xyz_mm, axis=1))),
        "penetration_max_mm": val["penetration_max_mm"], "penetration_p99_mm": val["penetration_p99_mm"],
        "penetration_vertex_max_mm": val["penetration_vertex_max_mm"], "contact_force_n": val["contact_force_n"],
        "physics_valid": bool(val["valid"]), "physics_reasons": val["reasons"],
    }


def _contact_mesh_fields(design, ind, sharp_ind) -> dict:
    """The sharpest Gaussian on the default mesh, both Gaussians with face contact on the default mesh and on the
    axis contact mesh the Gaussian experiment uses: time, penetration, validity, how far the apex stands off the
    tip (all with the design's friction)."""
    from twin.physics import AXIS_CONTACT_MESH, MeshSpec

    # the sharpest Gaussian of the paper (σ² = 5/3 mm², tip radius 0.33 mm): time and physics verdict
    sharp_s, s_stats, s_truth = _timed_press(design, sharp_ind, MeshSpec())
    # the same sigma^2 = 10 press with face contact (twin.contact): penetration vs how far the apex stands off
    fc_s, _, fc_truth = _timed_press(design, ind, MeshSpec(face_contact=True))
    fc_apex_beyond = _apex_beyond_tip_mm(fc_truth, DEPTH_MM)
    fc_sharp_s, _, fc_sharp_truth = _timed_press(design, sharp_ind, MeshSpec(face_contact=True))
    # the axis contact mesh the Gaussian experiment uses (0.5 mm core + face contact), sigma^2 = 10 and 5/3
    axis = {}
    for tag, a_ind in (("s10", ind), ("s5_3", sharp_ind)):
        secs, a_stats, a_truth = _timed_press(design, a_ind, AXIS_CONTACT_MESH)
        axis[tag] = {"press_s": secs, "penetration_max_mm": a_truth.validity["penetration_max_mm"],
                     "valid": bool(a_truth.validity["valid"]), "direct": bool(a_stats.direct),
                     "apex_beyond_tip_mm": _apex_beyond_tip_mm(a_truth, DEPTH_MM)}
    s_val = s_truth.validity
    return {
        "sharp_press_s": sharp_s, "sharp_press_direct": bool(s_stats.direct),
        "sharp_penetration_max_mm": s_val["penetration_max_mm"], "sharp_physics_valid": bool(s_val["valid"]),
        "face_contact_press_s": fc_s, "face_contact_penetration_max_mm": fc_truth.validity["penetration_max_mm"],
        "face_contact_apex_beyond_tip_mm": fc_apex_beyond, "face_contact_valid": bool(fc_truth.validity["valid"]),
        "face_contact_sharp_press_s": fc_sharp_s,
        "face_contact_sharp_penetration_max_mm": fc_sharp_truth.validity["penetration_max_mm"],
        "face_contact_sharp_valid": bool(fc_sharp_truth.validity["valid"]),
        "axis_mesh_press_s": axis["s10"]["press_s"], "axis_mesh_penetration_max_mm": axis["s10"]["penetration_max_mm"],
        "axis_mesh_apex_beyond_tip_mm": axis["s10"]["apex_beyond_tip_mm"],
        "axis_mesh_sharp_press_s": axis["s5_3"]["press_s"],
        "axis_mesh_sharp_penetration_max_mm": axis["s5_3"]["penetration_max_mm"], "axis_mesh": axis,
    }


class _FrameTiming(NamedTuple):
    fields: dict            # frame_ms_median and frame_ms_n, or the reason the renderer is unavailable
    reference_ms: list      # the reference job timed before each frame


def _frame_timing(design, truth, progress: bool = True) -> _FrameTiming:
    """Milliseconds per stereo frame of the pressed skin (:data:`N_FRAMES` after one warm-up)."""
    from tqdm import tqdm

    from benchmarks.latency import reference_workload_ms

    try:
        from twin.render import StereoRenderer
    except ImportError as exc:   # renderer not installed / no GL
        return _FrameTiming({"frame_ms_median": None, "render_note": f"renderer unavailable: {exc}"}, [])
    r = StereoRenderer(design, rng=np.random.default_rng(0))
    r.render_markers(truth.marker_xyz_mm, truth.marker_axis, skin_vertices_mm=truth.skin_vertices_mm,
                     skin_faces=truth.skin_faces)   # warm-up (static meshes, shaders)
    ms, ref_ms = [], []
    for _ in tqdm(range(N_FRAMES), desc="bench twin: frames", disable=not progress):
        ref_ms.append(reference_workload_ms())
        t0 = time.perf_counter()
        r.render_markers(truth.marker_xyz_mm, truth.marker_axis, skin_vertices_mm=truth.skin_vertices_mm,
                         skin_faces=truth.skin_faces)
        ms.append((time.perf_counter() - t0) * 1e3)
    return _FrameTiming({"frame_ms_median": float(np.median(ms)), "frame_ms_min": float(np.min(ms)),
                         "frame_reference_ms_min": float(np.min(ref_ms)), "frame_ms_n": N_FRAMES}, ref_ms)
