"""Scripted robot motions for the mocap indenter (the paper's Dobot MG400 at 1 mm/s).

A :class:`Motion` is a list of :class:`Waypoint` poses ``(x_mm, y_mm, depth_mm, yaw_deg)`` (see
:class:`twin.physics.SkinSim`), each optionally captured as a frame. :func:`execute` drives a
:class:`~twin.physics.SkinSim` through it: the indenter moves in straight lines in increments of at
most ``MAX_INCREMENT_MM`` per physics step (``CONTACT_INCREMENT_MM`` in contact, holding still while
a skin vertex lags more than ``PENETRATION_LIMIT_MM`` inside the indenter), and at every capture
waypoint the sim is settled to quasi-static equilibrium (criterion in
:data:`twin.solve.SETTLE_TOL_MM`). The equilibrium does not
depend on the rate, so the physics may move faster than the robot; the documented robot speed sets
the frames' timestamps (path length / speed) and is recorded in metadata. With frictionless contact
it does not depend on the path either: each captured pose is first solved directly
(:meth:`twin.physics.SkinSim.solve_at`, ~4x fewer steps), and the path is followed only where that
solve is rejected (a vertex would end inside the indenter: steep sines, sharp tips, letters) or with
friction; ``SettleStats.direct`` says which.

Motions (paper Sec. IV-B and IV-D):
* ``press``: from 1 mm clear of the skin down to ``depth`` at 1 mm/s, ``n_frames`` evenly spaced; with
  ``film_every_mm`` also frames filmed in motion on the way (below).
* ``tracking-G``: 1 mm vertical steps from 1 mm depth (1, 2, 3, 4, 5 mm).
* ``tracking-e``: at 3 mm depth, 1 mm lateral steps in +x (0..4 mm).
* ``tracking-o``: from touch, a rapid 2 mm down + 2 mm sideways move in 4 frames.
* ``press_repetitions``: a press repeated with the indenter yawed by 120° between repetitions.

Frames filmed in motion: a camera filming a press sees the skin while the indenter moves, not only at
the poses where the robot stops. A waypoint's ``film_every_mm`` captures the state every that many mm
of the robot's path into it, after the physics step that reaches the mark, without stopping or
settling: the path, and so every settled frame, is exactly that of the same motion unfilmed (the
capture only reads the state). Such a frame's truth is flagged ``in_motion`` and is never valid (the
skin lags the indenter by up to the lag limit); it feeds identification across frames and is never
scored against the indenter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.physics import PhysicsError, SkinSim, max_depth_mm
from twin.solve import SettleStats

__all__ = ["Waypoint", "Motion", "press_motion", "tracking_motion", "press_repetitions", "execute", "filmed_count",
           "MOTIONS", "ROBOT_SPEED_MM_S", "RAPID_SPEED_MM_S"]

ROBOT_SPEED_MM_S = 1.0     # paper: pressed at 1 mm/s
RAPID_SPEED_MM_S = 20.0    # the "rapid" diagonal move of the 'o' experiment
APPROACH_MM = 1.0          # start this far clear of the skin
MOTIONS = ("press", "tracking-G", "tracking-e", "tracking-o")


@dataclass(frozen=True)
class Waypoint:
    x_mm: float
    y_mm: float
    depth_mm: float
    yaw_deg: float = 0.0
    capture: bool = True
    speed_mm_s: float = ROBOT_SPEED_MM_S
    film_every_mm: float = 0.0   # > 0: frames filmed in motion every this many mm of the path into this waypoint

    @property
    def pose(self) -> tuple[float, float, float, float]:
        return (self.x_mm, self.y_mm, self.depth_mm, self.yaw_deg)


@dataclass(frozen=True)
class Motion:
    name: str
    waypoints: tuple[Waypoint, ...]


def press_motion(depth_mm: float, *, n_frames: int = 1, yaw_deg: float = 0.0, x_mm: float = 0.0,
                 y_mm: float = 0.0, film_every_mm: float = 0.0) -> Motion:
    """Approach from ``APPROACH_MM`` clear of the skin to ``depth_mm``; frames at depth·k/n, k = 1..n, and with
    ``film_every_mm`` > 0 frames filmed in motion every that many mm of the path between them (module notes:
    from rest, the first at the touch)."""
    if n_frames < 1:
        raise PhysicsError(f"n_frames must be >= 1, got {n_frames}")
    if not (np.isfinite(film_every_mm) and film_every_mm >= 0):
        raise PhysicsError(f"film_every_mm must be >= 0 (0: no frames in motion), got {film_every_mm!r}")
    wps = [Waypoint(x_mm, y_mm, -APPROACH_MM, yaw_deg, capture=False)]
    wps += [Waypoint(x_mm, y_mm, depth_mm * k / n_frames, yaw_deg, film_every_mm=film_every_mm)
            for k in range(1, n_frames + 1)]
    return Motion("press", tuple(wps))


def tracking_motion(name: str, *, yaw_deg: float = 0.0) -> Motion:
    """The paper's tracking motions (``tracking-G``, ``tracking-e``, ``tracking-o``); first frame at rest."""
    rest = Waypoint(0.0, 0.0, -APPROACH_MM, yaw_deg, capture=True)
    if name == "tracking-G":
        wps = [rest] + [Waypoint(0.0, 0.0, float(d), yaw_deg) for d in (1, 2, 3, 4, 5)]
    elif name == "tracking-e":
        wps = [rest, Waypoint(0.0, 0.0, 3.0, yaw_deg)] + [Waypoint(float(x), 0.0, 3.0, yaw_deg) for x in (1, 2, 3, 4)]
    elif name == "tracking-o":
        wps = [rest, Waypoint(0.0, 0.0, 0.0, yaw_deg)]
        wps += [Waypoint(0.5 * k, 0.0, 0.5 * k, yaw_deg, speed_mm_s=RAPID_SPEED_MM_S) for k in (1, 2, 3, 4)]
    else:
        raise PhysicsError(f"unknown motion {name!r}; known: {', '.join(MOTIONS)}")
    return Motion(name, tuple(wps))


def press_repetitions(depth_mm: float, *, repetitions: int = 3, yaw_step_deg: float = 120.0) -> Motion:
    """The Gaussian/sine protocol: press, lift, yaw the indenter by ``yaw_step_deg``, press again."""
    wps = []
    for r in range(repetitions):
        yaw = r * yaw_step_deg
        wps += [Waypoint(0.0, 0.0, -APPROACH_MM, yaw, capture=False), Waypoint(0.0, 0.0, depth_mm, yaw)]
    return Motion("press_repetitions", tuple(wps))


def execute(sim: SkinSim, motion: Motion, *, progress=None, direct: bool = True) -> list[tuple[float, SettleStats, object]]:
    """Run a motion; returns ``(timestamp_s, settle stats, Truth)`` for every captured waypoint.

    The first waypoint is reached by teleporting (the indenter is clear of the skin); the timestamp
    is the robot's path length so far divided by each segment's documented speed. With ``direct``
    (default) each captured pose is first solved directly (:meth:`SkinSim.solve_at`: valid for
    frictionless contact, checked, and undone when a vertex ends inside the indenter); where that is
    rejected, for waypoints that are not captured and for those filmed on the way (``film_every_mm``), the
    path is followed (:meth:`SkinSim.move_to`); a filmed frame's settle stats are zero steps, not converged.
    """
    deepest = max(w.depth_mm for w in motion.waypoints)
    if deepest > max_depth_mm(sim.design) + 1e-9:
        raise PhysicsError(f"motion {motion.name!r}: depth {deepest:g} mm exceeds what the gel allows "
                           f"({max_depth_mm(sim.design):g} mm = gel thickness - pin height - margin)")
    if not sim.face_contact:
        return _execute(sim, motion, progress, direct)
    # Face contact (twin.contact) keeps skin faces out of tips and crests. Should MuJoCo's solve still fail
    # with it (with tens of thousands of face-sphere constraints the discrete integrator's iterative M + K
    # solve runs out of iterations: mjWARN_INERTIA), the motion is run again from the same start with
    # vertex contacts only; the fallback is recorded on the sim and each frame's own validity check
    # reports what that costs.
    start = sim.checkpoint()
    try:
        out = _execute(sim, motion, progress, direct, stop_if_unstable=start.warnings)
    except sim._mj.FatalError:
        # a solve that failed mid-settle can diverge before the warning is checked: the vertices fly apart and
        # MuJoCo's collision arena overflows (measured on a 2π/5 sine pressed 5 mm) - the same failed solve
        out = None
    if out is not None:
        return out
    sim.restore(start)
    sim.disable_face_contact("MuJoCo's solve failed with face contact (too many face-sphere constraints)")
    if progress is not None and hasattr(progress, "reset"):
        progress.reset()
    return _execute(sim, motion, progress, direct)


def _execute(sim: SkinSim, motion: Motion, progress, direct: bool, *, stop_if_unstable: list[int] | None = None):
    """The motion itself (see :func:`execute`); None if MuJoCo's solve failed after the warning counts
    ``stop_if_unstable`` (when given)."""
    out = []
    t = 0.0
    first = motion.waypoints[0]
    sim.set_pose(*first.pose)
    prev = np.array(first.pose)
    for k, wp in enumerate(motion.waypoints):
        stats = None
        if k > 0:
            cur = np.array(wp.pose)
            dist = float(np.linalg.norm(cur[:3] - prev[:3]))
            if direct and wp.capture and wp.film_every_mm <= 0:
                stats = sim.solve_at(*wp.pose)
            if stats is None:
                sim.move_to(*wp.pose, on_step=_filming(sim, wp, dist, t, out, progress))
            if stop_if_unstable is not None and sim.unstable(stop_if_unstable):
                return None
            t += dist / wp.speed_mm_s
            prev = cur
        if wp.capture:
            if stats is None:
                stats = sim.settle()
            if stop_if_unstable is not None and sim.unstable(stop_if_unstable):
                return None
            out.append((t, stats, sim.truth(settled=stats.converged)))
            if progress is not None:
                progress.update()
    return out


def _filming(sim: SkinSim, wp: Waypoint, dist_mm: float, t0_s: float, out: list, progress):
    """The ``on_step`` of :meth:`SkinSim.move_to` for a segment of ``dist_mm`` into ``wp`` started at ``t0_s``:
    a frame filmed in motion (truth flagged ``in_motion``) after the step that passes each mark of
    ``wp.film_every_mm`` along the path, short of the segment's end; None when the segment is not filmed."""
    marks = _marks(wp, dist_mm)
    if not marks:
        return None

    def film(s: float) -> None:
        while marks and s * dist_mm >= marks[0] - 1e-9:
            marks.pop(0)
            out.append((t0_s + s * dist_mm / wp.speed_mm_s, SettleStats(0, False, 0.0, 0.0),
                        sim.truth(settled=False, in_motion=True)))
            if progress is not None:
                progress.update()
    return film


def filmed_count(motion: Motion) -> int:
    """How many frames a motion films in motion (:func:`press_motion` ``film_every_mm``)."""
    pts = [np.array(wp.pose[:3]) for wp in motion.waypoints]
    return sum(len(_marks(wp, float(np.linalg.norm(b - a)))) for wp, a, b in zip(motion.waypoints[1:], pts, pts[1:]))


def _marks(wp: Waypoint, dist_mm: float) -> list[float]:
    """Where along a segment of ``dist_mm`` into ``wp`` frames are filmed (mm of path, short of its end)."""
    if wp.film_every_mm <= 0 or dist_mm <= 0:
        return []
    return [float(m) for m in np.arange(wp.film_every_mm, dist_mm - 1e-9, wp.film_every_mm)]
