"""Physics validity of twin frames: geometric penetration checks against analytic shapes, the verdict,
its record in the truth files, and the twin flagging its own known contact limits."""

import json

import numpy as np
import pytest

from pipeline.types import HeightMap
from twin.truth import Truth
from twin.validity import PENETRATION_MAX_MM, frame_validity, rim_overlap_mm, skin_penetration


def _grid_skin(spacing_mm=1.5, half_mm=6.0, z=0.0):
    ax = np.arange(-half_mm, half_mm + 1e-9, spacing_mm)
    X, Y = np.meshgrid(ax, ax, indexing="ij")
    v = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])
    n = len(ax)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return v, f


def _cone(apex_xy, apex_z, slope):
    """A rigid cone pointing down at the skin (its surface z grows with distance from the apex)."""
    return lambda xy: apex_z + slope * np.hypot(xy[:, 0] - apex_xy[0], xy[:, 1] - apex_xy[1])


def test_tip_through_a_face_interior_is_seen_although_no_vertex_is_inside():
    """A sharp cone whose apex pokes 0.4 mm through the middle of a skin cell: every vertex, centroid and
    edge midpoint of the flat 1.5 mm skin is outside it, so only the indenter-side samples can see it."""
    v, f = _grid_skin()
    apex = (0.55, 0.2)                   # inside the triangle (0,0)-(1.5,0)-(1.5,1.5), off every skin sample
    ind = _cone(apex, -0.4, 4.0)
    pen = skin_penetration(v, f, ind)
    assert pen.vertex_max_mm == 0.0
    assert pen.max_mm == pytest.approx(0.4, abs=4.0 * 0.1 / np.sqrt(2))   # grid sample within 0.07 mm of the apex
    assert pen.max_mm > PENETRATION_MAX_MM


def test_uniform_overlap_and_clear_skin():
    v, f = _grid_skin()
    flat_inside = lambda xy: np.full(len(xy), -0.2)     # indenter face 0.2 mm below the skin: all of it inside
    pen = skin_penetration(v, f, flat_inside)
    assert pen.max_mm == pytest.approx(0.2, abs=1e-12) and pen.p99_mm == pytest.approx(0.2, abs=1e-12)
    flat_touch = lambda xy: np.full(len(xy), 0.01)      # 10 um above: touching, not inside
    pen = skin_penetration(v, f, flat_touch)
    assert pen.max_mm == 0.0 and pen.n_touching > 0
    assert pen.gap_touching_max_mm == pytest.approx(0.01, abs=1e-12)
    off_part = lambda xy: np.full(len(xy), np.nan)
    assert skin_penetration(v, f, off_part).max_mm == 0.0


def test_clamped_rim_is_left_out_and_measured_separately():
    v, f = _grid_skin()
    rim = np.abs(v[:, :2]).max(axis=1) > 5.0
    ind = lambda xy: np.where(np.abs(xy).max(axis=1) > 5.0, -0.3, 1.0)   # reaches 0.3 mm below the rim only
    assert skin_penetration(v, f, ind).max_mm == pytest.approx(0.3)
    assert skin_penetration(v, f, ind, free=~rim).max_mm == 0.0
    assert rim_overlap_mm(v, rim, ind) == pytest.approx(0.3)


def test_verdict_names_every_failed_check():
    v, f = _grid_skin()
    pen = skin_penetration(v, f, lambda xy: np.full(len(xy), 0.02))
    ok = frame_validity(pen, contact_force_n=1.0, settled=True, mujoco_warnings={})
    assert ok.valid and ok.reasons == ()
    bad = frame_validity(skin_penetration(v, f, lambda xy: np.full(len(xy), -0.1)), contact_force_n=1.0,
                         settled=False, mujoco_warnings={"mjWARN_INERTIA": 2})
    assert not bad.valid and len(bad.reasons) == 3
    assert "inside the indenter" in bad.reasons[0] and "settle" in bad.reasons[1] and "mjWARN_INERTIA" in bad.reasons[2]
    back = type(bad).from_dict(json.loads(json.dumps(bad.to_dict(), allow_nan=False)))   # strict JSON
    assert back.to_dict() == bad.to_dict() and np.isnan(back.gap_touching_max_mm)


def test_truth_file_keeps_the_validity_and_old_files_load_without_it(tmp_path):
    hm = HeightMap(np.arange(3.0), np.arange(2.0), np.zeros((2, 3)))
    args = (np.arange(1), np.zeros((1, 3)), np.array([[0, 0, -1.0]]), np.zeros((3, 3)), np.array([[0, 1, 2]]),
            hm, np.zeros(4))
    v = frame_validity(skin_penetration(*_grid_skin(), lambda xy: np.full(len(xy), -0.1)), contact_force_n=0.5,
                       settled=True, mujoco_warnings={}).to_dict()
    Truth(*args, v).save_npz(tmp_path / "a.npz")
    t = Truth.load_npz(tmp_path / "a.npz")
    assert t.validity == v and t.physics_valid is False
    Truth(*args).save_npz(tmp_path / "b.npz")
    assert Truth.load_npz(tmp_path / "b.npz").validity is None and Truth.load_npz(tmp_path / "b.npz").physics_valid is None


@pytest.mark.render
def test_a_pin_beyond_the_gel_flags_the_frame_which_is_drawn_with_the_pin_stopped_at_the_window():
    """A pin's tip past the gel, in the acrylic window (a real pin cannot get there): the frame is invalid
    and says why, and is drawn with the tip stopped 0.01 mm inside the gel, so that a sequence keeps its
    frame; a frame not flagged so still makes the renderer refuse."""
    from pipeline.design import load_design
    from twin.render import RenderError
    from twin.simulate import render_truths

    pen = skin_penetration(*_grid_skin(), lambda xy: np.full(len(xy), 0.02))
    bad = frame_validity(pen, contact_force_n=1.0, settled=True, mujoco_warnings={}, pin_overrun=0.3)
    ok = frame_validity(pen, contact_force_n=1.0, settled=True, mujoco_warnings={})
    assert not bad.valid and "0.300 mm beyond the gel" in bad.reasons[0] and ok.valid and ok.pin_overrun_mm == 0
    design = load_design("hexagon127")
    xyz = design.rest_markers_mm().copy()
    xyz[5, 2] = design.gel_acrylic_z_mm - 0.3
    hm = HeightMap(np.arange(3.0), np.arange(2.0), np.zeros((2, 3)))
    args = (np.arange(len(xyz)), xyz, np.tile([0.0, 0.0, -1.0], (len(xyz), 1)), *_grid_skin(half_mm=21.0), hm, np.zeros(4))
    assert render_truths(design, [Truth(*args, bad.to_dict())], rng=np.random.default_rng(0))[0].left.shape == (480, 640, 3)
    with pytest.raises(RenderError, match="in the gel"):
        render_truths(design, [Truth(*args, ok.to_dict())], rng=np.random.default_rng(0))


@pytest.mark.physics
def test_face_contact_keeps_a_sharp_tip_out_where_vertex_contacts_let_it_through():
    """σ² = 2.5 mm² Gaussian pressed 3 mm: the tip (curvature radius 0.5 mm) passes between the skin's
    1.5 mm contact vertices. With vertex contacts only, no vertex is inside yet faces are ~1 mm inside the
    tip, and the frame's truth must say so; with the faces colliding with the indenter's surface spheres
    (twin.contact, MeshSpec(face_contact=True)) the whole outer skin stays within the 0.05 mm bound."""
    from pipeline.design import load_design
    from twin import robot
    from twin.indenters import make_indenter
    from twin.physics import MeshSpec, SkinSim

    ind = make_indenter("gaussian", h_mm=5, sigma2_mm2=2.5)
    d = load_design("hexagon127")
    sim = SkinSim(d, ind, friction=0.0)                    # vertex contacts only (the default mesh)
    assert not sim.face_contact
    (_, _, truth), = robot.execute(sim, robot.press_motion(3.0))
    v = truth.validity
    assert v["penetration_vertex_max_mm"] <= PENETRATION_MAX_MM
    assert v["penetration_max_mm"] > 0.5
    assert not v["valid"] and any("inside the indenter" in r for r in v["reasons"])
    sim = SkinSim(d, ind, mesh=MeshSpec(face_contact=True), friction=0.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(3.0))
    v = truth.validity
    assert sim.face_contact and sim.face_contact_fallback is None
    assert stats.converged and v["valid"], v["reasons"]
    assert v["penetration_max_mm"] <= PENETRATION_MAX_MM and v["contact_force_n"] > 0
    # the spheres hold the skin out without holding it off: the apex vertex is pressed at least as deep as
    # the tip (vertices are not pushed back out of the cap), and not beyond by more than the chord sag of
    # its 1.5 mm faces over the 0.5 mm tip radius would explain
    apex = truth.skin_vertices_mm[np.argmin(np.hypot(*truth.skin_vertices_mm[:, :2].T)), 2]
    assert -3.0 - 0.6 < apex < -3.0 + PENETRATION_MAX_MM, apex


@pytest.mark.physics
@pytest.mark.slow
def test_face_contact_holds_a_sine_pressed_across_the_module_out_of_the_skin():
    """A sine at ω = π/5 (2.5 mm amplitude) pressed 3 mm: its crests run across the whole module, up to the
    clamped rim. With vertex contacts only the skin faces sag into the crests (measured 1.76 mm). Face contact
    used to blow up here (MuJoCo's contacts on faces with a clamped vertex drove the free rim vertices into the
    gel: mjWARN_INERTIA, then the vertex-contact fallback); with those faces left out and every sphere the sine
    needs (12,726) the frame is valid (measured 0.033 mm inside, settled, no MuJoCo warning, no fallback)."""
    from pipeline.design import load_design
    from twin import robot
    from twin.indenters import make_indenter
    from twin.physics import MeshSpec, SkinSim

    d = load_design("hexagon127")
    ind = make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=np.pi / 5)
    sim = SkinSim(d, ind, mesh=MeshSpec(face_contact=True), friction=0.0)
    # no face of the contact flex has a vertex on the world body (the clamped rim)
    fl = int(sim._face_flex[0])
    m = sim.model
    elem = m.flex_elem[m.flex_elemdataadr[fl]:m.flex_elemdataadr[fl] + 3 * m.flex_elemnum[fl]]
    vbody = m.flex_vertbodyid[m.flex_vertadr[fl]:m.flex_vertadr[fl] + m.flex_vertnum[fl]]
    assert m.flex_elemnum[fl] > 0 and np.all(vbody[elem] != 0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(3.0))
    v = truth.validity
    assert sim.face_contact and sim.face_contact_fallback is None
    assert sim.warnings() == {} and stats.converged
    assert v["valid"] and v["penetration_max_mm"] <= PENETRATION_MAX_MM, v["reasons"]
    assert v["contact_force_n"] > 0
    sim = SkinSim(d, ind, friction=0.0)                    # vertex contacts only: faces inside the crests
    (_, _, truth), = robot.execute(sim, robot.press_motion(3.0))
    assert not truth.validity["valid"] and truth.validity["penetration_max_mm"] > 1.0


@pytest.mark.physics
@pytest.mark.slow
def test_skin_beside_a_rounded_edge_stays_out_of_a_sine_wider_than_the_module():
    """A sine wider than the module, 2π/5 (crests 5 mm apart), yaw 120, pressed 5 mm on hexagon127. With the mount
    flush with the skin (the default mesh) the crests reach 5 mm below it, the free skin beside it is pulled down
    across one cell and MuJoCo's solve fails (vertex-contact fallback, 2.48 mm inside). With the skin rounding
    down over its edge to a mount 5 mm below its top (MeshSpec.edge_drop_mm, 1.5 mm cells out to it) the plate
    clears the mount and the whole free skin stays within PENETRATION_MAX_MM (measured 0.0195 mm, settled, no
    MuJoCo warning, no fallback)."""
    from pipeline.design import load_design
    from twin import robot
    from twin.indenters import make_indenter
    from twin.physics import MeshSpec, SkinSim

    ind = make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=2 * np.pi / 5)
    mesh = MeshSpec(face_contact=True, fine_half_mm=15.0, edge_start_mm=16.5, edge_drop_mm=5.0)
    sim = SkinSim(load_design("hexagon127"), ind, mesh=mesh, friction=0.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(5.0, yaw_deg=120.0))
    v = truth.validity
    assert sim.face_contact_fallback is None and sim.warnings() == {} and stats.converged
    assert v["rim_overlap_mm"] <= 1e-6                       # the plate does not reach the rigid mount
    assert v["valid"] and v["penetration_max_mm"] <= PENETRATION_MAX_MM, v["reasons"]


@pytest.mark.physics
@pytest.mark.slow
def test_a_roller_rim_carries_the_skin_edge_down_under_a_sine_wider_than_the_module():
    """A sine at ω = π/5, yaw 0, pressed 5 mm on hexagon127 with face contact. Clamped flush with the skin, the
    rim holds the skin's edge while the crests pass 5 mm below it, and the free skin beside it ends 0.057 mm
    inside the sine (over PENETRATION_MAX_MM). With a roller rim (MeshSpec(rim="roller")) the skin's edge slides
    down the mount's wall with the crests: it keeps its rest x-y, the indenter no longer reaches below any held
    vertex, and the whole skin stays within the bound (measured 0.032 mm, settled, no fallback). The direct solve
    reaches that pose with every vertex outside the sine but faces 2.5 mm inside; with face contact it is checked
    at the faces too and refused, so the press follows the path."""
    from pipeline.design import load_design
    from twin import robot
    from twin.indenters import make_indenter
    from twin.physics import MeshSpec, SkinSim

    sim = SkinSim(load_design("hexagon127"), make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=np.pi / 5),
                  mesh=MeshSpec(face_contact=True, rim="roller"), friction=0.0)
    roller = sim.mesh.roller
    rest = sim.mesh.nodes_mm[roller]
    (_, stats, truth), = robot.execute(sim, robot.press_motion(5.0))
    v = truth.validity
    assert sim.face_contact_fallback is None and sim.warnings() == {} and stats.converged
    now = sim.nodes_mm()[roller]
    assert np.abs(now[:, :2] - rest[:, :2]).max() <= 0.02    # held on the wall in x-y (a limit as stiff as a contact)
    assert now[:, 2].min() < rest[:, 2].min() - 1.0                   # and carried down along it
    assert v["rim_overlap_mm"] <= 1e-6
    assert v["valid"] and v["penetration_max_mm"] <= PENETRATION_MAX_MM, v["reasons"]
    assert not stats.direct and sim.direct_rejections == 1


@pytest.mark.physics
@pytest.mark.slow
def test_the_sine_experiments_plate_clears_the_mount_and_keeps_out_of_the_skin_with_friction():
    """ω = π/5 at yaw 240 (crests crossing the mesh cells obliquely), pressed 5 mm on hexagon127 with the design's
    friction (μ = 1): the sine experiment's plate (the relief out to 13.5 mm, rounded off beyond it) and mesh. The plate
    nowhere reaches below the rigid mount, and every skin face, those on the clamped rim included, stays within
    PENETRATION_MAX_MM of it (measured 0.022 / 0.024 mm, settled, no MuJoCo warning, no fallback). A plate covering
    the module reached 5 mm below the mount; with μ = 1 the free skin beside it ended 1.3-3.5 mm inside the sine. With
    the default sag tolerance (0.02 mm) this press ended 0.051-0.072 mm inside on the rounded-off plates tried first."""
    from benchmarks.experiments import sine
    from pipeline.design import load_design
    from twin import robot
    from twin.physics import SkinSim
    from twin.validity import skin_penetration

    sim = SkinSim(load_design("hexagon127"), sine.sine_plate(np.pi / 5), mesh=sine.sine_mesh())
    assert sim.friction == pytest.approx(1.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(5.0, yaw_deg=240.0))
    v = truth.validity
    assert sim.face_contact_fallback is None and sim.warnings() == {} and stats.converged
    assert v["rim_overlap_mm"] <= 1e-6
    assert v["valid"] and v["penetration_max_mm"] <= PENETRATION_MAX_MM, v["reasons"]
    every_face = skin_penetration(sim.skin_vertices_mm(), sim.mesh.top_faces, sim.indenter_z_at)
    assert every_face.max_mm <= PENETRATION_MAX_MM, every_face.max_mm
    assert v["contact_force_n"] > 10.0


def test_an_unknown_rim_is_refused():
    from pipeline.design import load_design
    from twin.mesh import MeshSpec, PhysicsError, build_mesh

    with pytest.raises(PhysicsError, match="rim"):
        build_mesh(load_design("hexagon127"), MeshSpec(rim="glued"))


@pytest.mark.physics
@pytest.mark.slow
def test_unstable_face_contact_falls_back_to_vertex_contact_and_is_flagged(monkeypatch):
    """Should MuJoCo's solve fail with face contact, the motion is re-run from its start with vertex contacts
    only (recorded on the sim, no MuJoCo warning left on the kept state), and the frame's own check reports
    the faces inside the crests. The failure is the real one face contact had before the faces with a clamped
    vertex were left out of it: a sine at ω = π/5 pressed across the module drives the free rim vertices into
    the gel (mjWARN_INERTIA, NaN accelerations)."""
    from collections import OrderedDict

    from pipeline.design import load_design
    from twin import model, robot
    from twin.indenters import make_indenter
    from twin.physics import MeshSpec, SkinSim

    monkeypatch.setattr(model, "_face_contact_faces", lambda mesh: mesh.top[mesh.top_faces])   # every face
    monkeypatch.setattr(model, "_MODEL_CACHE", OrderedDict())    # a model compiled with those faces
    sim = SkinSim(load_design("hexagon127"), make_indenter("sine", amplitude_mm=2.5, omega_rad_per_mm=np.pi / 5),
                  mesh=MeshSpec(face_contact=True), friction=0.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(3.0))
    assert not sim.face_contact and "solve failed" in sim.face_contact_fallback
    assert sim.warnings() == {} and stats.converged
    assert not truth.validity["valid"] and truth.validity["penetration_max_mm"] > 0.3


@pytest.mark.physics
def test_a_face_contact_solve_that_diverges_into_a_mujoco_error_falls_back(monkeypatch):
    """A failed face-contact solve can diverge before its warning is checked: the vertices fly apart and MuJoCo
    raises (its collision arena overflows; measured on a 2π/5 sine pressed 5 mm on a rounded-edge mesh). That is
    the same failed solve: the motion is re-run from its start with vertex contacts only and flagged."""
    import mujoco

    from pipeline.design import load_design
    from twin import robot
    from twin.indenters import make_indenter
    from twin.physics import MeshSpec, SkinSim

    real = robot._execute

    def diverging(sim, motion, progress, direct, *, stop_if_unstable=None):
        if stop_if_unstable is not None:                       # the face-contact attempt
            sim.set_pose(*motion.waypoints[-1].pose)
            sim.step()
            raise mujoco.FatalError("mj_stackAlloc: out of memory, stack overflow at mj_collideTree")
        return real(sim, motion, progress, direct)

    monkeypatch.setattr(robot, "_execute", diverging)
    sim = SkinSim(load_design("hexagon127"), make_indenter("gaussian", h_mm=5, sigma2_mm2=10),
                  mesh=MeshSpec(face_contact=True), friction=0.0)
    (_, stats, truth), = robot.execute(sim, robot.press_motion(1.0))
    assert not sim.face_contact and "solve failed" in sim.face_contact_fallback
    assert stats.converged and sim.warnings() == {} and truth.validity["contact_force_n"] > 0


def test_letter_surface_spheres_stay_on_the_letter_and_cover_its_edges():
    """The face-contact spheres of a letter (vertical 3 mm walls, flat top): none stands more than the edge
    spheres' 0.021 mm (r - sqrt(r^2 - cover^2)) proud of the true surface over the letter's top, and every
    point of the top edge lies inside some sphere, so a skin face lying on them cannot cut the edge. Before
    the spheres were lowered, those on the walls stood 0.375 mm above the top and held the skin off it."""
    from twin import contact
    from twin.indenters import make_indenter

    ind = make_indenter("letter", char="G")
    c, r = contact.surface_spheres(ind, skin_cell_mm=1.5, with_radii=True)
    # highest point of each sphere above the letter's flat top, where it lies over the top
    off = contact._disc_offsets(0.4)
    cap = np.sqrt(np.maximum(r[:, None] ** 2 - np.sum(off ** 2, axis=1)[None, :], np.nan))
    q = c[:, None, :2] + off[None, :, :]
    h = ind.height(q[..., 0], q[..., 1])
    over_top = (h >= ind.top_mm - 1e-6) & np.isfinite(cap)
    above = np.where(over_top, c[:, 2:3] + cap - h, -np.inf)
    assert np.max(above) <= 0.0215, np.max(above)
    # top-edge points: on the letter's top with a point 0.05 mm away off it
    x, y, z = ind.grid(0.05)
    X, Y = np.meshgrid(x, y)
    top = z >= ind.top_mm - 1e-6
    edge = top & ~(np.roll(top, 1, 0) & np.roll(top, -1, 0) & np.roll(top, 1, 1) & np.roll(top, -1, 1))
    pts = np.column_stack([X[edge], Y[edge], z[edge]])
    from scipy.spatial import cKDTree

    tree = cKDTree(c)
    d, k = tree.query(pts, k=8)
    inside = np.any(d <= r[k] + 1e-3, axis=1)
    assert inside.mean() >= 0.999, inside.mean()


def test_surface_spheres_follow_a_crest_sharper_than_the_sphere():
    """A sine at ω = 2π/5 (crest radius 1/(Aω²) = 0.25 mm, sharper than the 0.4 mm spheres): a 0.4 mm sphere
    tangent at the crest stands proud of the flanks and is lowered, leaving the crest 0.14 mm above the union
    of spheres (measured), where a skin face resting on them passes through it. Smaller spheres there keep the
    crest within 0.072 mm of the union (measured; the rest is the dip between neighbouring spheres)."""
    import math

    from scipy.spatial import cKDTree

    from twin import contact
    from twin.indenters import make_indenter

    A, w = 2.5, 2 * math.pi / 5
    ind = make_indenter("sine", amplitude_mm=A, omega_rad_per_mm=w)
    c, r = contact.surface_spheres(ind, skin_cell_mm=1.5, with_radii=True)
    assert np.any(r < contact.SPHERE_RADIUS_MM)
    # crest points (own frame): x with sin(wx) = 1, |x| <= 6, |y| <= 3, every 0.025 mm along y
    xs = (math.pi / 2 + 2 * math.pi * np.arange(-1, 2)) / w
    ys = np.arange(-3.0, 3.0, 0.025)
    X, Y = np.meshgrid(xs, ys)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    tree = cKDTree(c[:, :2])
    out = []
    for q, lst in zip(pts, tree.query_ball_point(pts, float(r.max()))):
        lst = np.array(lst, int)
        d2 = np.sum((c[lst, :2] - q) ** 2, axis=1)
        inside = d2 < r[lst] ** 2
        top = np.max(c[lst[inside], 2] + np.sqrt(r[lst[inside]] ** 2 - d2[inside]))
        out.append(A - top)                # how far the crest stands above the spheres
    assert 0.0 <= np.max(out) <= 0.1, np.max(out)


@pytest.mark.physics
def test_face_contact_keeps_a_letters_edges_out_of_the_skin():
    """Letter 'G' (vertical 3 mm walls, 1.6 mm strokes) pressed 1, 2, 3 mm along the tracking path: with vertex
    contacts only its edges cut the 1.5 mm skin faces (0.3-0.9 mm, measured); with face contact and the edge
    spheres every frame is valid (measured 0.000 / 0.000 / 0.018 mm, settled, no MuJoCo warning), and so it is
    with friction (mu = 1, the tracking experiment's: 0.000 / 0.007 / 0.024 mm, settled). (The flat 1.5 mm faces
    still lever vertices next to an edge off the letter's top: up to 0.35 mm at 3 mm, measured.)"""
    from pipeline.design import load_design
    from twin import robot
    from twin.indenters import make_indenter
    from twin.physics import MeshSpec, SkinSim

    for friction in (0.0, 1.0):
        sim = SkinSim(load_design("hexagon127"), make_indenter("letter", char="G"), mesh=MeshSpec(face_contact=True),
                      friction=friction)
        motion = robot.Motion("G", (robot.Waypoint(0, 0, -1.0, capture=False),) +
                              tuple(robot.Waypoint(0, 0, float(dz)) for dz in (1, 2, 3)))
        out = robot.execute(sim, motion)
        assert sim.face_contact and sim.face_contact_fallback is None
        for _, stats, truth in out:
            v = truth.validity
            assert stats.converged and v["valid"], (friction, v["reasons"])
            assert v["penetration_max_mm"] <= PENETRATION_MAX_MM
