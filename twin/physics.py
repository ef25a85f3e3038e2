"""MuJoCo model of the skin module: gel + skin (two volumetric flexes), pins, and a mocap indenter.

:class:`SkinSim` ties the parts together and holds the state of one simulation: the pose, stepping, the
path the robot follows, checkpoints, MuJoCo's warnings and the read-out of the truth. The parts:

* :mod:`twin.mesh` — the tetrahedral gel/skin mesh (``MeshSpec``, ``build_mesh``) and the pins embedded in it;
* :mod:`twin.model` — the MjSpec model built from it (flexes, contact, mass scaling, nodal volumetric
  stiffness) and the per-process cache of compiled models;
* :mod:`twin.stick` — friction: Coulomb's law as stick constraints with a return map;
* :mod:`twin.solve` — the settle criterion and the direct quasi-static solve at a pose;
* :mod:`twin.readout` — what the current state says (vertices, markers, contact, physics validity, the
  truth), a base of :class:`SkinSim` that reads the state and never steps or changes it.

Reaching a pose: :meth:`SkinSim.move_to` follows the robot's path in small increments (holding while a
contact lags); :meth:`SkinSim.solve_at` places the indenter at the pose directly, warm-starts the mesh
geometrically and settles with mass-proportional damping (:mod:`twin.solve`). With frictionless contact
both reach the same state; :func:`twin.robot.execute` tries the direct solve first at every captured pose.

Poses are ``(x_mm, y_mm, depth_mm, yaw_deg)`` in the sensor frame. MuJoCo's world frame is the sensor
frame rotated 180° about x (the sensor looks down at the indenter on the desk): world = (x, -y, -z)_sensor.
Lengths cross to metres only via :mod:`twin.units`.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np

from pipeline.design import SensorDesign
from twin import model as _model, solve, stick, units, volumetric
from twin.indenters import Indenter
from twin.mesh import AXIS_CONTACT_MESH, NAMED_MESHES, SINE_CONTACT_MESH, MeshSpec, PhysicsError, build_mesh, embed_pins
from twin.model import _BIT_FACES, _BIT_SPHERES, _FLIP
from twin.solve import DIRECT_ABORT_MM, DIRECT_ACCEPT_MM, SETTLE_CONSECUTIVE, SETTLE_DAMPED_STEPS, \
    SETTLE_MAX_STEPS, SETTLE_TOL_MM, SettleStats
from twin.readout import SkinReadout
from twin.stick import resolve_friction

# re-exported from twin.mesh and twin.solve: what a caller of SkinSim passes it, gets back or catches
__all__ = ["MeshSpec", "SkinSim", "SettleStats", "PhysicsError", "SETTLE_TOL_MM", "max_depth_mm", "DIRECT_ACCEPT_MM",
           "AXIS_CONTACT_MESH", "SINE_CONTACT_MESH", "NAMED_MESHES", "resolve_friction"]

FRICTION_SETTLE_MAX_STEPS = 1200  # with friction a dragged contact relaxes by its anchors sliding at most
                                  # stick.STICK_MAX_SLIDE_MM a step: the letter 'o' after its rapid 2 mm + 2 mm
                                  # move settled in 897 steps (damped continuation off; 400 + 400 damped did not)
CONTACT_POINT_SETTLE_SCALE = 2.0  # with friction the contact points settle to half the markers' tolerance: a sliding
                                  # contact's last relaxation is its anchors' slow drift (μ = 0.3 slide: Q/P 0.362 at the
                                  # markers' tolerance, 0.345 at half, 0.330 at a quarter, which doubles a press's steps)
FRICTION_SETTLE_DAMPING_PER_S = 30.0  # with friction a settle runs with mass-proportional DOF damping c = α m (α /s):
                                  # the stuck skin's ringing dies in fewer steps (each ~300 CG iterations at the stick
                                  # tolerance), and damping does not move where the forces balance (σ² = 10, 5 mm,
                                  # μ = 1: 135 -> 47 steps, markers within 0.012 mm of the undamped settle, as close
                                  # as CG at 1e-9 instead of 1e-10 comes; α = 60 / 100: 0.019 / 0.026 mm off, the
                                  # damped skin creeping past the settle criterion short of equilibrium)
MAX_INCREMENT_MM = 0.1       # largest indenter move per physics step while clear of the skin
CONTACT_INCREMENT_MM = 0.06  # ... and while touching it. A contact vertex lags the (zero-velocity) mocap by about
                             # 4 ζ² increments (the steady ramp error of the contact's reference dynamics: time
                             # constant 2 dt, the smallest MuJoCo allows, damping ratio ζ), more where the skin is
                             # stiff (near the clamped rim). A lag beyond the 0.2 mm height-field cell lets the stable
                             # Neo-Hookean skin push vertices sideways through prism walls (ζ = 1, 0.05 mm, σ² = 10:
                             # apex 1.1 mm inside; ζ = 0.7, 0.04 mm, a sine ω = π/15 pressed across the rim: 2.3 mm).
                             # ζ = 0.5 (dead-beat in theory) chattered and never settled. With friction 0.1 mm
                             # (5 mm, μ = 1, σ² = 10) cut the default mesh's press 4.7 -> 4.25 s (93 -> 61 approach
                             # steps, markers 0.010 mm off) and the axis contact mesh's 30 -> 26 s (0.046 mm inside,
                             # 0.014 mm off); not taken: the flanks the 0.06 mm increment was validated on not rerun
PENETRATION_LIMIT_MM = 0.08 # so the robot waits while any vertex lags deeper than this (the lag ζ = 1 at 0.02 mm had,
                             # where it was validated): σ² = 10, 5 mm presses in 170 steps instead of 267, then settles
                             # (~100), gap -0.006..0.092 mm (limit 0.10-0.12 or 0.08 mm increments: no fewer steps)
MAX_HOLD_STEPS = 30
HOLD_PROGRESS_MM = 1e-3
DEPTH_MARGIN_MM = 1.0        # markers must stay this far above the window: depth <= G - H - margin
_UNSTABLE_WARNINGS = ("mjWARN_INERTIA", "mjWARN_BADQACC", "mjWARN_CONTACTFULL", "mjWARN_CNSTRFULL", "mjWARN_BADQPOS",
                      "mjWARN_BADQVEL")


@dataclass(frozen=True)
class Checkpoint:
    """What :meth:`SkinSim.checkpoint` saves: integration state, pose, MuJoCo warning counts."""

    state: np.ndarray
    pose: tuple
    warnings: list
    stick: tuple = (None, None, None, None)   # friction: the ties' data, mean forces, their variances, anchors


def max_depth_mm(design: SensorDesign) -> float:
    """Deepest press the twin accepts: gel thickness − pin height − ``DEPTH_MARGIN_MM``."""
    return design.optics.gel_thickness_mm - design.pins.height_mm - DEPTH_MARGIN_MM


class SkinSim(SkinReadout):
    """The skin module in MuJoCo with one indenter on a mocap "robot".

    Parameters
    ----------
    design : SensorDesign
    indenter : Indenter from :func:`twin.indenters.make_indenter`
    mesh : MeshSpec resolution
    timestep_s : physics step (s); the equilibrium does not depend on it
    friction : Coulomb friction skin/indenter; None (default): the design's ``[twin] friction``
        (:data:`pipeline.design.TWIN_KEYS`: 1.0); 0 = frictionless contact (condim 1)

    Notes
    -----
    Poses are given as ``(x_mm, y_mm, depth_mm, yaw_deg)``: the indenter's own origin at sensor
    ``(x, y)``, its top at sensor ``z = -depth`` (depth < 0: clear of the skin).
    """

    def __init__(self, design: SensorDesign, indenter: Indenter, *, mesh: MeshSpec = MeshSpec(),
                 timestep_s: float = 0.01, friction: float | None = None) -> None:
        import mujoco

        self._mj = mujoco
        self.design, self.indenter, self.mesh_spec = design, indenter, mesh
        self.timestep_s = float(timestep_s)
        t0 = time.perf_counter()
        self.mesh = m = build_mesh(design, mesh)
        self.friction = resolve_friction(design, friction, indenter)
        # the compiled model (twin.model), and the index arrays beside it under the names of twin.model._DERIVED
        self.model, derived, self.model_from_cache = _model.load(design, indenter, m, mesh, self.timestep_s,
                                                                 self.friction)
        self.data = mujoco.MjData(self.model)
        for a, v in derived.items():
            setattr(self, a, v)
        self._pins = embed_pins(design, m, mesh)
        self.pose = (0.0, 0.0, -1.0, 0.0)
        self.set_pose(*self.pose)
        self.model.dof_damping[:] = self._base_damping()
        self._vol_ramp = 0      # steps left of the nodal forces' ramp after a direct solve's warm start
        self._update_volumetric()
        self._mj.mj_forward(self.model, self.data)
        self.build_seconds = time.perf_counter() - t0
        self.steps_taken = 0
        self.holds = 0          # physics steps the robot held still in move_to (penetration limit)
        self.direct_solves = 0          # poses reached by solve_at ...
        self.direct_rejections = 0      # ... and attempts it rejected (the path was then followed)
        self.direct_wasted_steps = 0    # physics steps spent on rejected attempts
        self.face_contact_fallback = None  # why face contact was switched off for this sim (None: it was not)
        self._stick_F = np.zeros((len(self._stick_eq), 3))
        self._stick_var = np.zeros(len(self._stick_eq))
        self._stick_anchor = np.zeros((len(self._stick_eq), 3))
        if len(self._stick_eq):
            self.data.eq_active[self._stick_eq.ravel()] = 0
        if self.mesh_spec.face_contact:
            import mujoco as _m
            sph = np.nonzero((self.model.geom_type == _m.mjtGeom.mjGEOM_SPHERE)
                             & (self.model.geom_contype == _BIT_SPHERES))[0]
            self._face_geoms = sph
            self._face_flex = np.nonzero(self.model.flex_contype == _BIT_FACES)[0]
        else:
            self._face_geoms = self._face_flex = np.zeros(0, int)

    # ----- nodal volumetric stiffness (twin.volumetric) ------------------------------------------
    def _base_damping(self) -> np.ndarray:
        """DOF damping outside direct solves: zero, or with nodal volumetric forces mass-proportional at
        ``volumetric.DAMPING_PER_S`` (the unlocked gel's slow modes otherwise ring for hundreds of steps)."""
        mass = self.model.body_mass[self.model.dof_bodyid]
        return volumetric.DAMPING_PER_S * mass if self.mesh_spec.volumetric == "nodal" else np.zeros_like(mass)

    def _update_volumetric(self, advance: bool = False) -> None:
        """Apply the nodal volumetric forces −K V̄ (J̄ − 1) ∂J̄/∂x of the current configuration to the free
        vertices' slide DOFs (``qfrc_applied``; explicit: the vertex masses are scaled for it, see
        ``volumetric.MASS_FACTOR``). After a direct solve's warm start the forces ramp up over
        ``volumetric.WARM_RAMP_STEPS`` steps (``advance``: one more step of it)."""
        v = self._vol
        if v is None:
            return
        if advance and self._vol_ramp > 0:
            self._vol_ramp -= 1
        scale = 1.0 - self._vol_ramp / max(volumetric.WARM_RAMP_STEPS, 1)
        q = self.data.qpos[self._qadr.ravel()].reshape(-1, 3)
        X = units.mm_to_m(self.mesh.nodes_mm * _FLIP)
        X[self._free] += q
        nv = v["nv"]
        Jbar, C = nv.evaluate(X)
        pr = v["pairs"]
        f = -(scale * nv.stiffness * (Jbar - 1.0))[nv.pair_term[pr], None] * C[pr]
        qf = self.data.qfrc_applied
        qf[self._qadr.ravel()] = 0.0
        np.add.at(qf, v["pair_dof"].ravel(), f.ravel())

    def volumetric_jbar(self) -> np.ndarray | None:
        """Current averaged volume ratios J̄ of the nodal terms (None without ``volumetric="nodal"``)."""
        if self._vol is None:
            return None
        X = units.mm_to_m(self._nodes_from_qpos() * _FLIP)
        return self._vol["nv"].evaluate(X)[0]

    # ----- state --------------------------------------------------------------------------
    def set_pose(self, x_mm: float, y_mm: float, depth_mm: float, yaw_deg: float, *, teleport: bool = True) -> None:
        """Place the indenter at a pose; no physics step. With friction the indenter is a driven body:
        ``teleport`` moves it there at once (no velocity), otherwise the next :meth:`step` moves it there
        with the velocity of that increment, which is what drags the skin through friction."""
        pos_w = np.array([x_mm, -y_mm, depth_mm - self.indenter.top_mm])
        if self._ind_qadr is not None:
            self._cmd_q = np.concatenate([units.mm_to_m(pos_w), [-math.radians(yaw_deg)]])
            if teleport:
                self.data.qpos[self._ind_qadr] = self._cmd_q
                self.data.qvel[self._ind_dadr] = 0.0
        else:
            half = -math.radians(yaw_deg) / 2.0
            self.data.mocap_pos[0] = units.mm_to_m(pos_w)
            self.data.mocap_quat[0] = [math.cos(half), 0.0, 0.0, math.sin(half)]
        self.pose = (float(x_mm), float(y_mm), float(depth_mm), float(yaw_deg))

    def step(self, n: int = 1) -> float:
        """Advance ``n`` physics steps; returns the largest vertex motion of the last step (mm)."""
        motion = 0.0
        idx = self._qadr.ravel()
        driven = self._ind_qadr is not None
        for _ in range(n):
            q = self.data.qpos[idx].copy()
            if driven:   # prescribed motion: the commanded increment as this step's velocity
                self.data.qvel[self._ind_dadr] = (self._cmd_q - self.data.qpos[self._ind_qadr]) / self.timestep_s
            self._update_volumetric(advance=True)
            self._mj.mj_step(self.model, self.data)
            if driven:
                self.data.qpos[self._ind_qadr] = self._cmd_q
                self.data.qvel[self._ind_dadr] = 0.0
                if len(self._stick_eq):
                    stick.update(self.model, self.data, friction=self.friction, eq=self._stick_eq, qadr=self._qadr,
                                 stick_free=self._stick_free, rest_free_m=self._rest_free_m, stick_k=self._stick_k,
                                 ind_qadr=self._ind_qadr, anchor=self._stick_anchor, mean_F=self._stick_F,
                                 var=self._stick_var, surface_z=self.indenter_z_at)
            motion = float(units.m_to_mm(np.max(np.abs(self.data.qpos[idx] - q)))) if len(q) else 0.0
            self.steps_taken += 1
        return motion

    def stuck_vertices(self) -> np.ndarray:
        """Mesh indices of the outer vertices currently stuck to the indenter (friction > 0)."""
        return self._stick_nodes[self.data.eq_active[self._stick_eq[:, 0]] != 0]

    def penetration_mm(self) -> float:
        """Deepest current contact penetration (mm, >= 0): how far a skin vertex lags inside the indenter."""
        n = self.data.ncon
        return float(units.m_to_mm(max(0.0, -float(np.min(self.data.contact.dist[:n]))))) if n else 0.0

    def move_to(self, x_mm: float, y_mm: float, depth_mm: float, yaw_deg: float, *,
                max_increment_mm: float = MAX_INCREMENT_MM, max_increment_deg: float = 1.0,
                contact_increment_mm: float = CONTACT_INCREMENT_MM,
                penetration_limit_mm: float = PENETRATION_LIMIT_MM, on_step=None) -> int:
        """Move the indenter in straight-line increments, one physics step each; returns steps.

        Increments are ``max_increment_mm`` while nothing touches and ``contact_increment_mm``
        (if smaller) while the indenter is in contact with the skin. While a skin vertex lags more
        than ``penetration_limit_mm`` inside the indenter the robot holds still (physics steps on) as
        long as the lag shrinks by ``HOLD_PROGRESS_MM`` a step, at most ``MAX_HOLD_STEPS`` in a row: the
        lag stays bounded whatever the shape and stiffness, and a vertex caught for good (a flank
        steeper than the mesh resolves) does not stall the motion. ``on_step(s)``: after each step (s: part made)."""
        a, b = np.array(self.pose), np.array([x_mm, y_mm, depth_mm, yaw_deg], float)
        dist, ang = float(np.linalg.norm(b[:3] - a[:3])), abs(b[3] - a[3])
        s, n, held, last = 0.0, 0, 0, float("inf")
        while s < 1.0 - 1e-12:
            pen = self.penetration_mm() if self.data.ncon else 0.0
            if pen > penetration_limit_mm and held < MAX_HOLD_STEPS and pen < last - HOLD_PROGRESS_MM:
                held += 1
                self.holds += 1
                last = pen
            else:
                held, last = 0, float("inf")
                inc = min(max_increment_mm, contact_increment_mm) if self.data.ncon else max_increment_mm
                ds = min(inc / dist if dist > 0 else 1.0, max_increment_deg / ang if ang > 0 else 1.0)
                s = min(1.0, s + ds)
                self.set_pose(*(a + (b - a) * s), teleport=False)
            self.step()
            n += 1
            if on_step is not None:
                on_step(s)
        return n

    def settle(self, *, tol_mm: float = SETTLE_TOL_MM, consecutive: int = SETTLE_CONSECUTIVE,
               max_steps: int | None = None, abort=None,
               damped_steps: int = SETTLE_DAMPED_STEPS) -> SettleStats:
        """Step until the markers are quasi-static (:func:`twin.solve.settle`; at most ``max_steps`` before the
        damped continuation, default ``SETTLE_MAX_STEPS``, with friction ``FRICTION_SETTLE_MAX_STEPS``). With
        friction the stick anchors count as markers: a contact still sliding is not at equilibrium even when the
        markers barely move (a 0.3 mm slide at mu = 0.3 looked settled with the anchors still sliding, Q/P 0.385,
        relaxing to 0.31). They count as contact points (:meth:`_contact_points_mm`): a vertex's anchor while it
        sticks, its own place while free. Counting every anchor instead, a vertex sticking at the contact's edge
        moved its anchor from where it last stuck (or from zero) to where it touched, and each such event held
        the settle for two windows more (5 mm, μ = 1: σ² = 10 settle 47 -> 37 steps, 5.2 -> 4.7 s, markers within
        0.005 mm; on the axis contact mesh σ² = 5/3 127 -> 60 steps, 20 -> 12.5 s, 0.010 mm, while σ² = 10 stays at
        128 steps, 10-30 anchors of small normal load at the contact's edge sliding 0.0005-0.001 mm a step long
        after the markers have settled at step 51). Those anchors are not left out: a looser tolerance on the
        contact points (2x) or their mean motion alone also stopped the μ = 0.3 slide early (Q/P 0.38 for 0.33,
        outside 0.25-0.36), its last relaxation being the same slow sliding of part of the contact. With
        friction the settle is damped (``FRICTION_SETTLE_DAMPING_PER_S``; 10 /s: σ² = 10 on the axis mesh 84
        settle steps, but 0.053 mm inside the indenter, over the 0.05 mm validity limit)."""
        if max_steps is None:
            max_steps = FRICTION_SETTLE_MAX_STEPS if len(self._stick_eq) else SETTLE_MAX_STEPS
        o = self.model.opt
        solver = o.tolerance, o.iterations
        o.tolerance, o.iterations = _model.settle_solver_options(*solver)
        try:
            return self._settle(tol_mm, consecutive, max_steps, abort, damped_steps)
        finally:
            o.tolerance, o.iterations = solver

    def _settle(self, tol_mm, consecutive, max_steps, abort, damped_steps) -> SettleStats:
        """:meth:`settle` at the settle's solver options."""

        def with_anchors():   # the contact points settle to 1/CONTACT_POINT_SETTLE_SCALE of the markers' tolerance
            return (np.vstack([self.markers()[0], CONTACT_POINT_SETTLE_SCALE * self._contact_points_mm()]),)
        if not len(self._stick_eq):
            return solve.settle(self.step, self.markers, self.model, tol_mm=tol_mm, consecutive=consecutive,
                                max_steps=max_steps, abort=abort, damped_steps=damped_steps)
        saved = self.model.dof_damping.copy()
        mass = self.model.body_mass[self.model.dof_bodyid]
        self.model.dof_damping[:] = saved + FRICTION_SETTLE_DAMPING_PER_S * mass   # FRICTION_SETTLE_DAMPING_PER_S
        try:
            return solve.settle(self.step, with_anchors, self.model, tol_mm=tol_mm, consecutive=consecutive,
                                max_steps=max_steps, abort=abort, damped_steps=damped_steps)
        finally:
            self.model.dof_damping[:] = saved

    def _contact_points_mm(self) -> np.ndarray:
        """Where each outer vertex that can stick meets the indenter, in the indenter's frame (K, 3) mm, z 0:
        its anchor's x, y while it sticks, its own x, y while free. A vertex sticking or coming free moves
        it by no more than the tie's give, so only sliding anchors (and moving skin) move these points."""
        X = self._rest_free_m[self._stick_free] + self.data.qpos[self._qadr[self._stick_free]]
        p_ind, yaw = self.data.qpos[self._ind_qadr[:3]], float(self.data.qpos[self._ind_qadr[3]])
        free = stick.to_indenter_frame(X, p_ind, yaw)
        stuck = self.data.eq_active[self._stick_eq[:, 0]] != 0
        pts = np.where(stuck[:, None], self._stick_anchor, free)
        pts[:, 2] = 0.0
        return units.m_to_mm(pts)

    # ----- direct quasi-static solve ---------------------------------------------------------
    def _nodes_from_qpos(self) -> np.ndarray:
        """All vertex positions (V, 3) mm, sensor frame, from ``qpos`` (valid between ``mj_step`` and
        the next kinematics pass, unlike ``flexvert_xpos`` which lags one step)."""
        X = self.mesh.nodes_mm.copy()
        q = self.data.qpos[self._qadr.ravel()].reshape(-1, 3)
        X[self._free] = units.m_to_mm(self._rest_free_m + q) * _FLIP
        return X

    def outer_penetration_mm(self) -> float:
        """Deepest free outer-surface vertex inside the indenter, measured vertically (mm, >= 0).

        Unlike :meth:`penetration_mm` (MuJoCo's contact distances) this also sees a vertex that has
        slipped through the height field's prism walls and no longer registers a contact."""
        X = self._nodes_from_qpos()[self._is_free_top]
        zi = self.indenter_z_at(X[:, :2])
        pen = X[:, 2] - zi
        pen = pen[np.isfinite(pen)]
        return float(max(0.0, pen.max())) if len(pen) else 0.0

    def solve_at(self, x_mm: float, y_mm: float, depth_mm: float, yaw_deg: float, *,
                 accept_mm: float = DIRECT_ACCEPT_MM, abort_mm: float = DIRECT_ABORT_MM) -> SettleStats | None:
        """Quasi-static equilibrium at a pose without following the path to it; None if not valid (the
        state is then as before the call). See :func:`twin.solve.solve_at`."""
        return solve.solve_at(self, x_mm, y_mm, depth_mm, yaw_deg, accept_mm=accept_mm, abort_mm=abort_mm)

    def checkpoint(self) -> "Checkpoint":
        """The sim's integration state, indenter pose and MuJoCo warning counts, for :meth:`restore`."""
        spec = self._mj.mjtState.mjSTATE_INTEGRATION
        state = np.empty(self._mj.mj_stateSize(self.model, spec))
        self._mj.mj_getState(self.model, self.data, state, spec)
        return Checkpoint(state, self.pose, [int(w.number) for w in self.data.warning],
                          (self.model.eq_data[self._stick_eq].copy(), self._stick_F.copy(), self._stick_var.copy(),
                           self._stick_anchor.copy()))

    def restore(self, cp: "Checkpoint") -> None:
        """Undo everything since :meth:`checkpoint` bit for bit, the warnings raised meanwhile included
        (an attempt that is thrown away must not mark the state that is kept)."""
        self._mj.mj_setState(self.model, self.data, cp.state, self._mj.mjtState.mjSTATE_INTEGRATION)
        for w, n in zip(self.data.warning, cp.warnings):
            w.number = n
        self.model.eq_data[self._stick_eq] = cp.stick[0]
        self._stick_F, self._stick_var = cp.stick[1].copy(), cp.stick[2].copy()
        self._stick_anchor = cp.stick[3].copy()
        self.set_pose(*cp.pose)
        self._update_volumetric()
        self._mj.mj_forward(self.model, self.data)

    @property
    def face_contact(self) -> bool:
        """Whether the outer faces currently collide with the indenter's surface spheres."""
        return bool(len(self._face_flex)) and bool(self.model.flex_contype[self._face_flex[0]])

    def disable_face_contact(self, reason: str) -> None:
        """Vertex contacts only from now on; ``reason`` is recorded. The sim switches to its own copy of
        the model first, so the per-process cache keeps serving face contact to later sims."""
        self.model = copy.copy(self.model)
        self.model.geom_contype[self._face_geoms] = 0
        self.model.geom_conaffinity[self._face_geoms] = 0
        self.model.flex_contype[self._face_flex] = 0
        self.model.flex_conaffinity[self._face_flex] = 0
        self.face_contact_fallback = reason

    def unstable(self, since: list[int] | None = None) -> bool:
        """MuJoCo reported a failed solve (singular effective inertia, NaN accelerations, contact
        buffer full): the state can no longer be trusted. ``since``: warning counts (``data.warning``
        order) before the stretch in question; only warnings raised after them count."""
        names = [self._mj.mjtWarning(i).name for i in range(len(self.data.warning))]
        base = since if since is not None else [0] * len(names)
        return any(int(w.number) > b for n, w, b in zip(names, self.data.warning, base) if n in _UNSTABLE_WARNINGS)

    def clear_warnings(self) -> None:
        for w in self.data.warning:
            w.number = 0

    def warnings(self) -> dict[str, int]:
        """MuJoCo warning counters that are non-zero (name → count)."""
        names = [self._mj.mjtWarning(i).name for i in range(len(self.data.warning))]
        return {n: int(w.number) for n, w in zip(names, self.data.warning) if w.number}
