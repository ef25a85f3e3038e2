"""A narrow sine pressed into the skin from rest: identification carried frame to frame.

Under z = 2.5·sin(ω·x) mm the pins under each crest converge towards touching columns as the press deepens.
Each cell is the sine experiment's own (``press_cell`` with its defaults): the frames the twin films in motion
every 1 mm of the press's path (at the touch and 1-4 mm) and the settled frame at 5 mm, read in order by one
Reconstructor; every reported id is checked against the twin marker nearest its 3-D position (within half a
separation). The figures "settled" below were measured on presses settled at 1, 2, 3, 4 and 5 mm
(``press_frames=5``, ``film_every_mm=0``), the form these tests had before the experiment filmed its presses.
"""

import math

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.physics, pytest.mark.render]

N_FRAMES = 6                  # filmed at the touch and 1, 2, 3, 4 mm, settled at 5 mm


def _cell(name, k):
    from benchmarks.experiments.sine import FILM_EVERY_MM, press_cell
    from pipeline.design import load_design

    assert FILM_EVERY_MM == 1.0
    cell, _ = press_cell(load_design(name), k, 0.0, 0, f"sine/{name}/{k}/0", None)
    assert cell["press_frames"] == 1 and cell["filmed_frames"] == N_FRAMES - 1
    return cell


@pytest.fixture(scope="module")
def crowded_cell():
    from benchmarks.experiments.sine import OMEGAS

    assert OMEGAS[1] == pytest.approx(2 * math.pi / 15)
    return _cell("hexagon127", 1)


def test_press_sequence_never_reports_a_wrong_id_and_holds_until_the_pins_crowd(crowded_cell):
    """The certainty rule may withdraw ids but must never emit a wrong one, in any frame of the press.
    Measured with the experiment's plate, face contact and friction (μ = 1): 127, 127, 127, 127, 127, 126
    of 127 at the touch, 1-4 mm and 5 mm (settled: 127, 127, 127, 127, 126 at 1-5 mm, the 5 mm frame's left
    view finding 126 blobs); frictionless, settled, on a plate covering the module, 127 in every frame (the
    design-to-image rule alone: 127, 127, 0, 67, 0; the frame-to-frame map fitting the increment instead of
    its change from the markers' last velocity: 127, 127, 127, 126, 124). Tolerance: one marker per frame."""
    c = crowded_cell
    assert len(c["matched_fraction_frames"]) == N_FRAMES
    assert c["wrong_ids_sequence"] == 0
    assert c["matched_fraction_frames"][:3] == [1.0] * 3
    assert min(c["matched_fraction_frames"]) >= 126 / 127
    assert c["identified_to_mm"] == 5.0


def test_press_sequence_identifies_the_crowded_pose(crowded_cell):
    """Identification contract: a crowded cell reached by a press from rest identifies >= 95 % of its
    markers, with zero wrong ids. All 127 blobs are detected; from 3 mm on the crest pins crowd beyond
    the local-stretch limit and the design-to-image rule withdraws the crest band (a cascade that
    leaves the rest unanchored: 0 of 127 at 5 mm), while each marker's frame-to-frame motion is still
    a smooth increment of its neighbours': the frame-to-frame map keeps 127 of 127 at 5 mm."""
    assert crowded_cell["matched_fraction"] >= 0.95
    assert crowded_cell["wrong_ids"] == 0


@pytest.fixture(scope="module")
def narrower_cell():
    from benchmarks.experiments.sine import OMEGAS

    assert OMEGAS[2] == pytest.approx(math.pi / 5)
    return _cell("hexagon127", 2)


def test_press_sequence_identifies_the_crowded_pose_of_the_narrower_sine(narrower_cell):
    """z = 2.5·sin(π/5·x) with the design's friction (μ = 1), the crest pins crowding faster frame by
    frame. Measured: 127 of 127 in every frame, none wrong (settled: the same at 1-5 mm). Settled, before
    the detector sized a pin at its narrowed scale space's lowest scale again, 127, 127, 127, 126, 122: pins
    at the edge of the left
    view, seen edge-on, fell under the size test; before that, without the first frame's motion from
    rest as the second frame's velocity, an outer-ring pin held by the clamped rim was lost from 2 mm on
    (127, 126, 126, 125, 121; 120 at 5 mm without the fit from the nearest followed markers too).
    Frictionless, on a plate covering the module: 127, 127, 127, 127, 121 (fitting the increment instead
    of its change from the last velocity: 127, 127, 123, 116, 101). Tolerance: >= 95 % at 5 mm, every
    frame to 4 mm whole."""
    c = narrower_cell
    assert c["wrong_ids_sequence"] == 0
    assert c["matched_fraction"] >= 0.95
    assert c["matched_fraction_frames"][:5] == [1.0] * 5


@pytest.fixture(scope="module")
def dense_cell():
    return _cell("hexagon217_sep180", 1)


def test_press_sequence_identifies_the_crowded_pose_of_the_dense_pattern(dense_cell):
    """hexagon217_sep180 (1.8 mm separation) under z = 2.5·sin(2π/15·x): the valley markers, millimetres
    farther from the cameras than the crests, look ~0.7 x the median marker and must be detected
    against their neighbours' size; markers lost for a frame are re-acquired. Measured with the design's
    friction: 217 of 217 in every frame, none wrong (settled: the same). Frictionless, settled, on a plate
    covering the module: 217,
    217, 217, 217, 215 (217, 215, 213, 212, 208 before the first shell's fit; before that, 217, 214,
    203, 152, 144, the detector rejecting 23 valley markers of one view at 4 mm as small). Tolerance:
    >= 95 % in every frame."""
    c = dense_cell
    assert c["wrong_ids_sequence"] == 0
    assert min(c["matched_fraction_frames"]) >= 0.95


@pytest.fixture(scope="module")
def dense_narrower_cell():
    from benchmarks.experiments.sine import OMEGAS

    assert OMEGAS[2] == pytest.approx(math.pi / 5)
    return _cell("hexagon217_sep180", 2)


def test_press_sequence_of_the_dense_pattern_under_the_narrower_sine_keeps_touching_pins(dense_narrower_cell):
    """hexagon217_sep180 under z = 2.5·sin(π/5·x), which a single frame at 5 mm does not identify at all: at
    5 mm the crest pins of the right view touch or overlap in rows and the far flank's, seen obliquely, touch
    side by side; each must give its own blob, and each must be followed from the previous frame where the
    map bends over two spacings (the far flank) or the pins crowd along the crest only (the first shell's
    fit), or, where merged pins leave holes in the first shell, from the nearest followed markers. Measured
    with the design's friction: 217 of 217 in every frame, none wrong; the settled frame physically valid
    (0.019 mm inside) while every filmed one is flagged in motion (up to 0.089 mm: the lag the robot allows).
    Before the detector split crest pins that overlap in the image by their waist: 209 at 5 mm (settled, 207:
    the right view found 210 blobs, six crest pins merged in pairs, a touching pair rejected as one blob, a
    pin whose saturating core is taken for glare, one more not found; now 213). Settled, 206 before a pin at
    the narrowed scale space's lowest scale was sized again (one on the far flank fell under the size test);
    187 without the fit from the nearest followed markers; 215, 215, 215, 203 from 2 mm without the first
    frame's motion from rest as the second frame's velocity, two outer-ring pins of the left view lost; 184
    at 5 mm without any of the three. Frictionless, settled, on a plate covering the module: 217, 217, 217,
    217, 214 (before: 217, 217, 217, 216, 165 with a pin dropped to the response merged between it and its
    brighter neighbour and each oblique pair found as one blob; then 217, 217, 217, 216, 200 with ~16 blobs
    found but not followed, the fit over two shells refused). Tolerance: >= 95 % in every frame, every frame
    to 2 mm whole, none wrong, the settled frame valid."""
    c = dense_narrower_cell
    assert c["frame_depths_mm"] == pytest.approx([0, 1, 2, 3, 4, 5], abs=0.061)
    assert c["wrong_ids_sequence"] == 0
    assert c["matched_fraction_frames"][:3] == [1.0] * 3
    assert min(c["matched_fraction_frames"]) >= 0.95 and c["identified_to_mm"] == 5.0
    assert c["physics_valid"] and c["skin_penetration_mm"] <= 0.05
    assert c["filmed_penetration_max_mm"] > 0.05     # the frames in motion lag: they are never what is scored
