"""simulate API and CLI: truth files, metadata, depth limits and user-facing errors."""

import json

import numpy as np
import pytest

from pipeline.design import load_design
from pipeline.types import DataError, HeightMap
from stereotactip.cli import main
from twin.indenters import make_indenter
from twin.physics import MeshSpec, PhysicsError, max_depth_mm
from twin.simulate import press_truth
from twin.truth import Truth


def _truth():
    ax = np.linspace(-1, 1, 5)
    return Truth(np.arange(3), np.zeros((3, 3)), np.tile([0, 0, -1.0], (3, 1)), np.zeros((4, 3)),
                 np.array([[0, 1, 2], [0, 2, 3]]), HeightMap(ax, ax, np.full((5, 5), np.nan)), np.array([0, 0, -1, 0.0]))


def test_truth_round_trip_and_validation(tmp_path):
    t = _truth()
    t.save_npz(tmp_path / "t.npz")
    u = Truth.load_npz(tmp_path / "t.npz")
    for f in ("marker_ids", "marker_xyz_mm", "marker_axis", "skin_vertices_mm", "skin_faces", "robot_pose"):
        assert np.array_equal(getattr(t, f), getattr(u, f))
    assert np.array_equal(np.isnan(u.indenter.z_mm), np.isnan(t.indenter.z_mm))
    with pytest.raises(DataError, match="marker_axis"):
        Truth(np.arange(1), np.zeros((1, 3)), np.array([[0, 0, -2.0]]), np.zeros((3, 3)), np.array([[0, 1, 2]]),
              t.indenter, t.robot_pose)
    with pytest.raises(DataError, match="does not exist"):
        Truth.load_npz(tmp_path / "missing.npz")
    data = (tmp_path / "t.npz").read_bytes()
    for cut in (0, 50, len(data) // 2):
        (tmp_path / "cut.npz").write_bytes(data[:cut])
        with pytest.raises(DataError, match=r"cut\.npz: unreadable or truncated"):
            Truth.load_npz(tmp_path / "cut.npz")


@pytest.mark.physics
def test_press_truth_frames_at_increasing_depth():
    d = load_design("hexagon127")
    run = press_truth(d, make_indenter("gaussian", sigma2_mm2=50), 2.0, n_frames=2, mesh=MeshSpec(fine_mm=2.5),
                      friction=0.0)
    assert len(run) == 2 and run.meta["mujoco_warnings"] == {}
    assert [t.robot_pose[2] for t in run] == [-1.0, -2.0]
    assert run.meta["timestamps_s"] == [2.0, 3.0]                 # 1 mm approach + depth at 1 mm/s
    centre = [t.marker_xyz_mm[np.argmin(np.hypot(*d.rest_markers_mm()[:, :2].T))] for t in run]
    rest_z = -d.marker_depth_mm
    assert rest_z > centre[0][2] > centre[1][2]                     # the centre marker goes deeper
    assert np.array_equal(run[0].marker_ids, np.arange(d.marker_count))


@pytest.mark.physics
def test_frames_filmed_in_motion_leave_the_press_unchanged(tmp_path, capsys):
    """A press filmed every 0.5 mm of its path gives frames at the touch and 0.5-1.5 mm, flagged in motion (never
    valid, never counted as invalid frames) with timestamps on the robot's path, and a settled frame identical
    to the unfilmed press's to the last bit: filming only reads the state. With friction (the design's, μ = 1),
    where the path decides the pose."""
    d = load_design("hexagon127")
    ind = make_indenter("gaussian", sigma2_mm2=50)
    plain = press_truth(d, ind, 2.0, mesh=MeshSpec(fine_mm=2.5))
    filmed = press_truth(d, ind, 2.0, mesh=MeshSpec(fine_mm=2.5), film_every_mm=0.5)
    assert [t.in_motion for t in filmed] == [True] * 5 + [False]
    assert [float(-t.robot_pose[2]) for t in filmed[:5]] == pytest.approx([-0.5, 0.0, 0.5, 1.0, 1.5], abs=0.061)
    assert filmed.meta["timestamps_s"][:5] == pytest.approx([0.5, 1.0, 1.5, 2.0, 2.5], abs=0.061)
    assert filmed.meta["filmed_frames"] == [0, 1, 2, 3, 4]
    assert [i - 5 for i in filmed.meta["invalid_frames"]] == plain.meta["invalid_frames"]   # the settled frame's alone
    assert all(not t.physics_valid and t.validity["reasons"][0].startswith("filmed in motion") for t in filmed[:5])
    np.testing.assert_array_equal(filmed[-1].marker_xyz_mm, plain[-1].marker_xyz_mm)
    np.testing.assert_array_equal(filmed[-1].skin_vertices_mm, plain[-1].skin_vertices_mm)
    assert filmed[-1].validity == plain[-1].validity
    assert not filmed[-1].in_motion and filmed[-1].validity["settled"]
    # the film follows the skin down: the centre marker deeper frame by frame once touched
    c = int(np.argmin(np.hypot(*d.rest_markers_mm()[:, :2].T)))
    z = [t.marker_xyz_mm[c, 2] for t in filmed]
    assert z[0] == pytest.approx(-d.marker_depth_mm) and all(b < a for a, b in zip(z[1:], z[2:]))
    with pytest.raises(PhysicsError, match="film_every_mm"):
        press_truth(d, ind, 2.0, film_every_mm=-1.0)
    assert main(["simulate", "--motion", "tracking-G", "--film-every", "1", "--out", str(tmp_path)]) == 2
    assert "--film-every 1: frames in motion are filmed on a press" in capsys.readouterr().err


def test_depth_limits():
    d = load_design("hexagon127")
    for bad in (-1.0, max_depth_mm(d) + 0.1, float("nan")):
        with pytest.raises(PhysicsError, match="depth"):
            press_truth(d, make_indenter("flat"), bad, friction=0.0)


@pytest.mark.parametrize("argv, msg", [
    (["--design", "nope"], "unknown design"),
    (["--indenter", "cube"], "unknown indenter"),
    (["--param", "radius=2"], "unknown parameter"),
    (["--param", "sigma2=-3"], "sigma2_mm2"),
    (["--depth", "20"], "depth"),
])
def test_cli_errors(tmp_path, capsys, argv, msg):
    assert main(["simulate", "--out", str(tmp_path / "o"), *argv]) == 2
    assert msg in capsys.readouterr().err


@pytest.mark.physics
@pytest.mark.render
def test_cli_simulate_writes_frames_truth_calibration(tmp_path, monkeypatch):
    monkeypatch.setenv("PYOPENGL_PLATFORM", "egl")
    out = tmp_path / "run"
    argv = ["simulate", "--design", "hexagon127", "--indenter", "gaussian", "--param", "sigma2=50", "--depth", "1",
            "--mesh", "default"]
    rc = main([*argv, "--out", str(out)])
    validity = json.loads((out / "meta.json").read_text())["validity"][0]
    # frames failing the twin's physics checks are written but flagged: exit 3 unless --allow-invalid
    assert rc == (0 if validity["valid"] else 3)
    assert validity == Truth.load_npz(out / "truth_0000.npz").validity
    assert main([*argv, "--allow-invalid", "--out", str(tmp_path / "again")]) == 0
    import cv2

    img = cv2.imread(str(out / "frame_0000.png"))
    assert img.shape == (480, 1280, 3)
    t = Truth.load_npz(out / "truth_0000.npz")
    assert t.robot_pose[2] == -1.0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["indenter"] == "gaussian" and meta["params"]["sigma2_mm2"] == 50.0 and "settle" in meta
    assert meta["mesh_choice"] == "default"
    assert (out / "calib.yaml").is_file() and (out / "preview.png").is_file()


@pytest.mark.physics
@pytest.mark.render
@pytest.mark.slow
def test_cli_simulate_by_default_presses_a_gaussian_on_the_axis_mesh_and_gives_a_valid_press(tmp_path, monkeypatch):
    """The 1.5 mm default mesh leaves a sigma^2 = 10 press flagged (faces 0.16-0.29 mm inside the indenter); without
    --mesh, simulate picks the axis contact mesh for a Gaussian on the axis (--mesh auto), which keeps it within the
    0.05 mm bound, so it exits 0 without --allow-invalid."""
    monkeypatch.setenv("PYOPENGL_PLATFORM", "egl")
    out = tmp_path / "run"
    rc = main(["simulate", "--design", "hexagon127", "--indenter", "gaussian", "--param", "sigma2=10",
               "--depth", "3", "--out", str(out)])
    meta = json.loads((out / "meta.json").read_text())
    assert meta["mesh_choice"] == "auto: axis"
    v = meta["validity"][-1]
    assert rc == 0 and v["valid"] and v["penetration_max_mm"] <= 0.05, v


@pytest.mark.physics
@pytest.mark.render
@pytest.mark.slow
def test_cli_simulate_presses_the_sine_experiments_plate_on_its_mesh(tmp_path, monkeypatch):
    """The sine experiment's plate and mesh from the CLI (ω = 2π/15, the relief out to 13.5 mm, rounded off beyond it;
    --mesh sine), pressed 3 mm with the design's friction: a valid frame (simulate exits 0), the plate nowhere below
    the mount."""
    monkeypatch.setenv("PYOPENGL_PLATFORM", "egl")
    out = tmp_path / "run"
    rc = main(["simulate", "--design", "hexagon127", "--indenter", "sine", "--param", "omega=0.41887902",
               "--param", "relief_radius_mm=13.5", "--param", "roll_off_radius_mm=2", "--depth", "3",
               "--mesh", "sine", "--out", str(out)])
    meta = json.loads((out / "meta.json").read_text())
    assert meta["mesh_choice"] == "sine"
    v = meta["validity"][-1]
    assert rc == 0 and v["valid"] and v["penetration_max_mm"] <= 0.05 and v["rim_overlap_mm"] <= 1e-6, v


def test_simulate_picks_the_mesh_the_experiments_press_each_indenter_on():
    """--mesh auto: the axis contact mesh for a Gaussian or sphere pressed on the axis (the Gaussian experiment's),
    the sine contact mesh for a sine plate (the sine experiment's), face contact on the default mesh for letters,
    terrain patches and any motion that leaves the axis (the tracking experiment's and the terrain taps')."""
    from twin.mesh import AXIS_CONTACT_MESH, NAMED_MESHES, SINE_CONTACT_MESH, MeshSpec, auto_mesh

    assert [auto_mesh(n) for n in ("gaussian", "sphere", "sine", "letter", "terrain", "flat")] == \
        ["axis", "axis", "sine", "face", "face", "face"]
    assert auto_mesh("gaussian", "tracking-G") == "face"
    assert (NAMED_MESHES["axis"], NAMED_MESHES["sine"], NAMED_MESHES["face"]) == \
        (AXIS_CONTACT_MESH, SINE_CONTACT_MESH, MeshSpec(face_contact=True))
