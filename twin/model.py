"""The skin module's MuJoCo model, built in code with :class:`mujoco.MjSpec`, and its per-process cache.

What :func:`build` compiles from a :class:`~twin.mesh.MeshSpec` mesh (:mod:`twin.mesh`), a design and an
indenter; :class:`twin.physics.SkinSim` runs it.

* Two 3-D flexes share the vertices: ``skin`` (the top layer, thickness T, the skin's E and ν) and
  ``gel`` (everything below, the gel's E and ν), MuJoCo's stable Neo-Hookean model
  (``elastic3d = 1``), the discrete integrator with the CG solver. St Venant–Kirchhoff (MuJoCo's
  default) softens under compression and lets elements collapse: a Gaussian (σ² = 10) pressed 5 mm
  inverted 302 gel and 6 skin tetrahedra (min det F = −1.15), squashed the skin to 0.4 T and left
  the centre marker 1.08 mm below the outer skin instead of T + H = 2.5 mm; with stable
  Neo-Hookean min det F = 0.58 (gel) / 0.86 (skin) and the gel flows sideways. Vertices on the bottom (bonded to the acrylic) and on the lateral
  boundary (clamped by the rigid mount) are fixed to the world body.
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
* With friction the indenter is a heavy driven body instead of a mocap, and every free outer vertex
  has two (inactive) joint equalities to it, tying its x and y to the indenter's, that the Coulomb
  check switches on (:mod:`twin.stick`); the contact keeps carrying the normal load.
* Mass scaling (:mod:`twin.materials`): ``m_i = MASS_SCALE · dt² · K_ii``; gravity off.
* Volumetric locking: linear tetrahedra lock as ν → 0.5 (uniform ν = 0.49 gel: 2.3× the layer solution's
  force). ``MeshSpec(volumetric="nodal")`` gives the flexes each material's shear modulus at ν = 0.15 and
  carries the rest of its bulk modulus on averaged nodal volume ratios (:mod:`twin.volumetric`; Bonet &
  Burton 1998): explicit forces on the vertices' slide DOFs, so with it the vertex masses are
  ``volumetric.MASS_FACTOR`` × heavier, the path is damped and the constraint solve converged tighter.
* Compiled models are cached per process (design, mesh, indenter, timestep, friction): a second sim
  of the same set-up copies the model instead of compiling it (~0.1 s instead of 0.8-1.3 s).

MuJoCo's world frame is the sensor frame rotated 180° about x (the sensor looks down at the
indenter on the desk): world = (x, -y, -z)_sensor (:data:`_FLIP`). Lengths cross to metres only via
:mod:`twin.units`.

The module is ~400 lines and stays whole: :func:`build` is split into its assembly steps (options, vertex bodies,
flexes, indenter, the index arrays the sim needs), and the solver options and volumetric terms it applies are the
knobs those steps read; moving them out would leave each half depending on the other's constants.
"""

from __future__ import annotations

import copy
import warnings
from collections import OrderedDict

import numpy as np

from pipeline.design import SensorDesign
from twin import contact, materials, units, volumetric
from twin.indenters import COLLISION_SPACING_MM, Indenter
from twin.mesh import MeshSpec, PhysicsError, _face_contact_faces, _grad_shape, _Mesh

__all__ = ["CONTACT_RADIUS_MM", "build", "load", "cache_key", "flex_elasticity"]

CONTACT_RADIUS_MM = 0.25     # vertex contact sphere > the 0.2 mm height-field cell, so it always spans several
                             # prisms (0.12 mm let the stiff apex vertex slip through a prism wall: σ² = 10, 5 mm,
                             # 0.75 mm inside); slope error r(1/cos θ - 1) <= 0.10 mm up to 45°
ELASTIC3D_STABLE_NEO_HOOKEAN = 1   # MuJoCo flex ``elastic3d``: 0 = St Venant–Kirchhoff, 1 = stable Neo-Hookean
ROLLER_SLACK_M = 1e-9          # a roller rim vertex's x-y range about its rest position (MeshSpec.rim = "roller")
CONTACT_TIMECONST_STEPS = 2.0  # contact solref time constant in physics steps (the smallest MuJoCo allows)
CONTACT_DAMPRATIO = 0.7
CONTACT_SOLIMP = [0.99, 0.999, 1e-5, 0.5, 2.0]   # impedance of contacts, the stick ties and the roller rim's limits:
                                                # 0.99 -> 0.999 over 0.01 mm of penetration
_FLIP = np.array([1.0, -1.0, -1.0])  # sensor <-> MuJoCo world
ARENA_MIN_BYTES = 256 * 1024 * 1024   # MuJoCo's arena (stack + per-step data) for every mesh up to ~9,500 nodes, and ...
ARENA_BYTES_PER_NODE2 = 3.0           # ... beyond, this many bytes per squared mesh node: the peak use per step grows with
                                      # the square of the node count (1.1 / 1.25 / 1.35 bytes per node² at 4,869 / 10,953 /
                                      # 20,770 nodes, 25 / 143 / 583 MB, a sphere or a sine pressed 1 mm); at the fixed
                                      # 256 MB the 0.75 mm mesh of the convergence study stopped in mj_collision
MODEL_CACHE_SIZE = 4         # compiled models kept per process (a press sweep re-presses one design/indenter at
                             # several yaws; compiling costs ~0.5-0.9 s of a ~3 s press, a copy ~0.01 s)
_MODEL_CACHE: "OrderedDict[tuple, tuple]" = OrderedDict()
_DERIVED = ("_free", "_qadr", "_top_geom", "_hmin", "_rest_free_m", "_col_top", "_col_bottom", "_is_free_top",
            "_n_surface_spheres", "_ind_qadr", "_ind_dadr", "_stick_nodes", "_stick_free", "_stick_eq",
            "_stick_k", "_vol")
STICK_DAMPRATIO = 1.0       # the stick constraint's damping ratio (time constant as the contacts')
STICK_TIMECONST_STEPS = 4.0
STICK_SOLVER_TOLERANCE = 1e-10  # with friction: CG's tolerance and iteration cap (friction_solver_options)
STICK_SOLVER_ITERATIONS = 1000
SETTLE_SOLVER_TOLERANCE = 1e-8  # every settle at least this converged (settle_solver_options)
DRIVEN_INDENTER_MASS_KG = 1e5     # with friction: the indenter's mass, >> the skin's whole scaled mass (~190 kg on the
                                  # axis contact mesh), so contact forces do not deflect it within a step (its position
                                  # is re-imposed after every step). At 100 kg the skin pushed it back ~0.008 mm a
                                  # step, the contacts saw the indenter receding and carried less than the load, and
                                  # stuck skin sat 0.06-0.18 mm inside wide Gaussians (σ² = 50/3, 50 at 5 mm); at 1e5
                                  # 0.018-0.024 mm, at 1e4 and 1e6 the same within 0.001 mm
# collision bits: vertex spheres (2/1) meet the height field (1/2); outer faces (4/8) meet surface spheres (8/4)
_BIT_FACES, _BIT_SPHERES = 4, 8
#: Frictionless contacts in MuJoCo's sense (condim 1): friction acts through the stick constraints of twin.stick,
#: not through MuJoCo's friction cone (soft: the skin under a tip crept back where contact mechanics says stick).
_CONDIM = 1


def arena_bytes(n_nodes: int) -> int:
    """MuJoCo's memory (``<size memory>``) for a skin mesh of ``n_nodes`` nodes: ``ARENA_MIN_BYTES``, or
    ``ARENA_BYTES_PER_NODE2`` per squared node where that is more (about 2.2-2.7x the measured peak use)."""
    return int(max(ARENA_MIN_BYTES, ARENA_BYTES_PER_NODE2 * float(n_nodes) ** 2))


def cache_key(design: SensorDesign, spec: MeshSpec, indenter: Indenter, timestep_s: float, friction: float):
    """Key of the compiled model in :data:`_MODEL_CACHE`; None (no caching) for indenters whose
    parameters are not plain scalars (e.g. a terrain patch's height map)."""
    params = sorted(indenter.params.items())
    if not all(isinstance(v, (int, float, str, bool)) for _, v in params):
        return None
    return (repr(design), repr(spec), indenter.name, repr(params), timestep_s, friction)


def load(design: SensorDesign, indenter: Indenter, mesh: _Mesh, spec: MeshSpec, timestep_s: float,
         friction: float):
    """The model of this set-up, from the per-process cache or compiled (:func:`build`): ``(model, derived,
    from_cache)``. A cached model is copied (``mj_copyModel``), so each sim may change its own; ``derived``
    (the arrays :func:`build` returns beside the model) is shared, never changed by a sim."""
    key = cache_key(design, spec, indenter, timestep_s, float(friction))
    hit = _MODEL_CACHE.get(key) if key is not None else None
    if hit is None:
        model, derived = build(design, indenter, mesh, spec, timestep_s, friction)
        if key is not None:
            # a pristine copy: a sim changes its own model as it runs (stick anchors, contacts switched off)
            _MODEL_CACHE[key] = (copy.copy(model), derived)
            while len(_MODEL_CACHE) > MODEL_CACHE_SIZE:
                _MODEL_CACHE.popitem(last=False)
        return model, derived, False
    _MODEL_CACHE.move_to_end(key)
    return copy.copy(hit[0]), hit[1], True


def build(design: SensorDesign, indenter: Indenter, mesh: _Mesh, spec: MeshSpec, timestep_s: float,
          friction: float):
    """Compile the skin module's model (module notes): ``(model, derived)`` with ``derived`` the index arrays
    the sim needs beside it, keyed by the sim's attribute names (:data:`_DERIVED`).

    The model is assembled in MuJoCo's spec in a fixed order — options, one body per free mesh vertex, the skin
    and gel flexes (and the outer faces' contact flex), the indenter with its surface spheres and stick
    equalities — because that order numbers the bodies, joints and equalities the sim indexes."""
    import mujoco as mj

    X_m = units.mm_to_m(mesh.nodes_mm * _FLIP)
    kd, ks = _nodal_stiffness(mesh, design, X_m)
    mjspec = mj.MjSpec()
    mjspec.modelname = f"skin_{design.name}"
    _set_options(mjspec.option, spec, timestep_s, friction)
    mjspec.memory = arena_bytes(len(X_m))
    is_top = np.zeros(len(X_m), bool)
    is_top[mesh.top] = True
    free = np.nonzero(~mesh.pinned)[0]
    vertbody, vert = _add_vertex_bodies(mjspec, mesh, spec, X_m, kd, is_top, timestep_s, friction)
    _add_flexes(mjspec, mesh, design, spec, vertbody, vert, friction)
    roller = mesh.roller if mesh.roller is not None else np.zeros(len(X_m), bool)
    # the outer vertices that can stick to the indenter: not those a roller rim holds in x-y already
    stick_candidates = free[is_top[free] & ~roller[free]]
    hmin, n_surface_spheres = _add_indenter(mjspec, indenter, spec, stick_candidates, timestep_s, friction)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # MuJoCo's note on flexes without equality constraints
        model = mjspec.compile()
    qadr = model.jnt_qposadr[:len(free) * 3].reshape(-1, 3)
    derived = {"_free": free, "_qadr": qadr, "_hmin": hmin, "_n_surface_spheres": n_surface_spheres,
               "_vol": build_volumetric(design, mesh, spec, X_m, free, qadr)}
    derived.update(_stick_indices(model, free, stick_candidates, ks, friction))
    derived.update(_column_indices(model, mesh, X_m, free, is_top))
    return model, derived


def _nodal_stiffness(mesh: _Mesh, design: SensorDesign, X_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, the diagonal stiffness of its elements (λ + 2μ)·V·|∇N|² (what its mass is scaled by, so the
    contact is as stiff as the element behind it) and its shear part μ·V·|∇N|² (a surface vertex's stiffness
    against sliding along the indenter), N·m⁻¹."""
    V = len(X_m)
    kd = np.zeros(V)
    ks = np.zeros(V)
    for tets, mat in ((mesh.tets_skin, materials.skin_material(design)), (mesh.tets_gel, materials.gel_material(design))):
        E, nu = units.mpa_to_pa(mat.youngs_modulus_mpa), mat.poisson_ratio
        lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
        vol, g, _ = _grad_shape(X_m[tets])
        np.add.at(kd, tets.ravel(), ((lam + 2 * mu) * vol[:, None] * np.sum(g * g, axis=2)).ravel())
        np.add.at(ks, tets.ravel(), (mu * vol[:, None] * np.sum(g * g, axis=2)).ravel())
    return kd, ks


def _set_options(o, spec: MeshSpec, dt: float, friction: float) -> None:
    """The discrete integrator (flex elasticity needs it) with the CG solver, no gravity, and the volumetric and
    friction solver options."""
    import mujoco as mj

    o.integrator = mj.mjtIntegrator.mjINT_DISCRETE
    o.solver = mj.mjtSolver.mjSOL_CG    # ~3x faster a step than Newton on the flex
    o.timestep = dt
    o.gravity = [0.0, 0.0, 0.0]
    o.tolerance = 1e-6
    volumetric_solver_options(spec, o)
    friction_solver_options(friction, o)


def _add_vertex_bodies(mjspec, mesh: _Mesh, spec: MeshSpec, X_m: np.ndarray, kd: np.ndarray, is_top: np.ndarray,
                       dt: float, friction: float) -> tuple[list[str], np.ndarray]:
    """One body on three slide joints per free vertex (a roller rim's limited in x-y), its mass scaled by its
    stiffness, and a contact sphere on each outer one; pinned vertices belong to the world. Returns the flexes'
    ``vertbody`` names and their vertex positions relative to those bodies."""
    import mujoco as mj

    r_m = float(units.mm_to_m(CONTACT_RADIUS_MM))
    vertbody, vert = [], np.zeros((len(X_m), 3))
    for n in range(len(X_m)):
        if mesh.pinned[n]:
            vertbody.append("world")
            vert[n] = X_m[n]
            continue
        b = mjspec.worldbody.add_body(name=f"v{n}", pos=X_m[n].tolist())
        for ax, axis in zip("xyz", ((1, 0, 0), (0, 1, 0), (0, 0, 1))):
            jnt = b.add_joint(type=mj.mjtJoint.mjJNT_SLIDE, axis=list(axis), name=f"v{n}{ax}")
            if mesh.roller is not None and mesh.roller[n] and ax != "z":
                # a roller rim holds the vertex on the mount's wall: x and y limited to their rest values
                jnt.limited, jnt.range = True, [-ROLLER_SLACK_M, ROLLER_SLACK_M]
                jnt.solref_limit = [CONTACT_TIMECONST_STEPS * dt, CONTACT_DAMPRATIO]   # as stiff as a contact
                jnt.solimp_limit = CONTACT_SOLIMP
        b.mass = materials.MASS_SCALE * volumetric_mass_factor(spec) * dt * dt * kd[n]
        b.inertia = [1e-15] * 3
        b.explicitinertial = True
        vertbody.append(f"v{n}")
        if is_top[n]:
            gm = b.add_geom(type=mj.mjtGeom.mjGEOM_SPHERE, size=[r_m, 0, 0], pos=[0, 0, r_m])
            gm.mass, gm.contype, gm.conaffinity, gm.condim = 0.0, 2, 1, _CONDIM
            gm.friction = [friction, 0.005, 0.0001]
            gm.group = 3
    return vertbody, vert


def _add_flexes(mjspec, mesh: _Mesh, design: SensorDesign, spec: MeshSpec, vertbody: list[str], vert: np.ndarray,
                friction: float) -> None:
    """The skin's and the gel's tetrahedra as two elastic 3-D flexes (no collision of their own) and, with face
    contact, the outer faces as a 2-D flex without stiffness that the indenter's surface spheres collide with."""
    import mujoco as mj

    for name, tets, mat in (("skin", mesh.tets_skin, materials.skin_material(design)),
                            ("gel", mesh.tets_gel, materials.gel_material(design))):
        f = mjspec.add_flex()
        f.name, f.dim = name, 3
        f.vertbody = vertbody
        f.vert = vert.ravel().tolist()
        f.elem = tets.ravel().tolist()
        f.young, f.poisson = flex_elasticity(spec, mat)
        f.elastic3d = ELASTIC3D_STABLE_NEO_HOOKEAN
        f.damping = materials.RAYLEIGH_DAMPING_S
        f.contype = f.conaffinity = 0
        f.selfcollide = mj.mjtFlexSelf.mjFLEXSELF_NONE
        f.radius = 1e-6
    if spec.face_contact:
        f = mjspec.add_flex()
        f.name, f.dim = "outer_faces", 2
        f.vertbody = vertbody
        f.vert = vert.ravel().tolist()
        f.elem = _face_contact_faces(mesh).ravel().tolist()
        f.young, f.elastic2d = 0.0, 0
        f.contype, f.conaffinity, f.condim = _BIT_FACES, _BIT_SPHERES, _CONDIM
        f.friction = [friction, 0.005, 0.0001]
        f.radius = 1e-6
        f.selfcollide = mj.mjtFlexSelf.mjFLEXSELF_NONE


def _add_indenter(mjspec, indenter: Indenter, spec: MeshSpec, stick_candidates: np.ndarray, dt: float,
                  friction: float) -> tuple[float, int]:
    """The indenter: a height field of its own-frame contact face (and, with face contact, spheres on its convex
    and steep parts) on a mocap body, or with friction on a driven body with the stick equalities of
    ``stick_candidates``. Returns the height field's lowest point (mm) and the number of surface spheres."""
    import mujoco as mj

    x, y, z = indenter.grid(COLLISION_SPACING_MM)
    z = np.where(np.isfinite(z), z, np.nanmin(z))
    hmin = float(z.min())
    span = max(float(z.max()) - hmin, 1e-3)
    hx, hy = indenter.half_size_mm
    mjspec.add_hfield(name="indenter", size=[float(units.mm_to_m(hx)), float(units.mm_to_m(hy)),
                                           float(units.mm_to_m(span)), float(units.mm_to_m(2.0))],
                      nrow=z.shape[0], ncol=z.shape[1], userdata=((z - hmin) / span).ravel().tolist())
    if friction > 0:
        # Friction acts on relative velocity, and a mocap body has none (it is teleported): the skin would
        # be held where it is, not dragged along. With friction the indenter is a heavy body on three
        # slide joints and a hinge whose positions are prescribed every step and whose velocity is the
        # commanded increment over the step (see step()).
        body = mjspec.worldbody.add_body(name="indenter")
        for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
            body.add_joint(type=mj.mjtJoint.mjJNT_SLIDE, axis=list(axis), name=f"indenter_{'xyz'[axis.index(1)]}")
        body.add_joint(type=mj.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], name="indenter_yaw")
        body.mass = DRIVEN_INDENTER_MASS_KG
        body.inertia = [DRIVEN_INDENTER_MASS_KG * 1e-4] * 3
        body.explicitinertial = True
        # stick: two (inactive) joint equalities per free outer vertex, x and y, switched on by the Coulomb
        # check (twin.stick) while the vertex sticks to the indenter at the point where it touched
        for n in stick_candidates:
            for ax in "xy":
                e = mjspec.add_equality()
                e.type, e.objtype = mj.mjtEq.mjEQ_JOINT, mj.mjtObj.mjOBJ_JOINT
                e.name1, e.name2 = f"v{n}{ax}", f"indenter_{ax}"
                e.active = False
                e.data[1] = 1.0       # q_vertex = c0 + 1 * q_indenter (c0: the anchor, set by twin.stick)
                e.solref = [STICK_TIMECONST_STEPS * dt, STICK_DAMPRATIO]
                e.solimp = CONTACT_SOLIMP
    else:
        body = mjspec.worldbody.add_body(name="indenter", mocap=True)
    g = body.add_geom(type=mj.mjtGeom.mjGEOM_HFIELD, hfieldname="indenter",
                      pos=[0, 0, float(units.mm_to_m(hmin))])
    g.contype, g.conaffinity, g.condim, g.priority = 1, 2, _CONDIM, 1
    g.friction = [friction, 0.005, 0.0001]
    g.solref = [CONTACT_TIMECONST_STEPS * dt, CONTACT_DAMPRATIO]
    g.solimp = CONTACT_SOLIMP
    n_surface_spheres = 0
    if spec.face_contact:
        cell = spec.core_mm or spec.fine_mm
        sag = contact.SAG_TOL_MM if spec.sag_tol_mm is None else float(spec.sag_tol_mm)
        centres, radii = contact.surface_spheres(indenter, skin_cell_mm=cell, with_radii=True, sag_tol_mm=sag)
        n_surface_spheres = int(len(centres))
        for c, r_s in zip(units.mm_to_m(centres), units.mm_to_m(radii)):
            gs = body.add_geom(type=mj.mjtGeom.mjGEOM_SPHERE, size=[float(r_s), 0, 0], pos=c.tolist())
            gs.contype, gs.conaffinity, gs.condim, gs.priority = _BIT_SPHERES, _BIT_FACES, _CONDIM, 1
            gs.friction = [friction, 0.005, 0.0001]
            gs.solref = [CONTACT_TIMECONST_STEPS * dt, CONTACT_DAMPRATIO]
            gs.solimp = CONTACT_SOLIMP
            gs.mass, gs.group = 0.0, 3
    return hmin, n_surface_spheres


def _stick_indices(model, free: np.ndarray, stick_candidates: np.ndarray, ks: np.ndarray, friction: float) -> dict:
    """With friction: the driven indenter's joint addresses and, per outer vertex that can stick, its index among
    the free vertices, its shear stiffness and its two equalities (x, y); empty without friction."""
    ind_qadr = ind_dadr = None
    stick_nodes = stick_free = np.zeros(0, np.int64)
    stick_eq = np.zeros((0, 2), np.int64)
    stick_k = np.zeros(0)
    if friction > 0:
        jid = [model.joint(f"indenter_{n}").id for n in ("x", "y", "z", "yaw")]
        ind_qadr = model.jnt_qposadr[jid].copy()
        ind_dadr = model.jnt_dofadr[jid].copy()
        free_pos = {int(n): i for i, n in enumerate(free)}
        stick_nodes = stick_candidates
        stick_free = np.array([free_pos[int(n)] for n in stick_nodes], dtype=np.int64)
        stick_k = ks[stick_nodes]
        stick_eq = np.arange(2 * len(stick_nodes)).reshape(-1, 2)   # the model's only equalities: (x, y) per vertex
        assert model.neq == stick_eq.size
    return {"_ind_qadr": ind_qadr, "_ind_dadr": ind_dadr, "_stick_nodes": stick_nodes, "_stick_free": stick_free,
            "_stick_eq": stick_eq, "_stick_k": stick_k}


def _column_indices(model, mesh: _Mesh, X_m: np.ndarray, free: np.ndarray, is_top: np.ndarray) -> dict:
    """For the direct solves: the contact geom of each free outer vertex, the rest world positions (m) of the free
    vertices, and the outer-surface and window vertex of each vertex's column (the mesh is a tensor grid: columns
    share x-y)."""
    top_geom = {}
    for n in free[is_top[free]]:
        top_geom[model.body(f"v{n}").geomadr[0]] = n
    key = np.round(mesh.nodes_mm[:, :2], 6)
    _, col = np.unique(key, axis=0, return_inverse=True)
    col = col.ravel()
    top_of = np.full(col.max() + 1, -1)
    top_of[col[mesh.top]] = mesh.top
    bottom_of = np.full(col.max() + 1, -1)
    zmin = np.full(col.max() + 1, np.inf)
    for i, (c, z) in enumerate(zip(col, mesh.nodes_mm[:, 2])):
        if z < zmin[c]:
            zmin[c], bottom_of[c] = z, i
    is_free_top = np.zeros(len(X_m), bool)
    is_free_top[free] = is_top[free]
    return {"_top_geom": top_geom, "_rest_free_m": X_m[free], "_col_top": top_of[col], "_col_bottom": bottom_of[col],
            "_is_free_top": is_free_top}


# ----- nodal volumetric stiffness (twin.volumetric) ------------------------------------------

def flex_elasticity(spec: MeshSpec, mat) -> tuple[float, float]:
    """Young's modulus (Pa) and Poisson ratio the flex gets for a material: all of it, or with
    ``MeshSpec.volumetric == "nodal"`` its shear modulus at ν = ``volumetric.NU_DEV`` (the rest of the
    bulk stiffness goes to the nodal term, :mod:`twin.volumetric`)."""
    E, nu = units.mpa_to_pa(mat.youngs_modulus_mpa), mat.poisson_ratio
    if spec.volumetric == "nodal" and nu > volumetric.NU_DEV:
        return volumetric.bulk_split(E, nu, volumetric.NU_DEV)[0], volumetric.NU_DEV
    return E, nu


def volumetric_solver_options(spec: MeshSpec, o) -> None:
    """Nodal volumetric forces need the constraint solve converged tighter: at tolerance 1e-6 CG stops
    early and the frictionless contact of the unlocked gel chatters (sphere R 10 mm, 1 mm, ν = 0.49:
    force 0-0.27 N step to step); at ``volumetric.SOLVER_TOLERANCE`` it holds 0.193-0.194 N, as Newton
    does at twice the time a step."""
    if spec.volumetric == "nodal":
        o.tolerance = volumetric.SOLVER_TOLERANCE
        o.iterations = volumetric.SOLVER_ITERATIONS


def friction_solver_options(friction: float, o) -> None:
    """The stick constraints need the constraint solve converged tighter: at tolerance 1e-6 CG stops early,
    leaves the stuck skin vibrating (0.03 mm a step) and a press never settles. At ``STICK_SOLVER_TOLERANCE``
    CG reproduces Newton's solution (sphere R 10 mm pressed 1.5 mm, slid 0.3 mm at μ = 1: the skin under the
    tip follows 0.931 of the slide and holds 0.934, Q/P 0.572 vs Newton's 0.574, 143 + 159 press and slide
    steps with both) in 2.4x less time (9.4 s vs 22.9 s); at 1e-8 it took 428 steps to settle the press.
    Measured on a σ² = 10 Gaussian pressed 5 mm at μ = 1 (the settle undamped): CG at 1e-10 averaged 383
    iterations a step (45 of 228 steps at the 1000 cap); 1e-9: 315 iterations but 239 steps, no faster; 1e-8:
    1327 steps (1e-8 only while approaching: the approach 2.0 s instead of 2.1); a 200-iteration cap: 1341 steps; Newton at 1e-10:
    4.6 iterations a step but the same 60 ms a step. The frictional press's cost is steps x CG iterations.
    A step's iterations grow with the ties switched on (~100 with ~20 stuck vertices, 500-1000 with 130-300),
    and no solver setting measured lowers them (σ² = 10, 5 mm, default mesh, 4.7 s): ``ls_tolerance`` 0.1 4.7 s,
    ``ls_iterations`` 10 4.6 s, the dense Jacobian 68 s; softer ties do not either and move the markers (tie
    ``solimp`` 0.95-0.99: 4.8 s, markers 0.058 mm off; 0.9-0.95: 4.6 s, 0.18 mm; time constant 8 steps: 5.5 s)."""
    if friction > 0:
        o.tolerance = min(o.tolerance, STICK_SOLVER_TOLERANCE)
        o.iterations = max(o.iterations, STICK_SOLVER_ITERATIONS)


def settle_solver_options(tolerance: float, iterations: int) -> tuple[float, int]:
    """CG's tolerance and iteration cap while a press settles: at least ``SETTLE_SOLVER_TOLERANCE``, with
    friction or without (with friction the whole press runs at ``STICK_SOLVER_TOLERANCE``). At the frictionless
    motion's 1e-6 CG stops after ~4 iterations and the contact forces change from step to step: a sphere
    (R 10 mm) pressed on the axis of the axis contact mesh, which is its own mirror image, moved the centre
    marker 0-0.018 mm sideways and mirrored markers' displacements differed by up to 0.035 mm, wandering from
    step to step after the settle (0.0244 / 0.049 mm at 2 mm in the physics benchmark's depth series).
    Settled at 1e-8 the same series (0.25-3 mm) is symmetric to 0.0019 / 0.0038 mm at 2.1-2.9 s a press
    (1e-6: 2.0-3.9 s), and the sine grid's 15 presses (hexagon127, face contact, 5 mm) keep their verdicts
    at 6.7-16.2 s a press (π/5 and 2π/5 at yaw 0: 9.4 / 16.2 s against 9.8 / 14.6 s). At 1e-10 the sines
    took 13-20 s, and π/5 at 5 mm on the default mesh (vertex contact) did not settle in 400 undamped
    steps and ended with a vertex 0.16 mm inside the sine
    (1e-8: 0.007 mm). The motion between settles stays at 1e-6."""
    return min(tolerance, SETTLE_SOLVER_TOLERANCE), max(iterations, STICK_SOLVER_ITERATIONS)


def volumetric_mass_factor(spec: MeshSpec) -> float:
    """Vertex mass multiplier with nodal volumetric stiffness (``volumetric.MASS_FACTOR``), else 1."""
    return volumetric.MASS_FACTOR if spec.volumetric == "nodal" else 1.0


def build_volumetric(design: SensorDesign, mesh: _Mesh, spec: MeshSpec, X_m: np.ndarray, free: np.ndarray,
                     qadr: np.ndarray):
    """The nodal volumetric energy of the materials stiffer in bulk than ``volumetric.NU_DEV`` and where
    its forces go (the free vertices' slide DOFs ``qadr``); None unless ``MeshSpec.volumetric == "nodal"``."""
    mode = spec.volumetric
    if mode == "element":
        return None
    if mode != "nodal":
        raise PhysicsError(f"MeshSpec.volumetric {mode!r}: 'element' or 'nodal'")
    m, d = mesh, design
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
    free_pos[free] = np.arange(len(free))
    keep = free_pos[nv.pair_node] >= 0
    return {"nv": nv, "pairs": np.nonzero(keep)[0], "pair_dof": qadr[free_pos[nv.pair_node[keep]]]}
