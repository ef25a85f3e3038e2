"""MuJoCo skin model: compiles for every design, rest markers exact, contact fidelity, pins.

Each test states its tolerance; the model is run at the resolutions the twin uses. Over ~400 lines on
purpose: one file for everything that pins the skin model's physics (each test builds its own sim, so
splitting the file would only split the list).
"""

import numpy as np
import pytest

from pipeline.design import list_designs, load_design
from twin.indenters import make_indenter
from twin.physics import MeshSpec, PhysicsError, SkinSim, max_depth_mm
from twin import robot

pytestmark = pytest.mark.physics

COARSE = MeshSpec(fine_mm=2.5)
GAP_TOL_MM = 0.1           # the twin's conformity goal: skin within 0.1 mm of a touching indenter
PENETRATION_TOL_MM = 0.05  # contact spheres may sink this much into the height field (stiff contact)


def _press(design, ind, depth, mesh=MeshSpec()):
    sim = SkinSim(design, ind, mesh=mesh, friction=0.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(depth))
    assert sim.warnings() == {}
    return sim, stats, truth


@pytest.mark.parametrize("name", [n for n in list_designs() if not load_design(n).monocular])
def test_every_design_compiles_steps_and_has_exact_rest_markers(name):
    d = load_design(name)
    sim = SkinSim(d, make_indenter("flat"), mesh=COARSE, friction=0.0)
    xyz, axis = sim.markers()
    assert np.abs(xyz - d.rest_markers_mm()).max() < 1e-9
    assert np.allclose(axis, [0, 0, -1])
    sim.step(5)
    assert sim.warnings() == {}
    top = sim.skin_vertices_mm()
    assert np.allclose(top[:, 2], d.dome_z_mm(top[:, :2]), atol=1e-6)   # rest outer surface (flat or dome)
    xyz2, _ = sim.markers()
    assert np.abs(xyz2 - xyz).max() < 1e-6                               # nothing moves without contact


def test_flat_plate_force_between_layer_estimates():
    """Plate over the whole disc pressed δ = 0.5 mm into the gel (bonded bottom, clamped rim).

    Fully confined layer: F_c = M A δ / G with M = E (1-ν) / ((1+ν)(1-2ν)) = 17.1 E for ν = 0.49; the
    uniform confined field is admissible, so the FE force cannot exceed it (energy minimum). A
    free-slip layer would give E A δ / G = F_c / 17; the clamped rim and a skin 57x stiffer than the
    gel suppress most bulging, so we require F >= 0.4 F_c.
    """
    d = load_design("hexagon127")
    sim = SkinSim(d, make_indenter("flat"), mesh=MeshSpec(fine_mm=2.0), friction=0.0)
    sim.set_pose(0, 0, -0.1, 0)
    sim.move_to(0, 0, 0.5, 0)
    sim.settle()
    E, nu, G = d.gel.youngs_modulus_mpa, d.gel.poisson_ratio, d.optics.gel_thickness_mm
    M = E * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
    area = _mesh_area_mm2(sim)
    f_confined = M * area * 0.5 / G            # MPa * mm^2 = N
    f = sim.contact_force_n()
    assert 0.4 * f_confined <= f <= 1.02 * f_confined, (f, f_confined)
    assert sim.warnings() == {}


def _mesh_area_mm2(sim):
    v = sim.skin_vertices_mm()
    a, b, c = (v[sim.mesh.top_faces[:, k], :2] for k in range(3))
    u, w = b - a, c - a
    return float(0.5 * np.abs(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]).sum())


def test_wide_gaussian_skin_follows_indenter_and_pins_tilt_with_the_skin():
    d = load_design("hexagon127")
    sim, stats, truth = _press(d, make_indenter("gaussian", h_mm=5, sigma2_mm2=50), 5.0)
    assert stats.converged
    gap = sim.gap_mm()
    assert len(gap) > 50
    assert gap.max() <= GAP_TOL_MM and gap.min() >= -PENETRATION_TOL_MM
    # pins: tilted on the flank, upright at the apex, and aligned with the local skin normal
    xyz, axis = truth.marker_xyz_mm, truth.marker_axis
    rest = d.rest_markers_mm()
    r = np.hypot(rest[:, 0], rest[:, 1])
    tilt = np.degrees(np.arccos(np.clip(-axis[:, 2], -1, 1)))
    assert tilt[np.argmin(r)] < 1.0
    flank = (r > 5.0) & (r < 9.0)
    assert np.median(tilt[flank]) > 5.0
    normals = _vertex_normals(truth.skin_vertices_mm, truth.skin_faces)
    base = xyz - d.pins.height_mm * axis
    nearest = np.argmin(np.linalg.norm(truth.skin_vertices_mm[None, :, :2] - base[flank, None, :2], axis=2), axis=1)
    cosang = np.sum(-axis[flank] * normals[nearest], axis=1)
    assert np.median(np.degrees(np.arccos(np.clip(cosang, -1, 1)))) < 0.5 * np.median(tilt[flank])
    # pins lean outward: on the flank of the dimple the skin's inner normal tilts away from the axis, so each
    # pin's marker end lies further out than its base (measured: radial component of the axis 0.33-0.37)
    radial = rest[flank, :2] / r[flank, None]
    assert np.all(np.sum(axis[flank, :2] * radial, axis=1) > 0.1)


def _vertex_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    out = np.zeros_like(v)
    for k in range(3):
        np.add.at(out, f[:, k], n)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out * np.sign(out[:, 2:3])          # outward (+z)


def test_sine_valleys_keep_the_skin_out():
    """A convex-hull collider would flatten the valleys to the crest level; the height field must not."""
    d = load_design("hexagon127")
    w = 2 * np.pi / 15
    sim, _, truth = _press(d, make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=w), 4.0)
    v = truth.skin_vertices_mm
    near = lambda x0: v[np.argmin(np.hypot(v[:, 0] - x0, v[:, 1]))]
    crest, valley = near(np.pi / (2 * w)), near(-np.pi / (2 * w))
    assert crest[2] == pytest.approx(-4.0, abs=GAP_TOL_MM)
    # the indenter surface above the valley vertex is at +1 mm: the skin there is free (pulled in by
    # its neighbours, not pushed); a convex-hull collider would hold it at the crest level, -4 mm
    assert valley[2] > crest[2] + 0.3
    assert sim.indenter_z_at(valley[None, :2])[0] - valley[2] > 1.0


@pytest.mark.parametrize("omega,depth", [(2 * np.pi / 15, 4.0), (np.pi / 15, 5.0), (np.pi / 5, 5.0)])
def test_sine_flanks_do_not_penetrate(omega, depth):
    """No outer-skin vertex over the marker pattern ends inside the sine. ω = π/15 at 5 mm presses the
    crest across the clamped rim, where the skin is stiffest and the contact lags most: without the
    robot's lag limit (PENETRATION_LIMIT_MM) vertices tunnelled 3.6 mm. ω = π/5 has 57° flanks: with the
    vertex mass scale at 0.02 instead of 0.05 (softer contact) vertices slipped 1.7 mm through them."""
    d = load_design("hexagon127")
    sim, _, _ = _press(d, make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=omega), depth)
    assert sim.gap_mm().min() >= -PENETRATION_TOL_MM
    v = sim.skin_vertices_mm()
    over = np.hypot(v[:, 0], v[:, 1]) <= d.pattern_radius_mm()
    gap = sim.indenter_z_at(v[over, :2]) - v[over, 2]
    assert np.nanmin(gap) >= -PENETRATION_TOL_MM


def _det_f(sim, tets):
    def vol6(Y):
        return np.linalg.det(np.stack([Y[:, 1] - Y[:, 0], Y[:, 2] - Y[:, 0], Y[:, 3] - Y[:, 0]], axis=2))
    return vol6(sim.nodes_mm()[tets]) / vol6(sim.mesh.nodes_mm[tets])


SKIN_KEEP_FRACTION = 0.8     # the skin is not crushed: thickness >= 80 % of its incompressible membrane value
MARKER_DEPTH_REL_TOL = 0.15  # marker-to-outer-skin distance along the axis within 15 % of T + H


SHARP_MESH = MeshSpec(core_mm=0.75)   # a σ² = 5/3 tip pokes between 1.5 mm vertices; 0.75 mm core about the axis


@pytest.mark.parametrize("sigma2,depth,mesh", [
    (10.0, 5.0, MeshSpec()),
    pytest.param(5 / 3, 3.0, SHARP_MESH, marks=pytest.mark.xfail(
        reason="under the sharp tip (curvature radius 0.33 mm, ~1.2 N at 3 mm) the apex skin is compressed to "
               "0.56 T where membrane stretch explains 0.77 T; centre marker 2.07 mm below the outer skin instead "
               "of T + H = 2.5 mm (-17 %). Not a coarse-mesh artefact: refined about the axis the compression "
               "grows (0.5 mm cells 0.47-0.60 T, 0.25 mm cells 0.45-0.50 T; docs/CONTACT_MODEL.md), the contact "
               "pressure there exceeding the skin's modulus; the premise (no compression beyond membrane "
               "thinning) holds for blunt tips only", strict=True)),
])
def test_no_inverted_elements_and_skin_keeps_its_thickness(sigma2, depth, mesh):
    """Under the paper's presses no tetrahedron inverts (det F > 0); the skin at the apex is not crushed
    and the marker under the apex stays T + H (within 15 %) below the outer skin, as the pipeline's skin
    model assumes. (St Venant–Kirchhoff inverted 302 gel tetrahedra here, min det F = -1.15, skin 0.41 T.)

    The rim is clamped, so a 5 mm dimple stretches the skin (measured ≈ 18 % biaxially at the apex);
    an incompressible skin then thins to T / (λ1 λ2), not T. Compression through the thickness beyond
    that (crushing by the contact) is what must not happen: thickness >= 0.8 T / (λ1 λ2).
    """
    d = load_design("hexagon127")
    T, H = d.skin.thickness_mm, d.pins.height_mm
    sim, stats, truth = _press(d, make_indenter("gaussian", h_mm=5, sigma2_mm2=sigma2), depth, mesh)
    assert stats.converged
    for tets in (sim.mesh.tets_skin, sim.mesh.tets_gel):
        assert _det_f(sim, tets).min() > 0.0
    X, X0 = sim.nodes_mm(), sim.mesh.nodes_mm
    centre = np.hypot(X0[:, 0], X0[:, 1]) < 1e-6
    z_outer = X[centre & (np.abs(X0[:, 2]) < 1e-9), 2][0]
    z_under = X[centre & (np.abs(X0[:, 2] + T) < 1e-9), 2][0]
    rest = d.rest_markers_mm()
    i = np.argmin(np.hypot(rest[:, 0], rest[:, 1]))
    m, a = truth.marker_xyz_mm[i], truth.marker_axis[i]
    v = truth.skin_vertices_mm
    j = np.argmin(np.hypot(v[:, 0] - m[0], v[:, 1] - m[1]))
    dist = -np.dot(v[j] - m, a)                                       # along the pin axis, outward
    assert dist == pytest.approx(T + H, rel=MARKER_DEPTH_REL_TOL), dist
    skin = sim.mesh.tets_skin
    apex = np.hypot(*X0[skin].mean(axis=1)[:, :2].T) < 1.0
    Ds = lambda Y: np.stack([Y[:, 1] - Y[:, 0], Y[:, 2] - Y[:, 0], Y[:, 3] - Y[:, 0]], axis=2)
    F = (Ds(X[skin[apex]]) @ np.linalg.inv(Ds(X0[skin[apex]]))).mean(axis=0)
    lam = np.linalg.svd(F, compute_uv=False)                          # λ1 >= λ2 in-plane stretches first
    assert z_outer - z_under >= SKIN_KEEP_FRACTION * T / (lam[0] * lam[1]), (z_outer, z_under, lam)
    assert z_outer == pytest.approx(-depth, abs=GAP_TOL_MM + 0.05)   # apex under the tip (+ sphere slope error)


def test_sharp_tip_inverts_nothing_and_the_skin_reaches_the_tip():
    d = load_design("hexagon127")
    sim, stats, truth = _press(d, make_indenter("gaussian", h_mm=5, sigma2_mm2=5 / 3), 3.0, SHARP_MESH)
    assert stats.converged
    for tets in (sim.mesh.tets_skin, sim.mesh.tets_gel):
        assert _det_f(sim, tets).min() > 0.0
    v = truth.skin_vertices_mm
    assert v[np.argmin(np.hypot(v[:, 0], v[:, 1])), 2] == pytest.approx(-3.0, abs=GAP_TOL_MM + 0.05)


@pytest.mark.slow
def test_thicker_skin_conforms_less_to_a_sharp_gaussian():
    """Both skins are pushed to the tip at the apex (contact); the thick one bridges the flanks: its mean
    separation from the indenter within 2.5 mm of the axis is larger (by > 0.05 mm)."""
    ind = make_indenter("gaussian", h_mm=5, sigma2_mm2=5 / 3)
    sep = {}
    for name in ("hexagon127_skin050", "hexagon127_skin150"):
        sim, _, truth = _press(load_design(name), ind, 3.0, SHARP_MESH)
        v = truth.skin_vertices_mm
        near = np.hypot(v[:, 0], v[:, 1]) < 2.5
        sep[name] = float(np.mean(np.abs(sim.indenter_z_at(v[near, :2]) - v[near, 2])))
    assert sep["hexagon127_skin050"] < sep["hexagon127_skin150"] - 0.05, sep


def test_mujoco_arena_grows_with_the_square_of_the_mesh(monkeypatch):
    """MuJoCo's arena is sized from the mesh (``twin.model.arena_bytes``): its peak use per step grows with the
    square of the node count, and a fixed 256 MB stopped the 0.75 mm mesh (20,770 nodes) in mj_collision. With
    the floor taken away, the per-node² size alone holds a 1 mm sphere press on a mesh refined over the whole
    pattern with two skin layers (4,869 nodes, ~25 MB used), with room to spare."""
    from twin import model as _model

    monkeypatch.setattr(_model, "ARENA_MIN_BYTES", 0)
    spec = MeshSpec(fine_mm=1.5, fine_half_mm=16.0, skin_layers=2, gel_levels_mm=(0.75, 1.5, 2.5, 4.0, 6.0))
    sim = SkinSim(load_design("hexagon127"), make_indenter("sphere", radius_mm=10.0), mesh=spec, friction=0.0)
    assert sim.model.narena == pytest.approx(_model.ARENA_BYTES_PER_NODE2 * len(sim.mesh.nodes_mm) ** 2, rel=1e-3)
    assert sim.model.narena < _model.arena_bytes(10_000) == _model.ARENA_BYTES_PER_NODE2 * 10_000 ** 2
    sim.set_pose(0.0, 0.0, 1.0, 0.0)
    sim.step(3)
    assert sim.data.ncon > 0
    assert sim.data.maxuse_arena <= 0.6 * sim.model.narena


def test_depth_limit_is_enforced():
    d = load_design("hexagon127")
    sim = SkinSim(d, make_indenter("flat"), mesh=COARSE, friction=0.0)
    with pytest.raises(PhysicsError, match="exceeds"):
        robot.execute(sim, robot.press_motion(max_depth_mm(d) + 0.5))


SETTLE_REF_TOL_MM = 0.03   # a mode decaying 1 %/step that drifted < 5e-3 mm between 10-step means is < 0.03 mm out


def test_settled_markers_match_a_long_run_reference():
    """The settle criterion stops within SETTLE_REF_TOL_MM of the markers after 300 further steps."""
    d = load_design("hexagon127")
    sim, stats, truth = _press(d, make_indenter("gaussian", h_mm=5, sigma2_mm2=10), 3.0, COARSE)
    assert stats.converged
    sim.step(300)
    ref, _ = sim.markers()
    assert np.linalg.norm(truth.marker_xyz_mm - ref, axis=1).max() < SETTLE_REF_TOL_MM
    assert sim.warnings() == {}


# ----- direct quasi-static solves (SkinSim.solve_at, the default in robot.execute) -----------------
DIRECT_TOL_MM = SETTLE_REF_TOL_MM  # direct vs followed: each settle stops within 0.03 mm of the equilibrium (test
                                  # above); measured 0.004 (σ² = 10, 5 mm) to 0.013 mm (σ² = 50, frames at 2 and 4 mm)


@pytest.mark.parametrize("sigma2,n_frames", [(10.0, 1), (50.0, 2)])
def test_direct_solve_reaches_the_followed_paths_equilibrium(sigma2, n_frames):
    """Frictionless + hyperelastic: the equilibrium depends on the pose only. The direct solve is
    accepted on wide Gaussians and its markers and skin agree with the followed path's within
    DIRECT_TOL_MM, in fewer physics steps."""
    d = load_design("hexagon127")
    ind = make_indenter("gaussian", h_mm=5, sigma2_mm2=sigma2)
    runs = {}
    for direct in (True, False):
        # the twin's mesh (on the 2.5 mm test mesh the σ² = 10 jump is rejected)
        sim = SkinSim(d, ind, friction=0.0)
        runs[direct] = (robot.execute(sim, robot.press_motion(4.0, n_frames=n_frames), direct=direct), sim)
        assert sim.warnings() == {}
    (fast, sim_f), (slow, sim_s) = runs[True], runs[False]
    assert all(s.direct for _, s, _ in fast) and not any(s.direct for _, s, _ in slow)
    assert sim_f.direct_solves == n_frames and sim_f.direct_rejections == 0
    for (_, _, a), (_, _, b) in zip(fast, slow):
        assert np.abs(a.marker_xyz_mm - b.marker_xyz_mm).max() < DIRECT_TOL_MM
        assert np.abs(a.skin_vertices_mm - b.skin_vertices_mm).max() < DIRECT_TOL_MM
    assert sim_f.steps_taken < 0.6 * sim_s.steps_taken
    assert sim_f.gap_mm().max() <= GAP_TOL_MM and sim_f.gap_mm().min() >= -PENETRATION_TOL_MM


def test_direct_solve_is_rejected_and_undone_where_vertices_would_tunnel():
    """A sine pressed 5 mm across the clamped rim: jumping there pushes vertices through the flanks
    (1.9 mm measured), so solve_at must reject it, restore the state bit for bit, and the motion
    then follows the path (same result as direct=False)."""
    d = load_design("hexagon127")
    ind = make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=np.pi / 15)
    sim = SkinSim(d, ind, mesh=COARSE, friction=0.0)
    q0, v0, pose0, t0 = sim.data.qpos.copy(), sim.data.qvel.copy(), sim.pose, sim.data.time
    assert sim.solve_at(0.0, 0.0, 5.0, 0.0) is None
    assert sim.direct_rejections == 1 and sim.direct_wasted_steps > 0
    assert np.array_equal(sim.data.qpos, q0) and np.array_equal(sim.data.qvel, v0)
    assert sim.pose == pose0 and sim.data.time == t0
    assert np.all(sim.model.dof_damping == 0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(5.0))
    assert not stats.direct
    sim2 = SkinSim(d, ind, mesh=COARSE, friction=0.0)
    (_, _, ref), = robot.execute(sim2, robot.press_motion(5.0), direct=False)
    assert np.abs(truth.marker_xyz_mm - ref.marker_xyz_mm).max() < DIRECT_TOL_MM
    assert sim.outer_penetration_mm() <= PENETRATION_TOL_MM


def test_direct_solve_refuses_friction():
    """With friction the equilibrium depends on the path: solve_at declines, the path is followed."""
    d = load_design("hexagon127")
    sim = SkinSim(d, make_indenter("gaussian", h_mm=5, sigma2_mm2=50), mesh=COARSE, friction=0.5)
    assert sim.solve_at(0.0, 0.0, 1.0, 0.0) is None
    assert sim.steps_taken == 0


def test_friction_comes_from_the_design_unless_given():
    """The coefficient a press uses is the design's ``[twin] friction`` (default 1), overridden by the indenter's
    own (its material) and by the caller's; a frictional model carries the x-y stick ties of every free outer
    vertex, a frictionless one none."""
    d = load_design("hexagon127")
    ind = make_indenter("gaussian", h_mm=5, sigma2_mm2=50)
    rough = SkinSim(d, ind, mesh=COARSE)
    assert rough.friction == 1.0 and rough.model.neq == 2 * int(np.count_nonzero(rough._is_free_top))
    assert SkinSim(d.with_overrides({"twin.friction": 0.7}), ind, mesh=COARSE).friction == 0.7
    plain = SkinSim(d.with_overrides({"twin.friction": 0.7}), ind, mesh=COARSE, friction=0.0)
    assert plain.friction == 0.0 and plain.model.neq == 0
    with pytest.raises(PhysicsError, match="coefficient"):
        SkinSim(d, ind, mesh=COARSE, friction=-0.1)
    resin = make_indenter("gaussian", h_mm=5, sigma2_mm2=50, friction=0.4)
    assert SkinSim(d, resin, mesh=COARSE).friction == 0.4
    assert SkinSim(d.with_overrides({"twin.friction": 0.7}), resin, mesh=COARSE).friction == 0.4
    smooth = SkinSim(d, make_indenter("gaussian", h_mm=5, sigma2_mm2=50, friction=0.0), mesh=COARSE)
    assert smooth.friction == 0.0 and smooth.model.neq == 0
    assert SkinSim(d, resin, mesh=COARSE, friction=0.9).friction == 0.9


def test_model_cache_gives_the_same_physics():
    """A second sim of the same design/indenter/mesh copies the compiled model: identical results, and
    a sim with different parameters is not served from the cache."""
    d = load_design("hexagon127")
    ind = make_indenter("gaussian", h_mm=5, sigma2_mm2=20)
    out = []
    for _ in range(2):
        sim = SkinSim(d, ind, mesh=COARSE, friction=0.0)
        (_, _, t), = robot.execute(sim, robot.press_motion(2.0))
        out.append((sim.model_from_cache, t.marker_xyz_mm))
    assert out[1][0] and np.array_equal(out[0][1], out[1][1])
    assert not SkinSim(d, make_indenter("gaussian", h_mm=5, sigma2_mm2=21), mesh=COARSE, friction=0.0).model_from_cache


# ----- mesh symmetry and contact mechanics (bench physics has the full comparison) ---------------------------

def test_mirrored_split_is_conforming_and_its_own_mirror_image():
    """Every interior face shared by exactly two tetrahedra, none degenerate, and the tetrahedra map onto
    themselves under x -> -x and y -> -y (the plain Kuhn split does not)."""
    from twin.mesh import build_mesh

    d = load_design("hexagon127")
    for mirrored in (True, False):
        m = build_mesh(d, MeshSpec(mirrored_split=mirrored))
        T = np.vstack([m.tets_skin, m.tets_gel])
        X = m.nodes_mm[T]
        vol6 = np.linalg.det(np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2))
        assert np.abs(vol6).min() > 1e-9
        F = np.sort(np.vstack([T[:, [0, 1, 2]], T[:, [0, 1, 3]], T[:, [0, 2, 3]], T[:, [1, 2, 3]]]), axis=1)
        assert set(np.unique(np.unique(F, axis=0, return_counts=True)[1])) == {1, 2}
        idx = {tuple(p): i for i, p in enumerate(np.round(m.nodes_mm, 6))}
        tets = {tuple(sorted(t)) for t in T.tolist()}
        for sx, sy in ((-1, 1), (1, -1)):
            mir = np.array([idx[(sx * p[0] + 0.0, sy * p[1] + 0.0, p[2])] for p in np.round(m.nodes_mm, 6)])
            assert ({tuple(sorted(mir[t])) for t in T.tolist()} == tets) == mirrored


def test_symmetric_sphere_press_gives_a_symmetric_field_on_the_mirrored_split():
    """A sphere on the axis: with the mirrored split the centre marker stays put sideways and mirrored
    markers move as mirror images within 0.03 mm (settle noise 0.005-0.024 mm measured); on the plain split
    the centre marker moves 0.14-0.15 mm (why the mirrored split exists)."""
    from benchmarks.experiments.physics import _mirror_errors

    d = load_design("hexagon127")
    out = {}
    for mirrored in (True, False):
        sim = SkinSim(d, make_indenter("sphere", radius_mm=10.0), mesh=MeshSpec(mirrored_split=mirrored),
                      friction=0.0)
        (_, stats, truth), = robot.execute(sim, robot.press_motion(3.0))
        assert stats.converged and sim.warnings() == {}
        out[mirrored] = _mirror_errors(d, truth)
    assert out[True][0] <= 0.02 and out[True][1] <= 0.03, out
    assert out[False][0] > 0.1, out


def test_symmetric_sphere_press_is_symmetric_on_the_axis_contact_mesh():
    """The twin's mesh for indenters centred on the axis (0.5 mm core, mirrored split, face contact): the
    sphere pressed 3 mm moves the centre marker at most 0.02 mm sideways and mirrored markers agree within
    0.02 mm (measured 0.0016 / 0.0043 mm), in a valid frame (0.024 mm inside)."""
    from benchmarks.experiments.physics import _mirror_errors
    from twin.physics import AXIS_CONTACT_MESH

    d = load_design("hexagon127")
    sim = SkinSim(d, make_indenter("sphere", radius_mm=10.0), mesh=AXIS_CONTACT_MESH, friction=0.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(3.0))
    assert stats.converged and sim.warnings() == {} and truth.validity["valid"], truth.validity
    centre, mirror = _mirror_errors(d, truth)
    assert centre <= 0.02 and mirror <= 0.02, (centre, mirror)


def test_a_press_series_on_the_axis_contact_mesh_settles_symmetric(monkeypatch):
    """The sphere pressed 1, 1.5 and 2 mm in turn on the axis contact mesh: each settled field is symmetric to
    0.003 mm (measured at most 0.0006 mm sideways, mirrored markers 0.0012 mm apart), because a settle converges
    the constraint solve (``twin.model.settle_solver_options``). Settled at the frictionless motion's 1e-6,
    CG's early stop leaves the contact forces uneven from step to step and the same series is asymmetric by
    more than 0.005 mm (measured 0.0065 / 0.013 mm at 1 mm)."""
    from benchmarks.experiments.physics import _mirror_errors
    from twin import model
    from twin.physics import AXIS_CONTACT_MESH

    d = load_design("hexagon127")

    def series():
        sim = SkinSim(d, make_indenter("sphere", radius_mm=10.0), mesh=AXIS_CONTACT_MESH, friction=0.0)
        out, prev = [], -robot.APPROACH_MM
        for depth in (1.0, 1.5, 2.0):
            wps = (robot.Waypoint(0.0, 0.0, prev, capture=False), robot.Waypoint(0.0, 0.0, depth))
            (_, stats, truth), = robot.execute(sim, robot.Motion("sphere-press", wps))
            assert stats.converged and truth.validity["valid"], truth.validity
            out.append(_mirror_errors(d, truth))
            prev = depth
        return np.array(out)

    converged = series()
    assert converged.max() <= 0.003, converged
    monkeypatch.setattr(model, "settle_solver_options", lambda tolerance, iterations: (tolerance, iterations))
    assert series().max() > 0.005


def test_layer_solution_reduces_to_hertz_and_matches_the_published_coefficients():
    """Dimitriadis et al. 2002: the bonded correction is 1 at χ -> 0 (Hertz) and, for ν = 0.5, its
    polynomial is 1 + 1.133χ + 1.283χ² + 0.769χ³ + 0.0975χ⁴ (their eq. 12)."""
    from benchmarks.experiments.physics import dimitriadis_force_n

    E, R, d = 0.02, 10.0, 1.0
    hertz = 4 / 3 * E / (1 - 0.25) * np.sqrt(R) * d ** 1.5
    f, chi = dimitriadis_force_n(E, 0.5, R, 1e6, d)
    assert f == pytest.approx(hertz, rel=1e-4) and chi < 1e-5
    f, chi = dimitriadis_force_n(E, 0.5, R, 10.0, d)
    poly = 1 + 1.133 * chi + 1.283 * chi ** 2 + 0.769 * chi ** 3 + 0.0975 * chi ** 4
    assert f / hertz == pytest.approx(poly, rel=2e-3)


# ----- nodal volumetric stiffness (twin.volumetric) -----------------------------------------------------

@pytest.mark.parametrize("free_only", [False, True])
def test_nodal_volume_forces_are_the_energy_gradient_and_a_dilation_gives_its_pressure(free_only):
    """U = sum_n (K/2) V_n (J_n - 1)^2 on the twin's mesh, two materials: the forces equal -dU/dx by central
    differences (relative 1e-6), and a uniform dilation J = 0.97 gives every node J_n = J, U = (K/2) V (J-1)^2
    per material and the virtual work sum f.x = -3 s^2 sum K V (J-1) of a pressure K (J - 1) (rel. 1e-9)."""
    from twin.mesh import build_mesh
    from twin.volumetric import NodalVolume

    m = build_mesh(load_design("hexagon127"), MeshSpec(fine_mm=2.5))
    X = m.nodes_mm
    Ks, Kg = 3.0, 0.5
    active = ~m.pinned if free_only else None
    nv = NodalVolume.build(X, [(m.tets_skin, Ks), (m.tets_gel, Kg)], active)
    rng = np.random.default_rng(0)
    Y = X + rng.normal(0.0, 0.2, X.shape)
    f = nv.forces(Y)
    h = 1e-5
    for i in rng.choice(np.nonzero(np.abs(f).sum(axis=1) > 0)[0], 15, replace=False):
        for a in range(3):
            Yp, Ym = Y.copy(), Y.copy()
            Yp[i, a] += h
            Ym[i, a] -= h
            fd = -(nv.energy(Yp) - nv.energy(Ym)) / (2 * h)
            assert abs(fd - f[i, a]) <= 1e-6 * np.abs(f).max(), (i, a, fd, f[i, a])

    def volume(tets):   # rest volume of the tetrahedra that carry the energy (an active node)
        P = X[tets]
        keep = np.ones(len(tets), bool) if active is None else active[tets].any(axis=1)
        return float(np.abs(np.linalg.det(np.stack([P[:, k] - P[:, 0] for k in (1, 2, 3)], axis=2)))[keep].sum() / 6)

    J = 0.97
    s = J ** (1 / 3)
    Jbar, _ = nv.evaluate(X * s)
    assert np.allclose(Jbar, J, atol=1e-12)
    Vs, Vg = volume(m.tets_skin), volume(m.tets_gel)
    assert nv.energy(X * s) == pytest.approx(0.5 * (J - 1) ** 2 * (Ks * Vs + Kg * Vg), rel=1e-9)
    work = float(np.sum(nv.forces(X * s) * X))
    assert work == pytest.approx(-3 * s ** 2 * (J - 1) * (Ks * Vs + Kg * Vg), rel=1e-9)


def test_nodal_volumetric_sim_applies_the_energy_gradient_and_restores_exactly():
    """In the sim (MeshSpec(volumetric="nodal")) the forces on the free vertices' slide DOFs are -dU/dq of
    the nodal energy in MuJoCo's world frame (central differences, rel. 1e-6); the flex keeps the gel's
    shear modulus; a checkpoint restores the state bit for bit."""
    from benchmarks.experiments.physics import _uniform
    from twin import materials, units, volumetric
    from twin.model import _FLIP, flex_elasticity

    d = _uniform(load_design("hexagon127"), 0.49)
    sim = SkinSim(d, make_indenter("sphere", radius_mm=10.0), mesh=MeshSpec(volumetric="nodal"), friction=0.0)
    E_flex, nu_flex = flex_elasticity(sim.mesh_spec, materials.gel_material(d))
    E = units.mpa_to_pa(d.gel.youngs_modulus_mpa)
    assert nu_flex == volumetric.NU_DEV
    assert E_flex / (2 * (1 + nu_flex)) == pytest.approx(E / (2 * (1 + 0.49)), rel=1e-12)   # shear modulus kept
    # ... and the nodal bulk modulus tops the flex's up to the material's
    assert E_flex / (3 * (1 - 2 * nu_flex)) + sim._vol["nv"].bulk[0] == pytest.approx(E / (3 * (1 - 2 * 0.49)))
    idx = sim._qadr.ravel()
    rng = np.random.default_rng(1)
    sim.data.qpos[idx] = rng.normal(0.0, 1e-4, len(idx))
    sim._update_volumetric()
    f = sim.data.qfrc_applied[idx].copy()
    nv = sim._vol["nv"]

    def energy(q):
        X = units.mm_to_m(sim.mesh.nodes_mm * _FLIP)
        X[sim._free] += q.reshape(-1, 3)
        return nv.energy(X)

    q, h = sim.data.qpos[idx].copy(), 1e-8
    for i in rng.choice(len(q), 12, replace=False):
        qp, qm = q.copy(), q.copy()
        qp[i] += h
        qm[i] -= h
        assert -(energy(qp) - energy(qm)) / (2 * h) == pytest.approx(f[i], rel=1e-6, abs=1e-6 * np.abs(f).max())
    cp = sim.checkpoint()
    sim.step(3)
    a = sim.data.qpos.copy()
    sim.restore(cp)
    sim.step(3)
    assert np.array_equal(sim.data.qpos, a)


@pytest.mark.parametrize("layered, force_max", [(False, 1.30), (True, 1.15)], ids=["production_levels", "layered"])
def test_nodal_volumetric_stiffness_unlocks_a_nearly_incompressible_gel(layered, force_max):
    """Sphere R = 10 mm into the uniform gel (nu = 0.49; bonded layer h = T + G) at 1 and 3 mm. Element-wise the
    linear tetrahedra lock: force 2.25-2.39x the bonded-layer Hertz solution (Dimitriadis et al. 2002). With the
    bulk stiffness on averaged nodal volumes the force is within 30 % of it on the production gel levels
    (measured 1.18-1.23x; the same mesh at nu = 0.3, far from locking, is 1.11-1.14x: the rest is the mesh's own
    error, a 6 mm bottom cell) and within the 15 % target on the gel refined through the thickness (seven
    levels: measured 1.12 / 1.14); the contact radius within 15 % of sqrt(R delta) (measured 0.98-1.09); the
    presses settle without MuJoCo warnings."""
    from benchmarks.experiments.physics import LAYERED_GEL_LEVELS_MM, RADIUS_MM, _contact_radius_mm, _press_series, \
        _uniform, dimitriadis_force_n

    d = load_design("hexagon127")
    u = _uniform(d, 0.49)
    depths = [1.0, 3.0]
    mesh = MeshSpec(volumetric="nodal", gel_levels_mm=LAYERED_GEL_LEVELS_MM) if layered else MeshSpec(volumetric="nodal")
    res, _, sim = _press_series(u, depths, mesh)
    h = u.skin.thickness_mm + u.optics.gel_thickness_mm
    theory, _ = dimitriadis_force_n(d.gel.youngs_modulus_mpa, 0.49, RADIUS_MM, h, depths)
    for (dep, f, tr, st, _), ft in zip(res, theory):
        assert st.converged, dep
        assert 0.85 <= f / ft <= force_max, (dep, f / ft)
        assert abs(_contact_radius_mm(tr, dep) / np.sqrt(RADIUS_MM * dep) - 1) <= 0.15, dep
    assert sim.warnings() == {}


# ----- friction ---------------------------------------------------------------------------------------

def _slide(mu, mesh=MeshSpec()):
    """Press a 10 mm sphere 1.5 mm, slide it 0.3 mm along x, settle, hold 200 steps. Returns the fraction of
    the slide the skin vertex under the tip followed at the end of the slide, after settling and after the
    hold; the ratio Q/P of the tangential to the normal force on the skin after settling; whether the
    slide settled."""
    sim = SkinSim(load_design("hexagon127"), make_indenter("sphere", radius_mm=10.0), friction=mu, mesh=mesh)
    sim.set_pose(0, 0, -0.5, 0)
    sim.move_to(0, 0, 1.5, 0)
    assert sim.settle().converged
    top = sim.skin_vertices_mm()
    i = int(np.argmin(np.hypot(top[:, 0], top[:, 1])))
    x0 = top[i, 0]
    sim.move_to(0.3, 0, 1.5, 0)
    moving = (sim.skin_vertices_mm()[i, 0] - x0) / 0.3
    stats = sim.settle()
    settled = (sim.skin_vertices_mm()[i, 0] - x0) / 0.3
    F = sim.data.qfrc_constraint[:3 * len(sim._free)].reshape(-1, 3).sum(axis=0)    # on the skin, world axes
    sim.step(200)
    held = (sim.skin_vertices_mm()[i, 0] - x0) / 0.3
    assert sim.warnings() == {}
    return moving, settled, held, float(np.hypot(F[0], F[1]) / F[2]), stats.converged


@pytest.mark.slow
def test_friction_sticks_where_cattaneo_mindlin_predicts_stick_and_does_not_creep():
    """Stick and slip from Coulomb's law at the outer vertices (stick constraints, twin.physics). At mu = 1 the
    tangential load after a 0.3 mm slide is Q/P = 0.55 < mu (measured), so Cattaneo-Mindlin predicts no gross
    slip: the skin under the tip moves with the indenter and stays there while held (MuJoCo's own soft
    friction let it creep back to ~0). At mu = 0 it does not follow."""
    moving, settled, held, qp, converged = _slide(1.0)
    assert converged and qp < 1.0, (qp, converged)
    assert settled >= 0.9 and abs(held - settled) <= 0.02, (settled, held)
    _, settled0, held0, qp0, converged0 = _slide(0.0)
    # frictionless, the normal forces on the curved, laterally shifted contact still lean: Q/P 0.03 (measured)
    assert converged0 and abs(settled0) < 0.1 and abs(held0) < 0.1 and qp0 < 0.1, (settled0, held0, qp0)


@pytest.mark.slow
def test_friction_below_the_stick_load_slides_at_coulombs_limit():
    """At mu = 0.3, below the Q/P = 0.55 the same slide needs to stick, the contact slides: the tangential load
    is capped by mu P plus the lean of the normal forces (Q/P 0.03 at mu = 0), measured 0.317 once settled (the
    stick anchors count in the settle criterion) and asserted within 0.25-0.36, and the skin under the tip lags
    the indenter (0.58 of the slide after settling; a sliding contact keeps relaxing slowly while held, to 0.49
    and Q/P 0.29 after 200 steps, as the sliding anchors move at most STICK_MAX_SLIDE_MM a step)."""
    _, settled, held, qp, converged = _slide(0.3)
    assert converged and 0.25 <= qp <= 0.36, (qp, converged)
    assert settled < 0.8 and held < 0.8, (settled, held)


@pytest.mark.slow
def test_friction_deep_press_settles_with_the_contact_carrying_the_normal_load():
    """A 5 mm press of the σ² = 10 Gaussian at mu = 1 settles to equilibrium. The stuck vertices are tied to the
    indenter in x and y only while their contacts carry the normal load; as point constraints that carried it too
    (contacts switched off while stuck) the stuck skin sank 0.13 mm into the indenter and the vertices at the edge
    of the contact were released and stuck again every few steps, so the press never settled (800 steps,
    measured). Measured now: settled, ~110-150 vertices stuck, the outer vertices within 0.05 mm of the surface."""
    from twin import robot

    sim = SkinSim(load_design("hexagon127"), make_indenter("gaussian", h_mm=5, sigma2_mm2=10), friction=1.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(5.0))
    assert stats.converged and not stats.direct, stats
    assert len(sim.stuck_vertices()) >= 50
    assert sim.outer_penetration_mm() <= 0.06, sim.outer_penetration_mm()
    assert sim.warnings() == {}


def test_rounded_edge_keeps_the_flat_top_and_lowers_the_clamp_to_the_mount():
    """MeshSpec(edge_drop_mm=...): the skin is flat where the markers are (rest markers exact), rounds down
    beyond edge_start_mm, and every clamped outer vertex sits on the mount edge_drop_mm below the skin's top; no
    tetrahedron inverts. A pattern whose markers reach onto the edge is refused."""
    import dataclasses

    from twin.mesh import build_mesh

    spec = MeshSpec(face_contact=True, fine_half_mm=15.0, edge_start_mm=16.5, edge_drop_mm=5.0)
    for name in ("hexagon61_sep354", "hexagon127", "hexagon217_sep180"):
        d = load_design(name)
        m = build_mesh(d, spec)
        top = m.nodes_mm[m.top]
        r = np.hypot(top[:, 0], top[:, 1])
        clamped = m.pinned[m.top]
        assert np.allclose(top[clamped, 2], -5.0)
        assert np.all(top[r <= 16.5, 2] == 0.0) and np.all(np.diff(top[np.argsort(r), 2]) <= 1e-9)
        flat = build_mesh(d, dataclasses.replace(spec, edge_drop_mm=1e-9))    # the same cells, not lowered
        vol6 = []
        for mesh in (m, flat):
            X = mesh.nodes_mm[np.vstack([mesh.tets_skin, mesh.tets_gel])]
            vol6.append(np.linalg.det(np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)))
        assert np.min(vol6[0] * np.sign(vol6[1])) > 1e-3                        # none inverted or degenerate
        sim = SkinSim(d, make_indenter("flat"), mesh=spec, friction=0.0)
        assert np.abs(sim.markers()[0] - d.rest_markers_mm()).max() < 0.01
    with pytest.raises(PhysicsError):
        build_mesh(load_design("square121"), spec)
