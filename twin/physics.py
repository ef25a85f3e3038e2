"""MuJoCo model of the skin module: gel + skin (two volumetric flexes), pins, and a mocap indenter.

Longer than the project's ~400 lines: one class, :class:`SkinSim`, whose build, stepping, settle, direct
solve, friction (stick) and truth parts share its private model state. Its seams for a split are the mesh
(``build_mesh``, ``MeshSpec``), the model build, the friction return map, and the direct solve.

Model (built in code with :class:`mujoco.MjSpec` from a :class:`~pipeline.design.SensorDesign`)
------------------------------------------------------------------------------------------------
* One tetrahedral mesh of the disc of radius ``design.gel.radius_mm`` from the outer skin surface
  (sensor z = 0) down to the acrylic window (z = -(T + G)). Vertices lie on a tensor grid: x-y
  spacing ``MeshSpec.fine_mm`` inside ``|x|, |y| <= fine_half_mm`` (where contact happens), growing
  geometrically to the rim; z levels 0, -T (skin) and ``gel_levels_mm`` below the skin, then the
  window. Each hexahedral cell is split into 6 Kuhn tetrahedra (conforming; ``MeshSpec.mirrored_split``
  mirrors the split in alternate cells for a mesh symmetric about the axis). Cells whose centre
  lies outside the radius are dropped, so the clamped rim is a staircase approximating the circle.
* Two 3-D flexes share the vertices: ``skin`` (the top layer, thickness T, the skin's E and ν) and
  ``gel`` (everything below, the gel's E and ν), MuJoCo's stable Neo-Hookean model
  (``elastic3d = 1``), the discrete integrator with the CG solver. St Venant–Kirchhoff (MuJoCo's
  default) softens under compression and lets elements collapse: a Gaussian (σ² = 10) pressed 5 mm
  inverted 302 gel and 6 skin tetrahedra (min det F = −1.15), squashed the skin to 0.4 T and left
  the centre marker 1.08 mm below the outer skin instead of T + H = 2.5 mm; with stable
  Neo-Hookean min det F = 0.58 (gel) / 0.86 (skin) and the gel flows sideways. Vertices on the bottom (bonded to the acrylic) and on the lateral
  boundary (clamped by the rigid mount) are fixed to the world body.
* Domed designs: the mesh is shifted vertically by ``design.dome_z_mm`` (fully in the skin layer,
  tapering linearly to zero at the window), so the skin is the dome of constant vertical
  thickness T; rest markers are exact, the physics (materials, contact, pins) is unchanged.
* Contact, two layers. (1) Every free vertex of the outer surface carries a small sphere (radius
  ``CONTACT_RADIUS_MM``) whose outermost point is the vertex; the indenter is a height field of its
  true shape (:mod:`twin.indenters`) on a mocap body. (2) Vertices alone let a convex tip or crest
  poke through the flat faces between them (chord sag κL²/8: 0.29 mm under the σ² = 10 cap, ~2 mm
  under the σ² = 5/3 tip) and let vertices slip sideways through the height field's prism walls on
  steep flanks; so the outer faces also form a 2-D flex without stiffness that collides with spheres
  placed on the indenter's convex and steep parts (:mod:`twin.contact`; ``MeshSpec.face_contact``,
  off by default: on the 1.5 mm mesh it trades face penetration for vertices held off the cap, see
  ``MeshSpec``).
  The volumetric flexes themselves do not collide (element contact of the whole skin layer produced
  4,600-6,600 contacts on a σ² = 10 press and the discrete integrator's M + K solve failed:
  mjWARN_INERTIA, then NaN accelerations, at vertex mass scales 0.05-1).
* Mass scaling (:mod:`twin.materials`): ``m_i = MASS_SCALE · dt² · K_ii``; gravity off.
* Volumetric locking: linear tetrahedra lock as ν → 0.5 (uniform ν = 0.49 gel: 2.3× the layer solution's
  force). ``MeshSpec(volumetric="nodal")`` gives the flexes each material's shear modulus at ν = 0.15 and
  carries the rest of its bulk modulus on averaged nodal volume ratios (:mod:`twin.volumetric`; Bonet &
  Burton 1998): explicit forces on the vertices' slide DOFs, so with it the vertex masses are
  ``volumetric.MASS_FACTOR`` × heavier, the path is damped and the constraint solve converged tighter.
* Reaching a pose: :meth:`SkinSim.move_to` follows the robot's path in small increments (holding
  while a contact lags); :meth:`SkinSim.solve_at` places the indenter at the pose directly, warm-
  starts the mesh geometrically and settles with mass-proportional damping. With frictionless
  contact the equilibrium depends on the pose only, so both reach the same state (σ² = 10, 5 mm:
  markers within 0.005 mm, 66 instead of 273 steps); the direct result is kept only if no outer
  vertex ends inside the indenter, else the state is restored and the path followed.
  :func:`twin.robot.execute` tries the direct solve first at every captured pose.
* Compiled models are cached per process (design, mesh, indenter, timestep, friction): a second sim
  of the same set-up copies the model instead of compiling it (~0.1 s instead of 0.8-1.3 s).
* Pins: each marker's pin base is the skin-underside point at the rest marker's x-y, embedded with
  barycentric weights in the skin tetrahedron that contains it. The pin is stiff (E_pin ≫ E_gel)
  and rotates with the skin it grows from: ``axis = R · (0, 0, -1)`` with ``R`` the polar rotation
  of the volume-averaged deformation gradient of the skin elements within one fine cell of the
  base; ``marker = base + H · axis``. At rest this is
  exactly ``design.rest_markers_mm()``.

MuJoCo's world frame is the sensor frame rotated 180° about x (the sensor looks down at the
indenter on the desk): world = (x, -y, -z)_sensor. Lengths cross to metres only via :mod:`twin.units`.
"""

from __future__ import annotations

import copy
import math
import time
from collections import OrderedDict
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from pipeline.design import SensorDesign
from pipeline.errors import UserError
from pipeline.types import HeightMap
from twin import contact, materials, units, volumetric
from twin.indenters import COLLISION_SPACING_MM, Indenter
from twin.truth import Truth
from twin.validity import FrameValidity, frame_validity, rim_overlap_mm, skin_penetration

__all__ = ["MeshSpec", "SkinSim", "SettleStats", "PhysicsError", "SETTLE_TOL_MM", "max_depth_mm", "DIRECT_ACCEPT_MM",
           "AXIS_CONTACT_MESH"]

CONTACT_RADIUS_MM = 0.25     # vertex contact sphere > the 0.2 mm height-field cell, so it always spans several
                             # prisms (0.12 mm let the stiff apex vertex slip through a prism wall: σ² = 10, 5 mm,
                             # 0.75 mm inside); slope error r(1/cos θ - 1) <= 0.10 mm up to 45°
ELASTIC3D_STABLE_NEO_HOOKEAN = 1   # MuJoCo flex ``elastic3d``: 0 = St Venant–Kirchhoff, 1 = stable Neo-Hookean
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
MAX_INCREMENT_MM = 0.1       # largest indenter move per physics step while clear of the skin
CONTACT_INCREMENT_MM = 0.06  # ... and while touching it. A contact vertex lags the (zero-velocity) mocap by about
                             # 4 ζ² increments (the steady ramp error of the contact's reference dynamics: time
                             # constant 2 dt, the smallest MuJoCo allows, damping ratio ζ), more where the skin is
                             # stiff (near the clamped rim). A lag beyond the 0.2 mm height-field cell lets the stable
                             # Neo-Hookean skin push vertices sideways through prism walls (ζ = 1, 0.05 mm, σ² = 10:
                             # apex 1.1 mm inside; ζ = 0.7, 0.04 mm, a sine ω = π/15 pressed across the rim: 2.3 mm).
                             # ζ = 0.5 (dead-beat in theory) chattered and never settled.
PENETRATION_LIMIT_MM = 0.08 # so the robot waits while any vertex lags deeper than this (the lag ζ = 1 at 0.02 mm had,
                             # where it was validated): σ² = 10, 5 mm presses in 170 steps instead of 267, then settles
                             # (~100), gap -0.006..0.092 mm (limit 0.10-0.12 or 0.08 mm increments: no fewer steps)
MAX_HOLD_STEPS = 30
HOLD_PROGRESS_MM = 1e-3
CONTACT_TIMECONST_STEPS = 2.0  # contact solref time constant in physics steps (the smallest MuJoCo allows)
CONTACT_DAMPRATIO = 0.7
DIRECT_DAMPING_PER_S = 10.0  # mass-proportional DOF damping c = α m while a direct solve settles (α = 10/s: the σ² = 10
                             # press settles in 66 steps instead of 156; 0: 156, 30: 82, 60: 116, 300: 256 followed)
DIRECT_ACCEPT_MM = 0.1       # a direct solve is kept only if no free outer vertex ends deeper inside the indenter
DIRECT_ABORT_MM = 0.3        # ... and is abandoned (state restored) as soon as one is this deep
DIRECT_CHECK_EVERY = 4       # steps between those checks while settling
PIN_ROTATION_RADIUS_FACTOR = 1.0  # pin rotation averaged over skin elements within 1 cell of its base
DEPTH_MARGIN_MM = 1.0        # markers must stay this far above the window: depth <= G - H - margin
_FLIP = np.array([1.0, -1.0, -1.0])  # sensor <-> MuJoCo world
MODEL_CACHE_SIZE = 4         # compiled models kept per process (a press sweep re-presses one design/indenter at
                             # several yaws; compiling costs ~0.5-0.9 s of a ~3 s press, a copy ~0.01 s)
_MODEL_CACHE: "OrderedDict[tuple, tuple]" = OrderedDict()
_DERIVED = ("_free", "_qadr", "_top_geom", "_hmin", "_rest_free_m", "_col_top", "_col_bottom", "_is_free_top",
            "_n_surface_spheres", "_ind_qadr", "_ind_dadr", "_stick_nodes", "_stick_free", "_stick_eq",
            "_stick_k", "_stick_geom", "_vol")
STICK_DAMPRATIO = 1.0       # the stick constraint's damping ratio (time constant as the contacts')
STICK_TIMECONST_STEPS = 4.0
STICK_FORCE_STEPS = 50      # steps of the running mean of a stuck vertex's constraint force
STICK_SIGNIFICANCE = 2.0     # ... and slides only by the excess beyond this many standard errors of that mean
STICK_RELAX = 0.1           # a sliding anchor moves this fraction of the excess force over the vertex stiffness ...
STICK_MAX_SLIDE_MM = 0.005   # ... and at most this far a step (the neighbours move too: a full step overshoots)
NORMAL_STEP_MM = 0.05        # central-difference step of the indenter's surface normal
DRIVEN_INDENTER_MASS_KG = 100.0   # with friction: the indenter's mass, >> the skin's scaled vertex masses, so contact
                                  # forces do not deflect it within a step (its position is re-imposed anyway)
# collision bits: vertex spheres (2/1) meet the height field (1/2); outer faces (4/8) meet surface spheres (8/4)
_BIT_FACES, _BIT_SPHERES = 4, 8
_UNSTABLE_WARNINGS = ("mjWARN_INERTIA", "mjWARN_BADQACC", "mjWARN_CONTACTFULL", "mjWARN_CNSTRFULL", "mjWARN_BADQPOS",
                      "mjWARN_BADQVEL")


class PhysicsError(UserError, ValueError):
    """A physics request the model cannot honour (e.g. a press deeper than the gel allows)."""


@dataclass(frozen=True)
class MeshSpec:
    """Resolution of the gel/skin mesh (mm). ``fine_mm`` sets the contact accuracy and the cost."""

    fine_mm: float = 1.5
    fine_half_mm: float = 9.0
    core_mm: float | None = None  # optional finer spacing about the axis (e.g. 0.75) for sharp tips: a σ² = 5/3
    core_half_mm: float = 3.0     # Gaussian tip (curvature radius 0.33 mm) pokes between 1.5 mm vertices (apex
                                  # skin 1.3 mm above the tip at 3 mm; 0.75 mm core: 0.12 mm) but the small
                                  # frictionless core vertices chatter (~0.03 mm/step on a σ² = 50 press), so off
    growth: float = 1.5
    skin_layers: int = 1
    gel_levels_mm: tuple[float, ...] = (1.5, 4.0)   # depths below the skin underside; the window adds G
    mirrored_split: bool = False  # True: Kuhn split mirrored in alternate cells, a mesh symmetric about the axis.
                                  # Sphere R 10 mm, 3 mm press: centre marker 0.15 -> 0.001 mm sideways, mirrored
                                  # markers 0.30 -> 0.005 mm apart; uniform-gel force / bonded-layer Hertz 2.27 ->
                                  # 1.47 (less locking). Not yet the default: on it the σ² = 10, 5 mm press crushes
                                  # the apex skin more (marker 2.11 mm below the skin, T + H = 2.5), direct and
                                  # followed solves differ by 0.035-0.06 mm, and a sine π/5 at 5 mm tunnels 4.8 mm
    face_contact: bool = False    # True: the outer faces also collide with spheres on the indenter's convex and
                                  # steep parts (twin.contact). It keeps faces out of tips (σ² = 10, 5 mm: 0.29 ->
                                  # 0.045 mm) but on this mesh the flat 1.5 mm faces then hold the vertices off a
                                  # curved cap (apex 0.24 mm beyond the tip; 1.0 mm mesh 0.13 mm in 6.2 s, 0.75 mm
                                  # 0.08 mm in 25 s), so it is not yet the default
    volumetric: str = "element"   # "nodal": each material's bulk stiffness beyond ν = 0.15 on averaged nodal volume
                                  # ratios (twin.volumetric), so a nearly incompressible gel does not lock: uniform
                                  # gel ν = 0.49, sphere R 10 mm at 1 / 3 mm, force / bonded-layer Hertz 2.25 / 2.39
                                  # -> 1.18 / 1.23 (ν = 0.3 element-wise on this mesh: 1.14 / 1.11). Not yet the
                                  # default: as the twin's default (bench twin --quick) the σ² = 10, 5 mm press takes
                                  # 2.6 s instead of 1.9 s, the sharp tip on AXIS_CONTACT_MESH 14 s instead of 7.7 s,
                                  # and that mesh's apex ends 0.05 mm beyond the σ² = 10 tip instead of on it


@dataclass(frozen=True)
class Checkpoint:
    """What :meth:`SkinSim.checkpoint` saves: integration state, pose, MuJoCo warning counts."""

    state: np.ndarray
    pose: tuple
    warnings: list
    stick: tuple = (None, None, None)   # friction: the stick constraints' anchors, mean forces, their variances


@dataclass(frozen=True)
class SettleStats:
    """Outcome of :meth:`SkinSim.settle`: steps taken, converged flag, last per-step motion (mm), seconds;
    ``direct``: the pose was solved directly (:meth:`SkinSim.solve_at`) rather than reached along the path."""

    steps: int
    converged: bool
    last_motion_mm: float
    seconds: float
    direct: bool = False
    damped_steps: int = 0   # steps of the damped continuation (SETTLE_DAMPED_PER_S), 0 if it settled without


# Mesh for indenters with one sharp feature on the sensor axis (Gaussians, spheres): 0.5 mm cells within 3 mm
# of the axis plus face contact. Measured at 5 mm (hexagon127 and its skin variants): every Gaussian from
# sigma2 = 5/3 to 50 within 0.012-0.026 mm of the indenter at face level, apex vertex within 0.01 mm of the
# tip for sigma2 >= 10 (0.18 mm beyond the 0.33 mm-radius sigma2 = 5/3 tip), 13-16 s a press instead of 1.3-1.4 s.
AXIS_CONTACT_MESH = MeshSpec(core_mm=0.5, core_half_mm=3.0, face_contact=True)


def max_depth_mm(design: SensorDesign) -> float:
    """Deepest press the twin accepts: gel thickness − pin height − ``DEPTH_MARGIN_MM``."""
    return design.optics.gel_thickness_mm - design.pins.height_mm - DEPTH_MARGIN_MM


def _axis(fine_mm: float, fine_half_mm: float, growth: float, radius_mm: float,
          core_mm: float | None = None, core_half_mm: float = 0.0) -> np.ndarray:
    pos = [0.0]
    if core_mm is not None and core_mm < fine_mm and core_half_mm > 0:
        pos = list(np.arange(0, int(math.floor(core_half_mm / core_mm + 1e-9)) + 1) * core_mm)
    while pos[-1] + fine_mm <= fine_half_mm + 1e-9:
        pos.append(pos[-1] + fine_mm)
    step = fine_mm
    while pos[-1] < radius_mm - 1e-9:
        step *= growth
        pos.append(min(pos[-1] + step, radius_mm + fine_mm) if pos[-1] + step > radius_mm else pos[-1] + step)
    pos = np.array(pos)
    return np.concatenate([-pos[:0:-1], pos])


@dataclass
class _Mesh:
    nodes_mm: np.ndarray        # (V, 3) rest positions, sensor frame
    tets_skin: np.ndarray       # (Ks, 4)
    tets_gel: np.ndarray        # (Kg, 4)
    pinned: np.ndarray          # (V,) bool
    top: np.ndarray             # (Vt,) indices of outer-surface vertices
    top_faces: np.ndarray       # (F, 3) into ``top`` order


def build_mesh(design: SensorDesign, spec: MeshSpec) -> _Mesh:
    """Tetrahedral mesh of the skin + gel disc (see module notes). Rest positions in the sensor frame."""
    T, G, R = design.skin.thickness_mm, design.optics.gel_thickness_mm, design.gel.radius_mm
    ax = _axis(spec.fine_mm, spec.fine_half_mm, spec.growth, R, spec.core_mm, spec.core_half_mm)
    zs = [0.0] + [-T * (k + 1) / spec.skin_layers for k in range(spec.skin_layers)]
    zs += [-T - g for g in spec.gel_levels_mm if g < G - 1e-6] + [-T - G]
    zl = np.array(sorted(zs))                      # ascending: bottom first
    nx, nz = len(ax), len(zl)
    cx = 0.5 * (ax[:-1] + ax[1:])
    keep = np.hypot(cx[:, None], cx[None, :]) < R   # (nx-1, nx-1)
    cover = np.zeros((nx, nx), int)
    for di in (0, 1):
        for dj in (0, 1):
            cover[di:nx - 1 + di, dj:nx - 1 + dj] += keep
    used_xy = cover > 0
    interior = cover == 4
    I, J, K = np.meshgrid(np.arange(nx), np.arange(nx), np.arange(nz), indexing="ij")
    gid = -np.ones((nx, nx, nz), int)
    used = np.broadcast_to(used_xy[:, :, None], gid.shape)
    gid[used] = np.arange(int(used.sum()))
    nodes = np.column_stack([ax[I[used]], ax[J[used]], zl[K[used]]])
    pinned = (K[used] == 0) | ~interior[I[used], J[used]]
    # Kuhn split of each kept cell; with ``mirrored_split`` mirrored in every other cell along each axis: the
    # neighbours' shared faces still agree (a Kuhn cube's face diagonals are unchanged by a reflection normal
    # to that face), and with the parity counted from the node on the axis the mesh is its own mirror image
    # in x and in y, so a load symmetric about the axis gives a symmetric field (see MeshSpec)
    ci, cj = np.nonzero(keep)
    c0 = int(np.argmin(np.abs(ax)))
    mirror = bool(spec.mirrored_split)
    flip_x, flip_y = mirror & ((ci - c0) % 2 == 1), mirror & ((cj - c0) % 2 == 1)
    tets_by_layer = []
    perms = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    for k in range(nz - 1):
        flip = np.column_stack([flip_x, flip_y, np.full(len(ci), mirror and k % 2 == 1)])
        layer = []
        for p in perms:
            c = np.zeros((len(ci), 3), int)
            g = np.where(flip, 1 - c, c)
            verts = [gid[ci + g[:, 0], cj + g[:, 1], k + g[:, 2]]]
            for d in p:
                c[:, d] += 1
                g = np.where(flip, 1 - c, c)
                verts.append(gid[ci + g[:, 0], cj + g[:, 1], k + g[:, 2]])
            tet = np.column_stack(verts)
            # a reflection reverses orientation: swap two vertices so every tetrahedron stays positive
            odd = flip.sum(axis=1) % 2 == 1
            tet[odd] = tet[odd][:, [0, 2, 1, 3]]
            layer.append(tet)
        tets_by_layer.append(np.vstack(layer))
    n_skin = spec.skin_layers
    tets_skin = np.vstack(tets_by_layer[nz - 1 - n_skin:])
    tets_gel = np.vstack(tets_by_layer[:nz - 1 - n_skin])
    # outer surface
    top_gid = gid[:, :, nz - 1]
    top = top_gid[used_xy]
    local = -np.ones((nx, nx), int)
    local[used_xy] = np.arange(len(top))
    a, b = local[ci, cj], local[ci + 1, cj]
    c_, d = local[ci + 1, cj + 1], local[ci, cj + 1]
    top_faces = np.vstack([np.column_stack([a, b, c_]), np.column_stack([a, c_, d])])
    if design.pattern.dome_height_mm > 0:
        zb = -(T + G)
        frac = np.clip((nodes[:, 2] - zb) / (-T - zb), 0.0, 1.0)   # 1 in the skin layer, 0 at the window
        nodes[:, 2] += design.dome_z_mm(nodes[:, :2]) * frac
    return _Mesh(nodes, tets_skin, tets_gel, pinned, top, top_faces)


def _face_contact_faces(mesh: _Mesh) -> np.ndarray:
    """Outer faces (F', 3) (mesh vertex indices) that take part in face contact: those whose three vertices
    are all free.

    A face with a clamped vertex cannot be pushed out as a whole: a sphere touching it near the clamped
    corner or edge acts on the free vertices only through their small barycentric weights ``w``, and
    MuJoCo's contact moves them by ``penetration / w`` to clear it. Where the indenter reaches the clamped
    rim (a sine's crests run across the whole module) that drove the free rim vertices into the gel and
    the press blew up within a few steps (sine ω = π/5 at 0.1-0.15 mm: a rim vertex 1.0 -> 4.2 -> 7.6 ...
    -> 161 mm in 9 steps, inverted elements, then mjWARN_INERTIA from the effective-metric M + K solve).
    Those faces are also outside what the validity check scores (:func:`twin.validity.skin_penetration`,
    ``free``): the rigid mount there is not skin the model can resolve."""
    faces = mesh.top[mesh.top_faces]
    return faces[~np.any(mesh.pinned[faces], axis=1)]


def _grad_shape(X: np.ndarray):
    """Per tet (K,4,3) rest positions → volumes (K,) and shape-function gradients (K,4,3); and Dm⁻¹."""
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)
    vol = np.abs(np.linalg.det(Dm)) / 6.0
    Bi = np.linalg.inv(Dm)
    g = np.concatenate([-Bi.sum(axis=1, keepdims=True), Bi], axis=1)
    return vol, g, Bi


class SkinSim:
    """The skin module in MuJoCo with one indenter on a mocap "robot".

    Parameters
    ----------
    design : SensorDesign
    indenter : Indenter from :func:`twin.indenters.make_indenter`
    mesh : MeshSpec resolution
    timestep_s : physics step (s); the equilibrium does not depend on it
    friction : Coulomb friction skin/indenter; 0 (default) = frictionless contact (condim 1)

    Notes
    -----
    Poses are given as ``(x_mm, y_mm, depth_mm, yaw_deg)``: the indenter's own origin at sensor
    ``(x, y)``, its top at sensor ``z = -depth`` (depth < 0: clear of the skin).
    """

    def __init__(self, design: SensorDesign, indenter: Indenter, *, mesh: MeshSpec = MeshSpec(),
                 timestep_s: float = 0.01, friction: float = 0.0) -> None:
        import mujoco

        self._mj = mujoco
        self.design, self.indenter, self.mesh_spec = design, indenter, mesh
        self.timestep_s = float(timestep_s)
        t0 = time.perf_counter()
        self.mesh = m = build_mesh(design, mesh)
        self.friction = float(friction)
        if not math.isfinite(self.friction) or not 0.0 <= self.friction <= 10.0:
            raise PhysicsError(f"friction {friction!r}: must be a coefficient in [0, 10]")
        key = self._cache_key()
        hit = _MODEL_CACHE.get(key) if key is not None else None
        if hit is None:
            self._build(friction)
            if key is not None:
                # a pristine copy: a sim changes its own model as it runs (stick anchors, contacts switched off)
                _MODEL_CACHE[key] = (copy.copy(self.model), {a: getattr(self, a) for a in _DERIVED})
                while len(_MODEL_CACHE) > MODEL_CACHE_SIZE:
                    _MODEL_CACHE.popitem(last=False)
        else:
            _MODEL_CACHE.move_to_end(key)
            self.model = copy.copy(hit[0])           # mj_copyModel: this sim may change its own options
            self.data = mujoco.MjData(self.model)
            for a, v in hit[1].items():
                setattr(self, a, v)
        self.model_from_cache = hit is not None
        self._embed_pins()
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
        if len(self._stick_eq):
            self.model.eq_data[self._stick_eq] = 0.0
            self.data.eq_active[self._stick_eq] = 0
        if self.mesh_spec.face_contact:
            import mujoco as _m
            sph = np.nonzero((self.model.geom_type == _m.mjtGeom.mjGEOM_SPHERE)
                             & (self.model.geom_contype == _BIT_SPHERES))[0]
            self._face_geoms = sph
            self._face_flex = np.nonzero(self.model.flex_contype == _BIT_FACES)[0]
        else:
            self._face_geoms = self._face_flex = np.zeros(0, int)

    # ----- construction ---------------------------------------------------------------------
    def _cache_key(self):
        """Key of the compiled model in :data:`_MODEL_CACHE`; None (no caching) for indenters whose
        parameters are not plain scalars (e.g. a terrain patch's height map)."""
        params = sorted(self.indenter.params.items())
        if not all(isinstance(v, (int, float, str, bool)) for _, v in params):
            return None
        return (repr(self.design), repr(self.mesh_spec), self.indenter.name, repr(params), self.timestep_s,
                self.friction)

    def _build(self, friction: float) -> None:
        mj, m, d = self._mj, self.mesh, self.design
        dt = self.timestep_s
        V = len(m.nodes_mm)
        X_m = units.mm_to_m(m.nodes_mm * _FLIP)
        kd = np.zeros(V)
        ks = np.zeros(V)      # shear part: a surface vertex's stiffness against sliding along the indenter
        for tets, mat in ((m.tets_skin, materials.skin_material(d)), (m.tets_gel, materials.gel_material(d))):
            E, nu = units.mpa_to_pa(mat.youngs_modulus_mpa), mat.poisson_ratio
            lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
            vol, g, _ = _grad_shape(X_m[tets])
            np.add.at(kd, tets.ravel(), ((lam + 2 * mu) * vol[:, None] * np.sum(g * g, axis=2)).ravel())
            np.add.at(ks, tets.ravel(), (mu * vol[:, None] * np.sum(g * g, axis=2)).ravel())
        spec = mj.MjSpec()
        spec.modelname = f"skin_{d.name}"
        o = spec.option
        o.integrator = mj.mjtIntegrator.mjINT_DISCRETE
        # CG is ~3x faster a step on the flex; with the stick constraints its inexact solves leave the skin
        # vibrating (0.03 mm a step) and a press never settles, where Newton's converge (measured: 0.001 mm)
        o.solver = mj.mjtSolver.mjSOL_NEWTON if friction > 0 else mj.mjtSolver.mjSOL_CG
        o.timestep = dt
        o.gravity = [0.0, 0.0, 0.0]
        o.tolerance = 1e-6
        self._volumetric_solver_options(o)
        spec.memory = 256 * 1024 * 1024
        is_top = np.zeros(V, bool)
        is_top[m.top] = True
        condim = 1            # friction acts through the stick constraints (_update_stick), not MuJoCo's cone
        r_m = float(units.mm_to_m(CONTACT_RADIUS_MM))
        vertbody, vert = [], np.zeros((V, 3))
        self._free = np.nonzero(~m.pinned)[0]
        for n in range(V):
            if m.pinned[n]:
                vertbody.append("world")
                vert[n] = X_m[n]
                continue
            b = spec.worldbody.add_body(name=f"v{n}", pos=X_m[n].tolist())
            for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
                b.add_joint(type=mj.mjtJoint.mjJNT_SLIDE, axis=list(axis))
            b.mass = materials.MASS_SCALE * self._volumetric_mass_factor() * dt * dt * kd[n]
            b.inertia = [1e-15] * 3
            b.explicitinertial = True
            vertbody.append(f"v{n}")
            if is_top[n]:
                gm = b.add_geom(type=mj.mjtGeom.mjGEOM_SPHERE, size=[r_m, 0, 0], pos=[0, 0, r_m])
                gm.mass, gm.contype, gm.conaffinity, gm.condim = 0.0, 2, 1, condim
                gm.friction = [friction, 0.005, 0.0001]
                gm.group = 3
        for name, tets, mat in (("skin", m.tets_skin, materials.skin_material(d)),
                                ("gel", m.tets_gel, materials.gel_material(d))):
            f = spec.add_flex()
            f.name, f.dim = name, 3
            f.vertbody = vertbody
            f.vert = vert.ravel().tolist()
            f.elem = tets.ravel().tolist()
            f.young, f.poisson = self._flex_elasticity(mat)
            f.elastic3d = ELASTIC3D_STABLE_NEO_HOOKEAN
            f.damping = materials.RAYLEIGH_DAMPING_S
            f.contype = f.conaffinity = 0
            f.selfcollide = mj.mjtFlexSelf.mjFLEXSELF_NONE
            f.radius = 1e-6
        if self.mesh_spec.face_contact:
            # the outer faces as a 2-D flex without stiffness: what the indenter's surface spheres collide with
            f = spec.add_flex()
            f.name, f.dim = "outer_faces", 2
            f.vertbody = vertbody
            f.vert = vert.ravel().tolist()
            f.elem = _face_contact_faces(m).ravel().tolist()
            f.young, f.elastic2d = 0.0, 0
            f.contype, f.conaffinity, f.condim = _BIT_FACES, _BIT_SPHERES, condim
            f.friction = [friction, 0.005, 0.0001]
            f.radius = 1e-6
            f.selfcollide = mj.mjtFlexSelf.mjFLEXSELF_NONE
        # indenter: height field of its own-frame contact face on a mocap body
        x, y, z = self.indenter.grid(COLLISION_SPACING_MM)
        z = np.where(np.isfinite(z), z, np.nanmin(z))
        self._hmin = float(z.min())
        span = max(float(z.max()) - self._hmin, 1e-3)
        hx, hy = self.indenter.half_size_mm
        spec.add_hfield(name="indenter", size=[float(units.mm_to_m(hx)), float(units.mm_to_m(hy)),
                                               float(units.mm_to_m(span)), float(units.mm_to_m(2.0))],
                        nrow=z.shape[0], ncol=z.shape[1], userdata=((z - self._hmin) / span).ravel().tolist())
        if friction > 0:
            # Friction acts on relative velocity, and a mocap body has none (it is teleported): the skin would
            # be held where it is, not dragged along. With friction the indenter is a heavy body on three
            # slide joints and a hinge whose positions are prescribed every step and whose velocity is the
            # commanded increment over the step (see step()).
            body = spec.worldbody.add_body(name="indenter")
            for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
                body.add_joint(type=mj.mjtJoint.mjJNT_SLIDE, axis=list(axis), name=f"indenter_{'xyz'[axis.index(1)]}")
            body.add_joint(type=mj.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], name="indenter_yaw")
            body.mass = DRIVEN_INDENTER_MASS_KG
            body.inertia = [DRIVEN_INDENTER_MASS_KG * 1e-4] * 3
            body.explicitinertial = True
            # stick: one (inactive) point constraint per free outer vertex, switched on by the Coulomb
            # check in _update_stick while the vertex sticks to the indenter at the point where it touched
            for n in self._free[is_top[self._free]]:
                e = spec.add_equality()
                e.type, e.objtype = mj.mjtEq.mjEQ_CONNECT, mj.mjtObj.mjOBJ_BODY
                e.name1, e.name2 = f"v{n}", "indenter"
                e.active = False
                e.solref = [STICK_TIMECONST_STEPS * dt, STICK_DAMPRATIO]
                e.solimp = [0.99, 0.999, 1e-5, 0.5, 2.0]
        else:
            body = spec.worldbody.add_body(name="indenter", mocap=True)
        g = body.add_geom(type=mj.mjtGeom.mjGEOM_HFIELD, hfieldname="indenter",
                          pos=[0, 0, float(units.mm_to_m(self._hmin))])
        g.contype, g.conaffinity, g.condim, g.priority = 1, 2, condim, 1
        g.friction = [friction, 0.005, 0.0001]
        g.solref = [CONTACT_TIMECONST_STEPS * dt, CONTACT_DAMPRATIO]
        g.solimp = [0.99, 0.999, 1e-5, 0.5, 2.0]
        self._n_surface_spheres = 0
        if self.mesh_spec.face_contact:
            cell = self.mesh_spec.core_mm or self.mesh_spec.fine_mm
            centres, radii = contact.surface_spheres(self.indenter, skin_cell_mm=cell, with_radii=True)
            self._n_surface_spheres = int(len(centres))
            for c, r_s in zip(units.mm_to_m(centres), units.mm_to_m(radii)):
                gs = body.add_geom(type=mj.mjtGeom.mjGEOM_SPHERE, size=[float(r_s), 0, 0], pos=c.tolist())
                gs.contype, gs.conaffinity, gs.condim, gs.priority = _BIT_SPHERES, _BIT_FACES, condim, 1
                gs.friction = [friction, 0.005, 0.0001]
                gs.solref = [CONTACT_TIMECONST_STEPS * dt, CONTACT_DAMPRATIO]
                gs.solimp = [0.99, 0.999, 1e-5, 0.5, 2.0]
                gs.mass, gs.group = 0.0, 3
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # MuJoCo's note on flexes without equality constraints
            self.model = spec.compile()
        self.data = mj.MjData(self.model)
        self._qadr = self.model.jnt_qposadr[:len(self._free) * 3].reshape(-1, 3)
        self._vol = self._build_volumetric(X_m)
        self._ind_qadr = self._ind_dadr = None
        self._stick_nodes = self._stick_free = self._stick_eq = np.zeros(0, np.int64)
        self._stick_k = np.zeros(0)
        self._stick_geom = np.zeros(0, np.int64)
        if friction > 0:
            jid = [self.model.joint(f"indenter_{n}").id for n in ("x", "y", "z", "yaw")]
            self._ind_qadr = self.model.jnt_qposadr[jid].copy()
            self._ind_dadr = self.model.jnt_dofadr[jid].copy()
            free_pos = {int(n): i for i, n in enumerate(self._free)}
            self._stick_nodes = self._free[is_top[self._free]]
            self._stick_free = np.array([free_pos[int(n)] for n in self._stick_nodes], dtype=np.int64)
            self._stick_k = ks[self._stick_nodes]
            self._stick_geom = np.array([self.model.body(f"v{n}").geomadr[0] for n in self._stick_nodes])
            self._stick_eq = np.arange(len(self._stick_nodes))    # the model's only equalities, in that order
            assert self.model.neq == len(self._stick_eq)
        self._top_geom = {}
        for n in self._free[is_top[self._free]]:
            self._top_geom[self.model.body(f"v{n}").geomadr[0]] = n
        # direct solves: rest world positions (m) of the free vertices, the outer-surface vertex and the
        # window vertex of each vertex's column (the mesh is a tensor grid: columns share x-y)
        self._rest_free_m = X_m[self._free]
        key = np.round(m.nodes_mm[:, :2], 6)
        _, col = np.unique(key, axis=0, return_inverse=True)
        col = col.ravel()
        top_of = np.full(col.max() + 1, -1)
        top_of[col[m.top]] = m.top
        bottom_of = np.full(col.max() + 1, -1)
        zmin = np.full(col.max() + 1, np.inf)
        for i, (c, z) in enumerate(zip(col, m.nodes_mm[:, 2])):
            if z < zmin[c]:
                zmin[c], bottom_of[c] = z, i
        self._col_top, self._col_bottom = top_of[col], bottom_of[col]
        self._is_free_top = np.zeros(V, bool)
        self._is_free_top[self._free] = is_top[self._free]

    # ----- nodal volumetric stiffness (twin.volumetric) ------------------------------------------
    def _flex_elasticity(self, mat) -> tuple[float, float]:
        """Young's modulus (Pa) and Poisson ratio the flex gets for a material: all of it, or with
        ``MeshSpec.volumetric == "nodal"`` its shear modulus at ν = ``volumetric.NU_DEV`` (the rest of the
        bulk stiffness goes to the nodal term, :mod:`twin.volumetric`)."""
        E, nu = units.mpa_to_pa(mat.youngs_modulus_mpa), mat.poisson_ratio
        if self.mesh_spec.volumetric == "nodal" and nu > volumetric.NU_DEV:
            return volumetric.bulk_split(E, nu, volumetric.NU_DEV)[0], volumetric.NU_DEV
        return E, nu

    def _base_damping(self) -> np.ndarray:
        """DOF damping outside direct solves: zero, or with nodal volumetric forces mass-proportional at
        ``volumetric.DAMPING_PER_S`` (the unlocked gel's slow modes otherwise ring for hundreds of steps)."""
        mass = self.model.body_mass[self.model.dof_bodyid]
        return volumetric.DAMPING_PER_S * mass if self.mesh_spec.volumetric == "nodal" else np.zeros_like(mass)

    def _volumetric_solver_options(self, o) -> None:
        """Nodal volumetric forces need the constraint solve converged tighter: at tolerance 1e-6 CG stops
        early and the frictionless contact of the unlocked gel chatters (sphere R 10 mm, 1 mm, ν = 0.49:
        force 0-0.27 N step to step); at ``volumetric.SOLVER_TOLERANCE`` it holds 0.193-0.194 N, as Newton
        does at twice the time a step."""
        if self.mesh_spec.volumetric == "nodal":
            o.tolerance = volumetric.SOLVER_TOLERANCE
            o.iterations = volumetric.SOLVER_ITERATIONS

    def _volumetric_mass_factor(self) -> float:
        """Vertex mass multiplier with nodal volumetric stiffness (``volumetric.MASS_FACTOR``), else 1."""
        return volumetric.MASS_FACTOR if self.mesh_spec.volumetric == "nodal" else 1.0

    def _build_volumetric(self, X_m: np.ndarray):
        """The nodal volumetric energy of the materials stiffer in bulk than ``volumetric.NU_DEV`` and where
        its forces go (the free vertices' slide DOFs); None unless ``MeshSpec.volumetric == "nodal"``."""
        mode = self.mesh_spec.volumetric
        if mode == "element":
            return None
        if mode != "nodal":
            raise PhysicsError(f"MeshSpec.volumetric {mode!r}: 'element' or 'nodal'")
        m, d = self.mesh, self.design
        groups: dict[tuple[float, float], list] = {}    # one term per node and material (equal materials merged)
        for tets, mat in ((m.tets_skin, materials.skin_material(d)), (m.tets_gel, materials.gel_material(d))):
            E, nu = units.mpa_to_pa(mat.youngs_modulus_mpa), mat.poisson_ratio
            if nu > volumetric.NU_DEV and len(tets):
                groups.setdefault((E, nu), []).append(tets)
        if not groups:
            return None
        groups = [(np.vstack(t), volumetric.bulk_split(E, nu, volumetric.NU_DEV)[1]) for (E, nu), t in groups.items()]
        active = ~m.pinned if volumetric.FREE_NODES_ONLY else None
        nv = volumetric.NodalVolume.build(X_m, groups, active)
        free_pos = -np.ones(len(m.nodes_mm), np.int64)
        free_pos[self._free] = np.arange(len(self._free))
        keep = free_pos[nv.pair_node] >= 0
        return {"nv": nv, "pairs": np.nonzero(keep)[0], "pair_dof": self._qadr[free_pos[nv.pair_node[keep]]]}

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

    def _embed_pins(self) -> None:
        d, m = self.design, self.mesh
        rest = d.rest_markers_mm()
        base = rest.copy()
        base[:, 2] += d.pins.height_mm                       # skin underside above the marker
        X = m.nodes_mm[m.tets_skin]                           # (K, 4, 3)
        vol, g, Bi = _grad_shape(X)
        rel = base[:, None, :] - X[None, :, 0, :]             # (N, K, 3)
        lam = np.einsum("kij,nkj->nki", Bi, rel)              # (N, K, 3) barycentric 1..3
        bary = np.concatenate([1 - lam.sum(axis=2, keepdims=True), lam], axis=2)
        inside = np.min(bary, axis=2)
        k = np.argmax(inside, axis=1)
        if np.any(inside[np.arange(len(k)), k] < -1e-6):
            raise PhysicsError(f"design {d.name}: a pin base lies outside the skin mesh")
        self._pin_tet = m.tets_skin[k]                        # (N, 4)
        self._pin_w = bary[np.arange(len(k)), k]              # (N, 4)
        # pin rotation: volume-weighted mean deformation gradient of the skin tetrahedra whose
        # centroids lie within PIN_ROTATION_RADIUS of the base (x-y), a symmetric neighbourhood
        from scipy.sparse import csr_matrix
        from scipy.spatial import cKDTree

        cent = X.mean(axis=1)
        rad = max(PIN_ROTATION_RADIUS_FACTOR * self.mesh_spec.fine_mm, d.pins.diameter_mm)
        lists = cKDTree(cent[:, :2]).query_ball_point(base[:, :2], rad)
        rows, cols, vals = [], [], []
        for i, lst in enumerate(lists):
            lst = [j for j in lst if abs(cent[j, 2] - base[i, 2]) <= d.skin.thickness_mm] or [int(k[i])]
            w = vol[lst] / vol[lst].sum()
            rows += [i] * len(lst)
            cols += list(lst)
            vals += list(w)
        used = np.unique(cols)
        remap = -np.ones(len(X), int)
        remap[used] = np.arange(len(used))
        self._rot_tets = m.tets_skin[used]
        self._rot_Bi = Bi[used]
        self._rot_avg = csr_matrix((vals, (rows, remap[cols])), shape=(len(base), len(used)))
        self._rest_axis = np.array([0.0, 0.0, -1.0])

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
                    self._update_stick()
            motion = float(units.m_to_mm(np.max(np.abs(self.data.qpos[idx] - q)))) if len(q) else 0.0
            self.steps_taken += 1
        return motion

    def _update_stick(self) -> None:
        """Coulomb's law at each outer vertex, with the constraint forces of the step just taken.

        A vertex that comes into contact sticks: a point constraint to the indenter is switched on at the
        point where it touched, so it moves with the indenter without creeping (MuJoCo's own friction is a
        velocity-level soft constraint: under a held tangential load it creeps back). Where the tangential
        force T on a stuck vertex exceeds μN (N its normal force), the anchor slides on the indenter's
        surface towards where the skin pulls, by the excess over the vertex's tangential stiffness (a
        return map, as in penalty-based finite-element friction), so a sliding vertex carries μN and no
        more. The constraint is switched off where N pulls (the skin separates). Normals are the
        indenter's true surface normals at the vertex.
        """
        d, mu = self.data, self.friction
        eq = self._stick_eq
        idx = self._qadr[self._stick_free]                       # (K, 3) the vertices' slide DOFs (world axes)
        F = d.qfrc_constraint[idx]
        stuck = d.eq_active[eq] != 0
        a = np.nonzero(stuck | np.any(F != 0.0, axis=1))[0]
        if not len(a):
            return
        # a step's constraint forces carry the inflated vertex masses' transients: the Coulomb check uses
        # their running mean over ~STICK_FORCE_STEPS steps
        w = 1.0 / STICK_FORCE_STEPS
        dev2 = np.sum((F[a] - self._stick_F[a]) ** 2, axis=1)
        self._stick_F[a] = np.where(stuck[a, None], (1 - w) * self._stick_F[a] + w * F[a], F[a])
        self._stick_var[a] = np.where(stuck[a], (1 - w) * self._stick_var[a] + w * dev2, 0.0)
        X = self._rest_free_m[self._stick_free[a]] + d.qpos[idx[a]]            # world m
        xs = units.m_to_mm(X[:, :2]) * _FLIP[:2]                               # sensor x-y mm
        h = NORMAL_STEP_MM
        gx = (self.indenter_z_at(xs + [h, 0]) - self.indenter_z_at(xs - [h, 0])) / (2 * h)
        gy = (self.indenter_z_at(xs + [0, h]) - self.indenter_z_at(xs - [0, h])) / (2 * h)
        n = np.stack([gx, -gy, np.ones_like(gx)], axis=1)       # into the skin, world frame
        n = np.where(np.isfinite(n), n, [0.0, 0.0, 1.0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        Fa = self._stick_F[a]
        N = np.einsum("ij,ij->i", Fa, n)
        Tv = Fa - N[:, None] * n
        T = np.linalg.norm(Tv, axis=1)
        st = stuck[a]
        p_ind, yaw = d.qpos[self._ind_qadr[:3]], float(d.qpos[self._ind_qadr[3]])
        c, s_ = math.cos(yaw), math.sin(yaw)

        def to_local(w):
            return np.stack([c * w[:, 0] + s_ * w[:, 1], -s_ * w[:, 0] + c * w[:, 1], w[:, 2]], axis=1)

        release = st & (N <= 0.0)
        d.eq_active[eq[a[release]]] = 0
        self._stuck_contact(a[release], True)
        # slide only where the excess is beyond the mean's own noise (its standard error, from the running
        # variance): otherwise the noise walks the anchors at the contact's edge and the press never settles
        noise = STICK_SIGNIFICANCE * np.sqrt(self._stick_var[a] * w / (2 - w)) * (1 + mu)
        slide = st & (N > 0.0) & (T - mu * N > noise)
        if np.any(slide):
            # the anchor moves against the constraint's tangential force, i.e. where the skin pulls
            step_m = STICK_RELAX * (T[slide] - mu * N[slide] - noise[slide]) / self._stick_k[a[slide]]
            step_m = np.minimum(step_m, units.mm_to_m(STICK_MAX_SLIDE_MM))
            shift = -Tv[slide] / T[slide, None] * step_m[:, None]
            e = eq[a[slide]]
            self.model.eq_data[e, 3:6] += to_local(shift)
        stick = ~st & (N > 0.0)
        if np.any(stick):
            e = eq[a[stick]]
            # the anchor is where the vertex touches the surface: a vertex that lags inside is held on it
            P = X[stick].copy()
            zi = -units.mm_to_m(self.indenter_z_at(xs[stick]))                # world z of the surface
            P[:, 2] = np.where(np.isfinite(zi), np.maximum(P[:, 2], zi), P[:, 2])   # the indenter lies below (world)
            self.model.eq_data[e, 0:3] = 0.0
            self.model.eq_data[e, 3:6] = to_local(P - p_ind)
            d.eq_active[e] = 1
            self._stuck_contact(a[stick], False)

    def _stuck_contact(self, k: np.ndarray, on: bool) -> None:
        """A stuck vertex's contact sphere is switched off: its constraint carries the normal load too (a
        contact and a point constraint on one vertex fight over it, and the press never settles)."""
        g = self._stick_geom[k]
        self.model.geom_contype[g] = 2 if on else 0
        self.model.geom_conaffinity[g] = 1 if on else 0

    def stuck_vertices(self) -> np.ndarray:
        """Mesh indices of the outer vertices currently stuck to the indenter (friction > 0)."""
        return self._stick_nodes[self.data.eq_active[self._stick_eq] != 0]

    def penetration_mm(self) -> float:
        """Deepest current contact penetration (mm, >= 0): how far a skin vertex lags inside the indenter."""
        n = self.data.ncon
        return float(units.m_to_mm(max(0.0, -float(np.min(self.data.contact.dist[:n]))))) if n else 0.0

    def move_to(self, x_mm: float, y_mm: float, depth_mm: float, yaw_deg: float, *,
                max_increment_mm: float = MAX_INCREMENT_MM, max_increment_deg: float = 1.0,
                contact_increment_mm: float = CONTACT_INCREMENT_MM,
                penetration_limit_mm: float = PENETRATION_LIMIT_MM) -> int:
        """Move the indenter in straight-line increments, one physics step each; returns steps.

        Increments are ``max_increment_mm`` while nothing touches and ``contact_increment_mm``
        (if smaller) while the indenter is in contact with the skin. While a skin vertex lags more
        than ``penetration_limit_mm`` inside the indenter the robot holds still (physics steps on) as
        long as the lag shrinks by ``HOLD_PROGRESS_MM`` a step, at most ``MAX_HOLD_STEPS`` in a row: the
        lag stays bounded whatever the shape and stiffness, and a vertex caught for good (a flank
        steeper than the mesh resolves) does not stall the motion.
        """
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
        return n

    def settle(self, *, tol_mm: float = SETTLE_TOL_MM, consecutive: int = SETTLE_CONSECUTIVE,
               max_steps: int = SETTLE_MAX_STEPS, abort=None,
               damped_steps: int = SETTLE_DAMPED_STEPS) -> SettleStats:
        """Step until the markers' mean over the last ``consecutive`` steps moved < ``tol_mm`` from the
        mean over the ``consecutive`` steps before (every marker); ``last_motion_mm`` is that drift.
        ``abort(n)``, if given, is asked after step ``n``; when it returns True the settle stops there
        (``converged`` False). Not settled after ``max_steps``, it goes on for at most ``damped_steps`` with
        the damped continuation (``SETTLE_DAMPED_PER_S``)."""
        t0 = time.perf_counter()
        w = max(1, int(consecutive))
        hist: list[np.ndarray] = []
        motion, n = float("inf"), 0

        def run(limit: int) -> bool:     # True: aborted
            nonlocal motion, n
            while n < limit:
                self.step()
                n += 1
                if abort is not None and abort(n):
                    return True
                hist.append(self.markers()[0])
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
            saved = self.model.dof_damping.copy()
            mass = self.model.body_mass[self.model.dof_bodyid]
            self.model.dof_damping[:] = saved + SETTLE_DAMPED_PER_S * mass
            try:
                start = n
                run(n + damped_steps)
                damped = n - start
            finally:
                self.model.dof_damping[:] = saved
        return SettleStats(n, motion < tol_mm, motion, time.perf_counter() - t0, damped_steps=damped)

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
        slipped through the height field's prism walls and no longer registers a contact.
        """
        X = self._nodes_from_qpos()[self._is_free_top]
        zi = self.indenter_z_at(X[:, :2])
        pen = X[:, 2] - zi
        pen = pen[np.isfinite(pen)]
        return float(max(0.0, pen.max())) if len(pen) else 0.0

    def solve_at(self, x_mm: float, y_mm: float, depth_mm: float, yaw_deg: float, *,
                 accept_mm: float = DIRECT_ACCEPT_MM, abort_mm: float = DIRECT_ABORT_MM) -> SettleStats | None:
        """Quasi-static equilibrium at a pose without following the path to it; None if not valid.

        With frictionless contact and a hyperelastic body the equilibrium depends only on the indenter's
        pose, not on how it got there, so the indenter is placed at the pose directly and the mesh warm-
        started geometrically: every free outer vertex inside the indenter is moved vertically onto its
        surface and the vertices below it by the same amount scaled linearly to zero at the window (a
        column compressed uniformly). The sim then settles (:meth:`settle`, same criterion) with a mass-
        proportional DOF damping ``DIRECT_DAMPING_PER_S`` that removes the slow gel modes (zero again
        afterwards). Without the followed path's lag limit, a vertex can be pushed through a steep flank
        or around a sharp tip; so the result is accepted only if the sim converged and no free outer
        vertex ends more than ``accept_mm`` inside the indenter (checked every ``DIRECT_CHECK_EVERY``
        steps while settling, abandoned beyond ``abort_mm``). Otherwise the state before the call is
        restored exactly and None returned: the caller follows the path instead (:meth:`move_to`).
        With friction the equilibrium depends on the path: always None.

        Measured (hexagon127, 5 mm press): Gaussian σ² = 10 equilibrium within 0.004 mm of the followed
        path's markers (σ² = 50: 0.0035 mm), 66 + 0 steps instead of 273; sines and the σ² = 5/3 tip
        are rejected (vertices 1.9-4.4 mm inside without the lag limit).
        """
        mj = self._mj
        if self.friction > 0:
            return None
        saved, steps0 = self.checkpoint(), self.steps_taken
        warn0 = saved.warnings
        self.set_pose(x_mm, y_mm, depth_mm, yaw_deg)
        X = self._nodes_from_qpos()
        top = self._col_top
        zi = self.indenter_z_at(X[top, :2])
        dz = np.where(np.isfinite(zi), np.minimum(0.0, zi - X[top, 2]), 0.0)
        zb = X[self._col_bottom, 2]
        frac = np.clip((X[:, 2] - zb) / np.maximum(X[top, 2] - zb, 1e-9), 0.0, 1.0)
        disp = np.zeros_like(X)
        disp[:, 2] = dz * frac
        q = self.data.qpos
        idx = self._qadr.ravel()
        q[idx] += units.mm_to_m(disp[self._free] * _FLIP).ravel()
        mass = self.model.body_mass[self.model.dof_bodyid]
        self.model.dof_damping[:] = DIRECT_DAMPING_PER_S * mass
        if self._vol is not None:
            # the vertical warm start compresses columns: at once the nodal forces of that volume change would
            # throw surface vertices into the indenter (σ² = 10, 5 mm: 0.42 mm in after 4 steps)
            self._vol_ramp = volumetric.WARM_RAMP_STEPS
        deepest = [0.0]

        def abort(n: int) -> bool:
            if n % DIRECT_CHECK_EVERY:
                return False
            deepest[0] = self.outer_penetration_mm()
            return deepest[0] > abort_mm or self.unstable(warn0)

        try:
            self._update_volumetric()
            mj.mj_forward(self.model, self.data)
            stats = self.settle(abort=abort)
        finally:
            self.model.dof_damping[:] = self._base_damping()
            self._vol_ramp = 0
        if stats.converged:
            deepest[0] = self.outer_penetration_mm()
        unstable = self.unstable(warn0)
        if stats.converged and deepest[0] <= accept_mm and not unstable:
            self.direct_solves += 1
            return replace(stats, direct=True)
        self.direct_rejections += 1
        self.direct_wasted_steps += self.steps_taken - steps0
        self.restore(saved)
        return None

    def checkpoint(self) -> "Checkpoint":
        """The sim's integration state, indenter pose and MuJoCo warning counts, for :meth:`restore`."""
        spec = self._mj.mjtState.mjSTATE_INTEGRATION
        state = np.empty(self._mj.mj_stateSize(self.model, spec))
        self._mj.mj_getState(self.model, self.data, state, spec)
        return Checkpoint(state, self.pose, [int(w.number) for w in self.data.warning],
                          (self.model.eq_data[self._stick_eq].copy(), self._stick_F.copy(), self._stick_var.copy()))

    def restore(self, cp: "Checkpoint") -> None:
        """Undo everything since :meth:`checkpoint` bit for bit, the warnings raised meanwhile included
        (an attempt that is thrown away must not mark the state that is kept)."""
        self._mj.mj_setState(self.model, self.data, cp.state, self._mj.mjtState.mjSTATE_INTEGRATION)
        for w, n in zip(self.data.warning, cp.warnings):
            w.number = n
        self.model.eq_data[self._stick_eq] = cp.stick[0]
        self._stick_F, self._stick_var = cp.stick[1].copy(), cp.stick[2].copy()
        stuck = self.data.eq_active[self._stick_eq] != 0
        self._stuck_contact(np.nonzero(~stuck)[0], True)
        self._stuck_contact(np.nonzero(stuck)[0], False)
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

    # ----- read-out -----------------------------------------------------------------------
    def nodes_mm(self) -> np.ndarray:
        """Current positions of all mesh vertices, sensor frame (V, 3) mm."""
        V = len(self.mesh.nodes_mm)
        return units.m_to_mm(self.data.flexvert_xpos[:V]) * _FLIP

    def skin_vertices_mm(self) -> np.ndarray:
        """Deformed outer skin surface vertices (Vt, 3), sensor frame; faces: ``mesh.top_faces``."""
        return self.nodes_mm()[self.mesh.top]

    def markers(self) -> tuple[np.ndarray, np.ndarray]:
        """Marker face centres (N, 3) mm and unit pin axes (N, 3), sensor frame, canonical order."""
        X = self.nodes_mm()
        P = X[self._pin_tet]                                            # (N, 4, 3)
        base = np.einsum("nk,nkj->nj", self._pin_w, P)
        Q = X[self._rot_tets]
        Ds = np.stack([Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0], Q[:, 3] - Q[:, 0]], axis=2)
        F = (self._rot_avg @ (Ds @ self._rot_Bi).reshape(len(Q), 9)).reshape(-1, 3, 3)
        U, _, Vt = np.linalg.svd(F)
        Rm = U @ Vt
        flip = np.linalg.det(Rm) < 0
        if np.any(flip):
            U[flip, :, -1] *= -1
            Rm = U @ Vt
        axis = Rm @ self._rest_axis
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        return base + self.design.pins.height_mm * axis, axis

    def indenter_heightmap(self, *, spacing_mm: float = 0.2) -> HeightMap:
        """Indenter contact surface in the sensor frame at the current pose."""
        x, y, depth, yaw = self.pose
        return self.indenter.sensor_heightmap(x, y, depth, yaw, half_mm=self.design.gel.radius_mm + 2.0,
                                              spacing_mm=spacing_mm)

    def indenter_z_at(self, xy_mm: np.ndarray) -> np.ndarray:
        """Indenter surface sensor z (mm) above sensor points (N, 2); NaN off the part."""
        from twin.indenters import sensor_to_indenter_xy

        x, y, depth, yaw = self.pose
        xi, yi = sensor_to_indenter_xy(xy_mm[:, 0], xy_mm[:, 1], x, y, yaw)
        return self.indenter.top_mm - self.indenter.height(xi, yi) - depth

    def touching(self) -> np.ndarray:
        """Mesh indices of the outer-surface vertices whose contact sphere touches the indenter."""
        out = set()
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            for gid in c.geom:
                if int(gid) in self._top_geom and c.dist < 1e-5:
                    out.add(self._top_geom[int(gid)])
        return np.array(sorted(out), dtype=np.int64)

    def gap_mm(self) -> np.ndarray:
        """Indenter − skin height (mm) at touching vertices (positive: a gap, negative: penetration)."""
        idx = self.touching()
        X = self.nodes_mm()[idx]
        return self.indenter_z_at(X[:, :2]) - X[:, 2]

    def contact_force_n(self) -> float:
        """Total force the indenter exerts on the skin along the press direction (N).

        Summed from the constraint forces on the vertex DOFs (the only constraints are the
        skin–indenter contacts), along world +z = sensor −z.
        """
        qz = self.data.qfrc_constraint[:3 * len(self._free)][2::3]
        return float(np.sum(qz))

    def validity(self, *, settled: bool) -> FrameValidity:
        """Physical validity of the current state (:mod:`twin.validity`): the outer skin's penetration
        into the indenter's true surface at vertices, face centroids, edge midpoints and the indenter's
        own 0.1 mm samples over the deformable skin (the clamped rim is the rigid mount: how far the
        indenter reaches below it is recorded as ``rim_overlap_mm``); the contact force; ``settled``;
        MuJoCo's warning counters so far."""
        top = self.skin_vertices_mm()
        free = ~self.mesh.pinned[self.mesh.top]
        pen = skin_penetration(top, self.mesh.top_faces, self.indenter_z_at, free=free)
        return frame_validity(pen, contact_force_n=self.contact_force_n(), settled=settled,
                              mujoco_warnings=self.warnings(), rim_overlap=rim_overlap_mm(top, ~free, self.indenter_z_at))

    def truth(self, *, settled: bool | None = None) -> Truth:
        """Truth of the current state (sensor frame, mm); with ``settled`` given, its physics validity
        (:meth:`validity`) is recorded in it."""
        xyz, axis = self.markers()
        x, y, depth, yaw = self.pose
        val = None if settled is None else self.validity(settled=settled).to_dict()
        return Truth(np.arange(len(xyz)), xyz, axis, self.skin_vertices_mm(), self.mesh.top_faces,
                     self.indenter_heightmap(), np.array([x, y, -depth, yaw]), val)
