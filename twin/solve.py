"""Reaching quasi-static equilibrium: the settle criterion and the direct solve at a pose.

:class:`twin.physics.SkinSim` reaches a pose in one of two ways. :meth:`~twin.physics.SkinSim.move_to`
follows the robot's path in small increments (holding while a contact lags) and then settles
(:func:`settle`); :func:`solve_at` places the indenter at the pose directly, warm-starts the mesh
geometrically and settles with mass-proportional damping. With frictionless contact the equilibrium
depends on the pose only, so both reach the same state (σ² = 10, 5 mm: markers within 0.005 mm, 66
instead of 273 steps); the direct result is kept only if no outer vertex (with face contact, no face) ends
inside the indenter, else the state is restored and the path followed. :func:`twin.robot.execute` tries the direct solve first at
every captured pose.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np

from twin import units, volumetric
from twin.model import _FLIP

if TYPE_CHECKING:
    from twin.physics import SkinSim

__all__ = ["SettleStats", "settle", "solve_at", "SETTLE_TOL_MM", "DIRECT_ACCEPT_MM"]

SETTLE_TOL_MM = 5e-3         # quasi-static: the markers' mean position over the last ...
SETTLE_CONSECUTIVE = 10      # ... this many steps differs from that over the previous as many by < tol (every
                             # marker). Per-step vertex motion < 5e-3 mm for 3 steps stopped 0.11 mm short of
                             # equilibrium (slow gel modes); markers also jitter ~0.003 mm a step in frictionless
                             # contact (σ² = 10, 5 mm: noise floor 0.005-0.008 mm vs a 300-step run), which the
                             # window means average out
SETTLE_MAX_STEPS = 400
SETTLE_DAMPED_PER_S = 100.0  # a press not settled after SETTLE_MAX_STEPS continues with mass-proportional DOF damping
SETTLE_DAMPED_STEPS = 400    # c = α m for at most this many steps more. Face contacts at zero distance switch on and
                             # off every step (1-5 of ~65 on a terrain tap) and keep the coarse rim cells ringing
                             # (0.01-0.03 mm drift per window after 600 undamped steps); the damping removes that energy
                             # and, the contact being frictionless, leaves the equilibrium where it is. A press that
                             # settles undamped is not touched (every earlier frame is reproduced bit for bit)
DIRECT_DAMPING_PER_S = 10.0  # mass-proportional DOF damping c = α m while a direct solve settles (α = 10/s: the σ² = 10
                             # press settles in 66 steps instead of 156; 0: 156, 30: 82, 60: 116, 300: 256 followed)
DIRECT_ACCEPT_MM = 0.1       # a direct solve is kept only if no free outer vertex (or face) ends deeper inside
DIRECT_ABORT_MM = 0.3        # ... and is abandoned (state restored) as soon as one is this deep
DIRECT_CHECK_EVERY = 4       # steps between those checks while settling


@dataclass(frozen=True)
class SettleStats:
    """Outcome of :func:`settle`: steps taken, converged flag, last per-step motion (mm), seconds;
    ``direct``: the pose was solved directly (:func:`solve_at`) rather than reached along the path."""

    steps: int
    converged: bool
    last_motion_mm: float
    seconds: float
    direct: bool = False
    damped_steps: int = 0   # steps of the damped continuation (SETTLE_DAMPED_PER_S), 0 if it settled without


def settle(step: Callable[[], float], markers: Callable[[], tuple], model, *, tol_mm: float = SETTLE_TOL_MM,
           consecutive: int = SETTLE_CONSECUTIVE, max_steps: int = SETTLE_MAX_STEPS, abort=None,
           damped_steps: int = SETTLE_DAMPED_STEPS) -> SettleStats:
    """Step (``step()``: one physics step) until the markers' mean (``markers()[0]``) over the last
    ``consecutive`` steps moved < ``tol_mm`` from the mean over the ``consecutive`` steps before (every
    marker); ``last_motion_mm`` is that drift. ``abort(n)``, if given, is asked after step ``n``; when it
    returns True the settle stops there (``converged`` False). Not settled after ``max_steps``, it goes on
    for at most ``damped_steps`` with the damped continuation (``SETTLE_DAMPED_PER_S`` on ``model``'s DOF
    damping, restored afterwards)."""
    t0 = time.perf_counter()
    w = max(1, int(consecutive))
    hist: list[np.ndarray] = []
    motion, n = float("inf"), 0

    def run(limit: int) -> bool:     # True: aborted
        nonlocal motion, n
        while n < limit:
            step()
            n += 1
            if abort is not None and abort(n):
                return True
            hist.append(markers()[0])
            if len(hist) > 2 * w:
                hist.pop(0)
            if len(hist) == 2 * w:
                h = np.array(hist)
                motion = float(np.max(np.linalg.norm(h[w:].mean(axis=0) - h[:w].mean(axis=0), axis=1)))
                if motion < tol_mm:
                    return False
        return False

    if run(max_steps):
        return SettleStats(n, False, motion, time.perf_counter() - t0)
    damped = 0
    if motion >= tol_mm and abort is None and damped_steps > 0:
        # the damped continuation (see SETTLE_DAMPED_PER_S); the direct solve (abort given) has its own damping
        saved = model.dof_damping.copy()
        mass = model.body_mass[model.dof_bodyid]
        model.dof_damping[:] = saved + SETTLE_DAMPED_PER_S * mass
        try:
            start = n
            run(n + damped_steps)
            damped = n - start
        finally:
            model.dof_damping[:] = saved
    return SettleStats(n, motion < tol_mm, motion, time.perf_counter() - t0, damped_steps=damped)


def solve_at(sim: "SkinSim", x_mm: float, y_mm: float, depth_mm: float, yaw_deg: float, *,
             accept_mm: float = DIRECT_ACCEPT_MM, abort_mm: float = DIRECT_ABORT_MM) -> SettleStats | None:
    """Quasi-static equilibrium at a pose without following the path to it; None if not valid.

    With frictionless contact and a hyperelastic body the equilibrium depends only on the indenter's
    pose, not on how it got there, so the indenter is placed at the pose directly and the mesh warm-
    started geometrically: every free outer vertex inside the indenter is moved vertically onto its
    surface and the vertices below it by the same amount scaled linearly to zero at the window (a
    column compressed uniformly). The sim then settles (:func:`settle`, same criterion) with a mass-
    proportional DOF damping ``DIRECT_DAMPING_PER_S`` that removes the slow gel modes (zero again
    afterwards). Without the followed path's lag limit, a vertex can be pushed through a steep flank
    or around a sharp tip; so the result is accepted only if the sim converged and no free outer
    vertex ends more than ``accept_mm`` inside the indenter (checked every ``DIRECT_CHECK_EVERY``
    steps while settling, abandoned beyond ``abort_mm``), nor, with face contact, any point of the outer
    faces at the end (the frame's own check, :meth:`~twin.physics.SkinSim.validity`). Otherwise the state
    before the call is restored exactly and None returned: the caller follows the path instead
    (:meth:`~twin.physics.SkinSim.move_to`).
    With friction the equilibrium depends on the path: always None.

    Measured (hexagon127, 5 mm press): Gaussian σ² = 10 equilibrium within 0.004 mm of the followed
    path's markers (σ² = 50: 0.0035 mm), 66 + 0 steps instead of 273; sines and the σ² = 5/3 tip
    are rejected (vertices 1.9-4.4 mm inside without the lag limit).
    """
    mj = sim._mj
    if sim.friction > 0:
        return None
    saved, steps0 = sim.checkpoint(), sim.steps_taken
    warn0 = saved.warnings
    sim.set_pose(x_mm, y_mm, depth_mm, yaw_deg)
    X = sim._nodes_from_qpos()
    top = sim._col_top
    zi = sim.indenter_z_at(X[top, :2])
    dz = np.where(np.isfinite(zi), np.minimum(0.0, zi - X[top, 2]), 0.0)
    zb = X[sim._col_bottom, 2]
    frac = np.clip((X[:, 2] - zb) / np.maximum(X[top, 2] - zb, 1e-9), 0.0, 1.0)
    disp = np.zeros_like(X)
    disp[:, 2] = dz * frac
    q = sim.data.qpos
    idx = sim._qadr.ravel()
    q[idx] += units.mm_to_m(disp[sim._free] * _FLIP).ravel()
    mass = sim.model.body_mass[sim.model.dof_bodyid]
    sim.model.dof_damping[:] = DIRECT_DAMPING_PER_S * mass
    if sim._vol is not None:
        # the vertical warm start compresses columns: at once the nodal forces of that volume change would
        # throw surface vertices into the indenter (σ² = 10, 5 mm: 0.42 mm in after 4 steps)
        sim._vol_ramp = volumetric.WARM_RAMP_STEPS
    deepest = [0.0]

    def abort(n: int) -> bool:
        if n % DIRECT_CHECK_EVERY:
            return False
        deepest[0] = sim.outer_penetration_mm()
        return deepest[0] > abort_mm or sim.unstable(warn0)

    try:
        sim._update_volumetric()
        mj.mj_forward(sim.model, sim.data)
        stats = sim.settle(abort=abort)
    finally:
        sim.model.dof_damping[:] = sim._base_damping()
        sim._vol_ramp = 0
    if stats.converged:
        deepest[0] = sim.outer_penetration_mm()
        if sim.face_contact:
            # the faces collide too, so the whole outer surface counts, as the frame's own check sees it: a crest
            # can pass through a face between vertices that all stay outside (a sine at π/5, 5 mm, roller rim:
            # vertices within the bound, faces 2.5 mm inside, where the followed path ends 0.03 mm inside)
            deepest[0] = max(deepest[0], sim.validity(settled=True).penetration_max_mm)
    unstable = sim.unstable(warn0)
    if stats.converged and deepest[0] <= accept_mm and not unstable:
        sim.direct_solves += 1
        return replace(stats, direct=True)
    sim.direct_rejections += 1
    sim.direct_wasted_steps += sim.steps_taken - steps0
    sim.restore(saved)
    return None
