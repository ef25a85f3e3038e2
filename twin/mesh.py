"""The skin module's tetrahedral mesh, its resolution, and where the markers' pins sit in it.

What :class:`twin.physics.SkinSim` simulates, before any MuJoCo object exists: the rest geometry of the gel +
skin disc (sensor frame, mm) and the pins embedded in its skin elements.

* One tetrahedral mesh of the disc of radius ``design.gel.radius_mm`` from the outer skin surface
  (sensor z = 0) down to the acrylic window (z = -(T + G)). Vertices lie on a tensor grid: x-y
  spacing ``MeshSpec.fine_mm`` inside ``|x|, |y| <= fine_half_mm`` (where contact happens), growing
  geometrically to the rim; z levels 0, -T (skin) and ``gel_levels_mm`` below the skin, then the
  window. Each hexahedral cell is split into 6 Kuhn tetrahedra (conforming; ``MeshSpec.mirrored_split``
  mirrors the split in alternate cells for a mesh symmetric about the axis). Cells whose centre
  lies outside the radius are dropped, so the clamped rim is a staircase approximating the circle.
  Vertices on the bottom (bonded to the acrylic) and on the lateral boundary (clamped by the rigid
  mount) are pinned.
* Domed designs: the mesh is shifted vertically by ``design.dome_z_mm`` (fully in the skin layer,
  tapering linearly to zero at the window), so the skin is the dome of constant vertical
  thickness T; rest markers are exact.
* Rounded edge (``MeshSpec.edge_drop_mm`` > 0): the module's skin need not meet its rigid mount flush with its top.
  Beyond ``edge_start_mm`` the skin rounds down (a smoothstep in r, level with the flat top where it starts) to the
  innermost clamped outer vertex, and every clamped outer vertex sits on the mount ``edge_drop_mm`` below the skin's
  top; the shift is full in the skin layer and tapers linearly to zero at the window, like the dome. The x-y
  spacing is ``edge_mm`` over the edge, and even steps of at most ``fine_mm · growth`` lead to it. Every marker's
  skin cell must lie on the flat top (``EDGE_MARKER_TOL_MM``), so the rest markers are those of the design. A wide
  indenter pressed that deep then clears the mount (``rim_overlap_mm`` 0) instead of reaching below it.
* Roller rim (``MeshSpec.rim = "roller"``): the lateral boundary above the window is held in x and y by the
  mount's wall but slides freely along it in z (each such vertex keeps its three slide joints, x and y limited
  to their rest values), instead of being clamped. It stands for a skin whose mount lies below its top: an
  indenter wider than the module pressed deep carries the skin's edge down with it rather than meeting a rigid
  mount flush with the skin (``rim_overlap_mm`` 0). The bottom stays bonded to the window. Those vertices are
  free, so the penetration check and face contact include the faces at the rim.
* The outer faces that take part in face contact (:func:`_face_contact_faces`): those without a
  clamped vertex.
* Pins: each marker's pin base is the skin-underside point at the rest marker's x-y, embedded with
  barycentric weights in the skin tetrahedron that contains it. The pin is stiff (E_pin ≫ E_gel)
  and rotates with the skin it grows from: ``axis = R · (0, 0, -1)`` with ``R`` the polar rotation
  of the volume-averaged deformation gradient of the skin elements within one fine cell of the
  base; ``marker = base + H · axis`` (:func:`embed_pins`, :func:`pin_markers`). At rest this is
  exactly ``design.rest_markers_mm()``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.design import SensorDesign
from pipeline.errors import UserError

__all__ = ["MeshSpec", "AXIS_CONTACT_MESH", "SINE_CONTACT_MESH", "NAMED_MESHES", "auto_mesh", "PhysicsError", "build_mesh",
           "PinEmbedding", "embed_pins", "pin_markers"]

EDGE_MARKER_TOL_MM = 0.02         # how far a marker's skin cell may sit on the rounded edge (MeshSpec.edge_drop_mm)
RIMS = ("clamped", "roller")       # MeshSpec.rim: how the mount holds the lateral boundary (module notes)
PIN_ROTATION_RADIUS_FACTOR = 1.0  # pin rotation averaged over skin elements within 1 cell of its base


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
    sag_tol_mm: float | None = None   # face contact: how far a skin face may sag into a convex part of the indenter
                                  # before spheres are placed there (twin.contact; None: its SAG_TOL_MM, 0.02 mm).
                                  # The sines' crests crossing the cells obliquely (yaw 240) held faces 0.05-0.06 mm
                                  # inside at 0.02 mm and 0.03-0.04 mm at 0.01 mm
    edge_drop_mm: float = 0.0     # > 0: the skin rounds down over its edge to a mount this far below its top (module
                                  # notes); 0: the mount is flush with the skin (the mesh is unchanged)
    edge_start_mm: float = 16.5   # radius where the rounded edge begins: beyond every hexagon pattern's marker cells
    edge_mm: float = 1.5          # x-y spacing from edge_start_mm out to the rim, over the edge
    rim: str = "clamped"          # "roller": the lateral boundary is held in x and y and slides freely in z (module
                                  # notes). Not the default, nor the sine experiment's: on the sine grid's 15 presses
                                  # (hexagon127, face contact, 5 mm) 9 are valid against 6 clamped, but at 2π/15
                                  # (yaw 0, 120) the crests press rim vertices that cannot move sideways 0.87 /
                                  # 1.44 mm inside. With the limits at MuJoCo's default softness (the rim ~1 mm free
                                  # sideways) 11 of 15 were valid. σ² = 10 at 5 mm on AXIS_CONTACT_MESH: markers
                                  # <= 0.032 mm (mean 0.016) from the clamped rim's


# Mesh for indenters with one sharp feature on the sensor axis (Gaussians, spheres): 0.5 mm cells within 3 mm
# of the axis plus face contact. Measured at 5 mm (hexagon127 and its skin variants): every Gaussian from
# sigma2 = 5/3 to 50 within 0.012-0.026 mm of the indenter at face level, apex vertex within 0.01 mm of the
# tip for sigma2 >= 10 (0.18 mm beyond the 0.33 mm-radius sigma2 = 5/3 tip), 13-16 s a press instead of 1.3-1.4 s.
# The cells are split mirrored (mirrored_split): with every cell cut along the same diagonal a press on the axis
# moved the centre marker 0.24-0.26 mm sideways and mirrored markers' displacements differed by up to 0.37 mm
# (sigma2 = 10 and 5/3 at 5 mm); mirrored, 0.027-0.028 mm and 0.040-0.045 mm, equally valid.
AXIS_CONTACT_MESH = MeshSpec(core_mm=0.5, core_half_mm=3.0, face_contact=True, mirrored_split=True)

# Mesh for indenters whose crests run across the whole module (the sine plates): face contact, 1.5 mm cells out to
# 18 mm (beyond 9 mm the default mesh grows to 3.4 mm cells, whose faces chord through a plate rounded off there),
# and spheres wherever a face would sag 0.01 mm into a crest (the default 0.02 mm held faces 0.05-0.06 mm inside
# crests crossing the cells obliquely). Measured on the sine experiment's 15 presses (hexagon127, 5 mm, mu = 1, its
# plate rounded off beyond 13.5 mm): all valid, at most 0.043 mm inside, 10-121 s a press.
SINE_CONTACT_MESH = MeshSpec(face_contact=True, fine_half_mm=18.0, sag_tol_mm=0.01)

# The meshes offered by name (``simulate --mesh``), each measured against a locking-free refinement by
# ``bench physics`` (docs/CONTACT_MODEL.md); "face" is the default mesh with face contact (the terrain taps' and
# the tracking experiment's)
NAMED_MESHES = {"default": MeshSpec(), "face": MeshSpec(face_contact=True), "axis": AXIS_CONTACT_MESH,
                "sine": SINE_CONTACT_MESH}

# ``simulate --mesh auto`` (its default): the mesh the experiments press each indenter on, where every press was
# measured valid. The 1.5 mm default mesh with vertex contact leaves faces 0.24 mm inside a sigma2 = 10 Gaussian at
# 5 mm and a vertex near the apex of circular217_dome's dome 0.82 mm inside a sigma2 = 5 one at 2.5 mm; on the
# axis contact mesh both are within 0.01 mm (2026-11-29).
_AUTO_ON_AXIS = {"gaussian": "axis", "sphere": "axis", "sine": "sine"}


def auto_mesh(indenter_name: str, motion: str = "press") -> str:
    """The name of the mesh ``simulate --mesh auto`` presses ``indenter_name`` on: the axis contact mesh for a
    Gaussian or sphere pressed on the axis, the sine contact mesh for a sine plate, and the default mesh with face
    contact for anything else or any motion that leaves the axis (letters, terrain patches, slides)."""
    if motion == "press" and indenter_name in _AUTO_ON_AXIS:
        return _AUTO_ON_AXIS[indenter_name]
    return "face"


def _axis(fine_mm: float, fine_half_mm: float, growth: float, radius_mm: float,
          core_mm: float | None = None, core_half_mm: float = 0.0,
          edge_start_mm: float | None = None, edge_mm: float = 1.5) -> np.ndarray:
    pos = [0.0]
    if core_mm is not None and core_mm < fine_mm and core_half_mm > 0:
        pos = list(np.arange(0, int(math.floor(core_half_mm / core_mm + 1e-9)) + 1) * core_mm)
    while pos[-1] + fine_mm <= fine_half_mm + 1e-9:
        pos.append(pos[-1] + fine_mm)
    step = fine_mm
    while pos[-1] < radius_mm - 1e-9:
        if edge_start_mm is not None:
            # even steps of at most fine_mm * growth out to where the edge starts, then edge_mm over the edge:
            # no thin cell against a wide one, whose stiffness ratio MuJoCo's M + K solve does not converge on
            n = max(1, math.ceil((edge_start_mm - pos[-1]) / (fine_mm * growth) - 1e-9))
            pos += list(pos[-1] + (edge_start_mm - pos[-1]) * np.arange(1, n + 1) / n)
            while pos[-1] < radius_mm - 1e-9:
                pos.append(pos[-1] + edge_mm)
            break
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
    roller: np.ndarray | None = None   # (V,) bool: free in z only (MeshSpec.rim = "roller"), else None


def build_mesh(design: SensorDesign, spec: MeshSpec) -> _Mesh:
    """Tetrahedral mesh of the skin + gel disc (see module notes). Rest positions in the sensor frame."""
    if spec.rim not in RIMS:
        raise PhysicsError(f"MeshSpec.rim must be one of {', '.join(RIMS)}, got {spec.rim!r}")
    T, G, R = design.skin.thickness_mm, design.optics.gel_thickness_mm, design.gel.radius_mm
    edge = spec.edge_drop_mm > 0
    ax = _axis(spec.fine_mm, spec.fine_half_mm, spec.growth, R, spec.core_mm, spec.core_half_mm,
               spec.edge_start_mm if edge else None, spec.edge_mm)
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
    lateral = ~interior[I[used], J[used]] & (K[used] > 0)
    roller = lateral if spec.rim == "roller" else None
    pinned = (K[used] == 0) | (lateral & (spec.rim == "clamped"))
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
    if edge:
        shift = _edge_z_mm(nodes, pinned, top, spec, T, G)
        # every marker's pin stands in a skin cell of the flat top (within EDGE_MARKER_TOL_MM), so the rest
        # markers stay where the design puts them
        xy = design.rest_markers_mm()[:, :2]
        i = np.clip(np.searchsorted(ax, xy[:, 0]), 1, nx - 1)
        j = np.clip(np.searchsorted(ax, xy[:, 1]), 1, nx - 1)
        lift = np.zeros((nx, nx))
        lift[used_xy] = np.abs(shift[gid[:, :, nz - 1][used_xy]])
        cell = np.max([lift[i - a, j - b] for a in (0, 1) for b in (0, 1)], axis=0)
        if np.any(cell > EDGE_MARKER_TOL_MM):
            raise PhysicsError(f"design {design.name}: markers out to r = {design.pattern_radius_mm():.2f} mm lie in "
                               f"skin cells on the rounded edge (edge_start_mm = {spec.edge_start_mm:g})")
        nodes[:, 2] += shift
    return _Mesh(nodes, tets_skin, tets_gel, pinned, top, top_faces, roller)


def _edge_z_mm(nodes: np.ndarray, pinned: np.ndarray, top: np.ndarray, spec: MeshSpec, T: float, G: float) -> np.ndarray:
    """Vertical shift (V,) mm of the rounded edge: 0 inside ``edge_start_mm``, ``-edge_drop_mm`` from the innermost
    clamped outer vertex on (the mount's top), a smoothstep between (level with the flat top where it starts and
    with the mount where it ends); full in the skin layer, tapering linearly to 0 at the window."""
    r = np.hypot(nodes[:, 0], nodes[:, 1])
    r1 = float(r[top][pinned[top]].min())
    t = np.clip((r - spec.edge_start_mm) / (r1 - spec.edge_start_mm), 0.0, 1.0)
    zb = -(T + G)
    frac = np.clip((nodes[:, 2] - zb) / (-T - zb), 0.0, 1.0)
    return -spec.edge_drop_mm * t * t * (3.0 - 2.0 * t) * frac


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


@dataclass(frozen=True)
class PinEmbedding:
    """Where the pins sit in the skin mesh (:func:`embed_pins`): each base's skin tetrahedron and barycentric
    weights, and the skin tetrahedra whose volume-averaged deformation gradient rotates each pin."""

    pin_tet: np.ndarray      # (N, 4) mesh vertices of the tetrahedron holding each pin base
    pin_w: np.ndarray        # (N, 4) the base's barycentric weights in it
    rot_tets: np.ndarray     # (M, 4) skin tetrahedra that take part in some pin's rotation
    rot_Bi: np.ndarray       # (M, 3, 3) their rest Dm⁻¹
    rot_avg: object          # (N, M) sparse volume weights: pin i's mean deformation gradient
    rest_axis: np.ndarray    # (3,) the pin axis at rest (into the gel)


def embed_pins(design: SensorDesign, mesh: _Mesh, spec: MeshSpec) -> PinEmbedding:
    """Embed each marker's pin base in the skin mesh (see module notes)."""
    d, m = design, mesh
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
    pin_tet = m.tets_skin[k]                              # (N, 4)
    pin_w = bary[np.arange(len(k)), k]                    # (N, 4)
    # pin rotation: volume-weighted mean deformation gradient of the skin tetrahedra whose
    # centroids lie within PIN_ROTATION_RADIUS of the base (x-y), a symmetric neighbourhood
    from scipy.sparse import csr_matrix
    from scipy.spatial import cKDTree

    cent = X.mean(axis=1)
    rad = max(PIN_ROTATION_RADIUS_FACTOR * spec.fine_mm, d.pins.diameter_mm)
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
    return PinEmbedding(pin_tet, pin_w, m.tets_skin[used], Bi[used],
                        csr_matrix((vals, (rows, remap[cols])), shape=(len(base), len(used))),
                        np.array([0.0, 0.0, -1.0]))


def pin_markers(X: np.ndarray, pins: PinEmbedding, height_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Marker face centres (N, 3) mm and unit pin axes (N, 3) for mesh vertex positions ``X`` (V, 3)."""
    P = X[pins.pin_tet]                                             # (N, 4, 3)
    base = np.einsum("nk,nkj->nj", pins.pin_w, P)
    Q = X[pins.rot_tets]
    Ds = np.stack([Q[:, 1] - Q[:, 0], Q[:, 2] - Q[:, 0], Q[:, 3] - Q[:, 0]], axis=2)
    F = (pins.rot_avg @ (Ds @ pins.rot_Bi).reshape(len(Q), 9)).reshape(-1, 3, 3)
    U, _, Vt = np.linalg.svd(F)
    Rm = U @ Vt
    flip = np.linalg.det(Rm) < 0
    if np.any(flip):
        U[flip, :, -1] *= -1
        Rm = U @ Vt
    axis = Rm @ pins.rest_axis
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return base + height_mm * axis, axis
