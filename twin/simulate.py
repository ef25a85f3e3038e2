"""Presses and motions of the twin → stereo frames + truth (+ calibration) in memory or on disk.

Python API
----------
* :func:`press_truth` / :func:`motion_truth`: physics only, ``list[Truth]`` (benchmarks that batch
  rendering separately).
* :func:`press` / :func:`run_motion`: the same, each truth rendered by
  :class:`twin.render.StereoRenderer` → ``list[(StereoFrame, Truth)]``.
* :func:`write_run`: frames, truth, calibration, metadata and a preview to a folder (used by the CLI).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.design import SensorDesign, to_dict
from pipeline.types import StereoFrame
from twin import robot
from twin.indenters import Indenter
from twin.physics import MeshSpec, PhysicsError, SkinSim, max_depth_mm
from twin.truth import Truth

__all__ = ["press_truth", "motion_truth", "press", "run_motion", "render_truths", "write_run", "SimRun"]


class SimRun(list):
    """A list of Truth (or (StereoFrame, Truth)) with ``meta``: settle stats and timings."""

    meta: dict[str, Any]


def _check_depth(design: SensorDesign, depth_mm: float) -> None:
    lim = max_depth_mm(design)
    if not np.isfinite(depth_mm) or depth_mm < 0 or depth_mm > lim:
        raise PhysicsError(f"depth {depth_mm!r} mm: must be in [0, {lim:g}] mm for design {design.name} "
                           f"(gel {design.optics.gel_thickness_mm:g} mm - pin {design.pins.height_mm:g} mm - margin)")


def _run(design: SensorDesign, indenter: Indenter, motion: robot.Motion, mesh: MeshSpec, progress: bool,
         friction: float | None = None) -> SimRun:
    from tqdm import tqdm

    t0 = time.perf_counter()
    sim = SkinSim(design, indenter, mesh=mesh, friction=friction)
    t_build = time.perf_counter() - t0
    n_cap = sum(w.capture for w in motion.waypoints) + robot.filmed_count(motion)
    with tqdm(total=n_cap, desc=f"twin {motion.name}", disable=not progress) as bar:
        res = robot.execute(sim, motion, progress=bar)
    out = SimRun(t for _, _, t in res)
    out.meta = {
        "motion": motion.name, "robot_speed_mm_s": robot.ROBOT_SPEED_MM_S, "friction": sim.friction,
        "timestamps_s": [t for t, _, _ in res],
        "settle": [{"steps": s.steps, "converged": s.converged, "last_motion_mm": s.last_motion_mm,
                    "seconds": s.seconds, "direct": s.direct, "damped_steps": s.damped_steps} for _, s, _ in res],
        "direct_solves": sim.direct_solves, "direct_rejections": sim.direct_rejections,
        "direct_wasted_steps": sim.direct_wasted_steps, "model_from_cache": sim.model_from_cache,
        "build_s": t_build, "physics_s": time.perf_counter() - t0 - t_build, "steps": sim.steps_taken,
        "mesh": {"fine_mm": mesh.fine_mm, "fine_half_mm": mesh.fine_half_mm, "vertices": int(len(sim.mesh.nodes_mm)),
                 "dofs": int(sim.model.nv)},
        "mujoco_warnings": sim.warnings(),
        "contact": ("vertex spheres + face contact (twin.contact)" if sim.face_contact else "vertex spheres only")
                   + (f"; face contact switched off: {sim.face_contact_fallback}" if sim.face_contact_fallback else ""),
        "surface_spheres": int(sim._n_surface_spheres),
        "validity": [t.validity for _, _, t in res],
        "invalid_frames": [i for i, (_, _, t) in enumerate(res)
                           if t.validity is not None and not t.validity["valid"] and not t.in_motion],
        "filmed_frames": [i for i, (_, _, t) in enumerate(res) if t.in_motion],
    }
    return out


def press_truth(design: SensorDesign, indenter: Indenter, depth_mm: float, *, n_frames: int = 1,
                yaw_deg: float = 0.0, mesh: MeshSpec = MeshSpec(), progress: bool = False,
                friction: float | None = None, film_every_mm: float = 0.0) -> SimRun:
    """Physics only: press ``depth_mm`` (skin contact at 0), ``n_frames`` truths at depth·k/n, with
    ``film_every_mm`` > 0 also truths filmed in motion on the way (:func:`twin.robot.press_motion`)."""
    _check_depth(design, depth_mm)
    return _run(design, indenter, robot.press_motion(depth_mm, n_frames=n_frames, yaw_deg=yaw_deg,
                                                     film_every_mm=film_every_mm), mesh, progress, friction)


def motion_truth(design: SensorDesign, indenter: Indenter, motion: str, *, yaw_deg: float = 0.0,
                 mesh: MeshSpec = MeshSpec(), progress: bool = False, friction: float | None = None) -> SimRun:
    """Physics only: one of :data:`twin.robot.MOTIONS` (``press`` = 5 mm, 5 frames)."""
    m = robot.press_motion(5.0, n_frames=5, yaw_deg=yaw_deg) if motion == "press" else \
        robot.tracking_motion(motion, yaw_deg=yaw_deg)
    return _run(design, indenter, m, mesh, progress, friction)


#: Where an invalid frame's pins that went beyond the gel are drawn: this far inside it (mm).
PIN_STOP_MM = 0.01


def render_truths(design: SensorDesign, truths: list[Truth], *, rng: np.random.Generator,
                  timestamps_s: list[float] | None = None) -> list[StereoFrame]:
    """Render each truth with one :class:`twin.render.StereoRenderer` (sensor noise from ``rng``).

    A frame flagged physically invalid because a pin's tip went beyond the gel (``pin_overrun_mm``) is
    drawn with those tips stopped :data:`PIN_STOP_MM` inside it, where the acrylic window would stop a
    real pin: the sequence keeps its frame, which is never scored (its truth says why)."""
    from twin.render import StereoRenderer

    r = StereoRenderer(design, rng=rng)
    frames = []
    for i, t in enumerate(truths):
        xyz = t.marker_xyz_mm
        if t.validity is not None and (t.validity.get("pin_overrun_mm") or 0.0) > 0:
            xyz = xyz.copy()
            xyz[:, 2] = np.maximum(xyz[:, 2], design.gel_acrylic_z_mm + PIN_STOP_MM)
        f = r.render_markers(xyz, t.marker_axis, skin_vertices_mm=t.skin_vertices_mm, skin_faces=t.skin_faces)
        ts = timestamps_s[i] if timestamps_s is not None else float(i)
        frames.append(StereoFrame(f.image, timestamp_s=ts, index=i, source=f"twin:{design.name}"))
    return frames


def _with_frames(design, truths: SimRun, rng) -> SimRun:
    frames = render_truths(design, list(truths), rng=rng, timestamps_s=truths.meta["timestamps_s"])
    out = SimRun(zip(frames, truths))
    out.meta = truths.meta
    return out


def press(design: SensorDesign, indenter: Indenter, depth_mm: float, *, n_frames: int = 1, yaw_deg: float = 0.0,
          rng: np.random.Generator, mesh: MeshSpec = MeshSpec(), progress: bool = False,
          friction: float | None = None, film_every_mm: float = 0.0) -> SimRun:
    """Press and render: ``[(StereoFrame, Truth), ...]`` for frames at depth·k/n_frames, k = 1..n (and those
    filmed in motion every ``film_every_mm`` of the path, in order)."""
    return _with_frames(design, press_truth(design, indenter, depth_mm, n_frames=n_frames, yaw_deg=yaw_deg,
                                            mesh=mesh, progress=progress, friction=friction,
                                            film_every_mm=film_every_mm), rng)


def run_motion(design: SensorDesign, indenter: Indenter, motion: str, *, rng: np.random.Generator,
               yaw_deg: float = 0.0, mesh: MeshSpec = MeshSpec(), progress: bool = False,
               friction: float | None = None) -> SimRun:
    """A scripted motion (:data:`twin.robot.MOTIONS`), rendered: ``[(StereoFrame, Truth), ...]``."""
    return _with_frames(design, motion_truth(design, indenter, motion, yaw_deg=yaw_deg, mesh=mesh,
                                             progress=progress, friction=friction), rng)


def write_run(out_dir: str | Path, design: SensorDesign, indenter: Indenter, run: SimRun, *,
              extra_meta: dict[str, Any]) -> Path:
    """Write frame_XXXX.png, truth_XXXX.npz, calib.yaml, meta.json and preview.png to ``out_dir``."""
    from pipeline.io.atomic import atomic_write_json, imwrite_atomic
    from twin.render import true_calibration

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for i, (frame, truth) in enumerate(run):
        imwrite_atomic(out / f"frame_{i:04d}.png", frame.image)
        truth.save_npz(out / f"truth_{i:04d}.npz")
    true_calibration(design).save_yaml(out / "calib.yaml")
    if len(run):
        _preview(out / "preview.png", *run[-1])
    meta = {"design": design.name, "design_dict": to_dict(design), "indenter": indenter.name,
            "params": {k: v for k, v in indenter.params.items() if isinstance(v, (int, float, str))},
            **extra_meta, **run.meta, "write_s": time.perf_counter() - t0}
    atomic_write_json(out / "meta.json", meta, indent=2, default=float)
    return out


def _preview(path: Path, frame: StereoFrame, truth: Truth) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 3.6), gridspec_kw={"width_ratios": [2.6, 1]})
    img = frame.image if frame.image.ndim == 2 else frame.image[:, :, ::-1]
    ax[0].imshow(img, cmap="gray")
    ax[0].set_title("stereo frame (left | right)")
    ax[0].axis("off")
    hm = truth.indenter
    im = ax[1].imshow(hm.z_mm, origin="lower", extent=[hm.x_mm[0], hm.x_mm[-1], hm.y_mm[0], hm.y_mm[-1]], cmap="viridis")
    ax[1].plot(truth.marker_xyz_mm[:, 0], truth.marker_xyz_mm[:, 1], ".", color="w", ms=2)
    ax[1].set_title("indenter z (sensor frame, mm) + markers")
    fig.colorbar(im, ax=ax[1])
    fig.tight_layout()
    from pipeline.io.atomic import savefig_atomic

    try:
        savefig_atomic(fig, path, dpi=90)
    finally:
        plt.close(fig)
