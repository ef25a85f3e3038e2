"""The certainty rule of marker identification (pipeline/vision/identity.py): no wrong id, ever.

Property-based (hypothesis, derandomized so that CI runs the same examples every time) over every
built-in marker pattern: random missing and spurious blobs (spurious ones also right next to
markers), a contiguous occluded patch, centre jitter up to 0.3 separations, in-plane rotation up
to +-30 deg, and stereo pairs of analytic presses with different defects in each view. The
generators are the identification benchmark's (benchmarks/experiments/identification.py), so the
tests and the benchmark's figures speak of the same trials. Over ~400 lines on purpose: the property
tests and the falsifying views they once drew (kept as regular tests) share the view generators here.
"""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from benchmarks.experiments.identification import PATTERN_DESIGNS, add_defects, run_trial, view_px
from pipeline.design import load_design
from pipeline.vision.dtrc import code_rings, match_stereo
from pipeline.vision.identity import (R_ANCHOR, R_ROTATION, REASONS, certify, lattice_of, rotation_limit_deg)
from pipeline.io.synthetic import nominal_calibration
from pipeline.types import Blobs

DESIGNS = {name: load_design(name) for name in PATTERN_DESIGNS}
FIXTURES = Path(__file__).resolve().parent / "data"
PROPERTY = settings(derandomize=True, database=None, max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])
seeds = st.integers(min_value=0, max_value=2**32 - 1)
designs = st.sampled_from(PATTERN_DESIGNS)


def _blobs(pts):
    return Blobs(np.ascontiguousarray(pts), np.full(len(pts), 3.0), np.ones(len(pts)))


def _wrong(ids, truth):
    coded = ids >= 0
    return int(np.sum(ids[coded] != truth[coded]))


@PROPERTY
@given(name=designs, seed=seeds, missing=st.floats(0.0, 0.12), spurious=st.floats(0.0, 0.12),
       rot=st.floats(-15.0, 15.0))
def test_no_wrong_id_under_missing_and_spurious_blobs(name, seed, missing, spurious, rot):
    design = DESIGNS[name]
    rng = np.random.default_rng(seed)
    pts, truth, _ = add_defects(view_px(design, rng, rot_deg=rot), rng, missing=missing, spurious=spurious)
    coding = code_rings(_blobs(pts), design)
    assert _wrong(coding.ids, truth) == 0
    assert len(coding.unmatched_reasons) == len(coding.unmatched_ids)


@PROPERTY
@given(name=designs, seed=seeds, rot=st.floats(-30.0, 30.0), jitter=st.floats(0.0, 0.3))
def test_no_wrong_id_under_rotation_and_jitter(name, seed, rot, jitter):
    design = DESIGNS[name]
    rng = np.random.default_rng(seed)
    pts, truth, _ = add_defects(view_px(design, rng, rot_deg=rot, jitter_sep=jitter), rng)
    assert _wrong(code_rings(_blobs(pts), design).ids, truth) == 0


@PROPERTY
@given(name=designs, seed=seeds, patch=st.floats(0.02, 0.2), missing=st.floats(0.0, 0.05))
def test_no_wrong_id_with_an_occluded_patch(name, seed, patch, missing):
    design = DESIGNS[name]
    rng = np.random.default_rng(seed)
    pts, truth, _ = add_defects(view_px(design, rng), rng, occlusion=patch, missing=missing, spurious=missing)
    assert _wrong(code_rings(_blobs(pts), design).ids, truth) == 0


def _occluded_view(name, seed):
    """The identification benchmark's occlusion_15 view of ``name`` drawn from a fresh generator ``seed``:
    (blobs, true id per blob, the ids whose design neighbours are all visible)."""
    from benchmarks.experiments.identification import _complete_neighbourhood

    rng = np.random.default_rng(seed)
    pts, truth, gone = add_defects(view_px(DESIGNS[name], rng), rng, occlusion=0.15)
    return pts, truth, _complete_neighbourhood(DESIGNS[name], gone)


def test_a_piece_read_shifted_from_the_rest_pattern_is_withdrawn():
    """hexagon217_sep180 pressed (an analytic Gaussian, 3 % missing + 3 % spurious blobs, the left view of trial 380 of
    the identification benchmark's press_first_frame stream), read with the rest pattern as its previous frame:
    ring coding's proposal holds a piece of 19 markers one step over from where they are, joined to the rest by a
    single bare edge whose rest end is a spurious blob read as marker 198. The only lattice shifts that lengthen that
    edge past the seam length carry the piece across the rest (a skin folded over itself: no explanation); the true
    reading collapses the edge, the piece's seam marker on the rest's own slot 198, which a blob at the seam that is
    not a marker explains. That shift stays open, so the piece is withdrawn and no id is wrong (a rule that counted
    only lengthened edges kept the piece, emitted all 19 wrong and cost the frame its rest reading)."""
    from pipeline.vision.dtrc.tracking import _aligned

    f = np.load(FIXTURES / "rest_read_piece_hexagon217_sep180.npz")
    design = DESIGNS[str(f["design"])]
    rest = (_aligned(np.ascontiguousarray(f["rest"]), f["xy"]), np.arange(len(f["rest"]), dtype=np.int64))
    coding = code_rings(_blobs(f["xy"]), design, previous=rest)
    assert _wrong(coding.ids, f["truth"]) == 0
    assert np.count_nonzero(coding.ids >= 0) >= 0.9 * np.count_nonzero(f["truth"] >= 0)


def test_a_corner_beyond_an_occluded_patch_is_not_read_as_the_skin_folded_over():
    """hexagon61 with the patch over the ring beside its lower-left corner (35, 37, 49-51, 57-60 hidden): the
    corner's four markers (15, 16, 17, 36) touch the rest only by two bare edges (15-14, 17-18). The lattice shifts
    that lengthen both edges past the seam length carry the corner across the rest onto the hidden slots (the view
    would show the skin's markers in reversed order across the seam); the one that collapses an edge (17 onto 18)
    lengthens the other across the rest too, so no one reading explains the seam either by rows crowded out or by
    blobs at the seam that are not markers. The corner is read, every marker with a complete neighbourhood
    identified."""
    pts, truth, complete = _occluded_view("hexagon61_sep354", 13)
    coding = code_rings(_blobs(pts), DESIGNS["hexagon61_sep354"])
    assert _wrong(coding.ids, truth) == 0
    assert {15, 16, 17, 36} <= set(coding.ids.tolist())
    assert set(complete.tolist()) <= set(coding.ids.tolist())
    assert np.count_nonzero(coding.ids >= 0) == np.count_nonzero(truth >= 0)


def test_an_outer_row_beyond_an_occluded_patch_is_read_along_itself():
    """square121 with the patch over its lower-left quadrant (57-63, 85-89, 104-108, 117, 118 hidden): the outer
    ring beyond it, 22-28 round the corner 25, is a strip one marker wide with the inner corner 60 beside it. Its
    markers have identified neighbours along the strip only, so the certainty rule has no map to test them
    against; read step by step along the column from 19-21 and along the row from 29-31, the strip is identified,
    the corner (whose design neighbours are all visible) with it, none wrong."""
    pts, truth, complete = _occluded_view("square121", 336)
    coding = code_rings(_blobs(pts), DESIGNS["square121"])
    assert _wrong(coding.ids, truth) == 0
    assert set(range(22, 29)) <= set(coding.ids.tolist())
    assert set(complete.tolist()) <= set(coding.ids.tolist())
    assert any("along their rows" in m for m in coding.messages)


def test_a_row_is_not_read_on_where_its_steps_change():
    """The same view's reading with the strip left open (the rule's own verdict): ``extend_rows`` reads all
    of it. With marker 19 moved a third of a step down the column (19-20 shorter than 20-21, as where pins crowd
    into a crest) the column no longer continues evenly, and 22-24, which only the column reaches, stay open;
    the row from 29-31 still reads 25-28."""
    from pipeline.vision.identity import R_NO_BLOB
    from pipeline.vision.identity.rows import extend_rows

    lat = lattice_of(DESIGNS["square121"])
    pts, truth, _ = _occluded_view("square121", 336)
    strip = np.isin(truth, np.arange(22, 29))
    ids = np.where(strip, -1, truth)
    reason = np.full(len(lat.xy), R_NO_BLOB)
    read = extend_rows(pts, ids, lat, reason.copy())
    np.testing.assert_array_equal(read, truth)
    moved = pts.copy()
    b19, b20 = np.flatnonzero(truth == 19)[0], np.flatnonzero(truth == 20)[0]
    moved[b19] += (moved[b20] - moved[b19]) / 3.0
    read = extend_rows(moved, ids, lat, reason.copy())
    assert _wrong(read, truth) == 0
    assert set(read.tolist()) & set(range(22, 29)) == {25, 26, 27, 28}


@pytest.mark.parametrize("name, fresh", [("square121", 300), ("hexagon217_sep180", 0), ("hexagon61_sep354", 200)])
def test_every_marker_with_a_complete_neighbourhood_beside_an_occluded_patch_is_identified_on_every_lattice(name, fresh):
    """The benchmark's occlusion_15 views of the translation lattices whose outer rows a patch can leave one marker
    wide: the first 200 of one generator's stream (as the benchmark draws them) and ``fresh`` views drawn from
    generators of their own. No wrong id, and every marker whose design neighbours are all visible gets its id.
    Before the rows were read, square121 left a corner marker open in stream view 82 and in 4 of the 300 fresh
    views, hexagon217 in stream view 159 (the corner 16 of an outer ring left two slots wide along one side);
    hexagon61, while the piece test counted a shift carrying a corner across the rest as an alternative, in stream
    views 116, 129 and 184 and in 7 of the 200 fresh views."""
    from benchmarks.experiments.identification import _complete_neighbourhood

    design = DESIGNS[name]
    rng = np.random.default_rng(0)
    views = []
    for k in range(200):
        pts, truth, gone = add_defects(view_px(design, rng), rng, occlusion=0.15)
        views.append((f"stream {k}", pts, truth, _complete_neighbourhood(design, gone)))
    views += [(f"fresh {seed}", *_occluded_view(name, seed)) for seed in range(fresh)]
    for which, pts, truth, complete in views:
        ids = code_rings(_blobs(pts), design).ids
        assert _wrong(ids, truth) == 0, which
        assert set(complete.tolist()) <= set(ids[ids >= 0].tolist()), which


@settings(derandomize=True, database=None, max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=designs, seed=seeds)
def test_no_wrong_id_in_an_occluded_first_frame_read_from_rest(name, seed):
    """The benchmark's occlusion_15_rest trial: a 15 % patch hidden, read as the runner reads a first frame
    (ring coding, then the rest pattern as the previous frame): no wrong id."""
    assert run_trial(DESIGNS[name], "occlusion_15_rest", np.random.default_rng(seed))["wrong"] == 0


def _centre_hidden_view(turn_deg, bulge=0.15, hidden=0.15, whole=False):
    """circular217_dome's rest view (px) turned by ``turn_deg``, bulged by up to ``bulge`` about the centre,
    with the ``hidden`` fraction of its markers nearest the centre hidden (a glare spot over the middle of
    the skin): (blobs, true id per blob); with ``whole``, (every marker's position, the ids shown)."""
    from benchmarks.experiments.identification import rest_px

    rest = rest_px(DESIGNS["circular217_dome"])
    centre = rest.mean(axis=0)
    t = np.radians(turn_deg)
    r = rest - centre
    uv = centre + (r * (1 + bulge * np.exp(-(np.hypot(*r.T) / (0.5 * np.hypot(*r.T).max())) ** 2))[:, None]) @ \
        np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T
    gone = np.argsort(np.hypot(*(uv - centre).T))[:int(round(hidden * len(uv)))]
    keep = np.setdiff1d(np.arange(len(uv)), gone)
    return (uv, keep) if whole else (uv[keep], keep)


@pytest.mark.parametrize("turn_deg", [-15.0, -8.0, -3.75, 0.0, 2.0, 7.5, 12.0, 15.0])
def test_a_circular_view_without_its_centre_is_read_from_the_rings_about_it(turn_deg):
    """circular217_dome with the 15 % of its markers nearest the centre hidden (rings 0-2 and most of ring 3),
    turned by up to the 15 deg the identification benchmark draws: each outer ring alone fixes the turn only
    modulo its pitch (7.5 deg for the 48 markers of ring 8), the rings together fix it, and three rings
    further out, concentric and not twisted against each other, centre the reading. Every visible marker
    gets its id and none is wrong."""
    pts, truth = _centre_hidden_view(turn_deg)
    ids = code_rings(_blobs(pts), DESIGNS["circular217_dome"]).ids
    assert _wrong(ids, truth) == 0
    assert np.count_nonzero(ids >= 0) == len(pts)


@pytest.mark.parametrize("turn", [-2, -1, 1, 2])
def test_a_reading_of_the_rings_about_a_hidden_centre_turned_ring_by_ring_is_refused(turn):
    """The same view (turned 5 deg) proposed with every ring turned by ``turn`` slots, the one reading its
    neighbourhoods barely tell from the true one (rings 7 and 8 turned by one slot each differ by 1.07 deg):
    the rings' affine maps turn apart by 2 pi (1 / n_k - 1 / n_k+2) more than the true reading's, and
    nothing is certified; the true reading is certified whole."""
    from pipeline.vision.identity.lattice import RING_TWIST

    design = DESIGNS["circular217_dome"]
    lat = lattice_of(design)
    pts, truth = _centre_hidden_view(5.0)
    twist = lat.alt[[k for k, name in enumerate(lat.alt_names) if name == f"{RING_TWIST} {turn:+d} slot(s)"][0]]
    assert np.count_nonzero(certify(pts, twist[truth], lat) >= 0) == 0
    np.testing.assert_array_equal(certify(pts, truth.copy(), lat), truth)


@PROPERTY
@given(seed=seeds, turn=st.floats(-15.0, 15.0), hidden=st.floats(0.03, 0.25), defects=st.floats(0.0, 0.05))
def test_no_wrong_id_with_the_centre_of_a_circular_view_hidden(seed, turn, hidden, defects):
    """circular217_dome, the hidden patch about the centre from 3 % to 25 % of the markers, random missing
    and spurious blobs beside it: no wrong id."""
    rng = np.random.default_rng(seed)
    uv, shown = _centre_hidden_view(turn, bulge=float(rng.uniform(0, 0.15)), hidden=hidden, whole=True)
    # as in the benchmark, no spurious blob within half a separation of a hidden or missing marker
    pts, truth, _ = add_defects(uv, rng, missing=defects, spurious=defects,
                                hidden=np.setdiff1d(np.arange(len(uv)), shown))
    assert _wrong(code_rings(_blobs(pts), DESIGNS["circular217_dome"]).ids, truth) == 0


def test_a_first_frame_with_its_centre_hidden_is_read_from_rest():
    """The view above turned 2 deg against the rest pattern, read from rest with ring coding's reading
    withheld: every visible marker lies 0.23 separations or more from its rest position, beyond the
    frame-to-frame map's bootstrap gate; brought onto the view by an affine fit first (read_from_rest),
    the rest pattern gives every visible marker its id and none is wrong."""
    from dataclasses import replace

    from benchmarks.experiments.identification import rest_px
    from pipeline.vision.dtrc import read_from_rest

    design = DESIGNS["circular217_dome"]
    rest = rest_px(design)
    pts, truth = _centre_hidden_view(2.0)
    coding = code_rings(_blobs(pts), design)
    withheld = replace(coding, ids=np.full(len(pts), -1, np.int64), carried=None)
    ids = read_from_rest(_blobs(pts), design, withheld, (rest, np.arange(len(rest), dtype=np.int64))).ids
    assert _wrong(ids, truth) == 0
    assert np.count_nonzero(ids >= 0) == len(pts)


def _occluded_first_frame(name, seed):
    """The identification benchmark's occlusion_15_rest view of ``name`` drawn from ``seed``: (blobs, true id
    per blob, the ids whose design neighbours are all visible, the rest pattern in px)."""
    from benchmarks.experiments.identification import (BASE_JITTER_SEP, REST_TURN_DEG, _complete_neighbourhood,
                                                       add_defects, rest_px, view_px)

    design = DESIGNS[name]
    rng = np.random.default_rng(seed)
    uv = view_px(design, rng, rot_deg=rng.uniform(-REST_TURN_DEG, REST_TURN_DEG), jitter_sep=BASE_JITTER_SEP,
                 perspective=False)
    pts, truth, gone = add_defects(uv, rng, occlusion=0.15)
    return pts, truth, _complete_neighbourhood(design, gone), rest_px(design)


def test_a_first_frame_ring_coding_reads_is_completed_from_rest():
    """square121 with a 15 % patch hidden at its rim: ring coding identifies over 90 % of the view (the outer
    row beyond the patch along its rows) but leaves open a marker beside the patch. The rest pattern's reading
    gives every blob ring coding identified the same id and identifies that marker too, so it is taken:
    every marker identified, none wrong."""
    from pipeline.vision.dtrc import read_from_rest

    design = DESIGNS["square121"]
    pts, truth, complete, rest = _occluded_first_frame("square121", 58)
    coding = code_rings(_blobs(pts), design)
    coded = coding.ids >= 0
    assert 0.9 * len(pts) <= np.count_nonzero(coded) < len(pts)
    ids = read_from_rest(_blobs(pts), design, coding, (rest, np.arange(len(rest), dtype=np.int64))).ids
    assert np.array_equal(ids[coded], coding.ids[coded])
    assert _wrong(ids, truth) == 0
    assert set(complete.tolist()) <= set(ids[ids >= 0].tolist())
    assert np.count_nonzero(ids >= 0) == len(pts)


@pytest.mark.parametrize("shift", [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.5, 0.0)])
def test_a_first_frame_read_from_a_wrong_rest_pattern_keeps_ring_codings_ids(shift):
    """The same view with the rest pattern off by a whole separation (or half of one: a calibration wrong by
    that much): the rest reading adds nothing ring coding had not certified, and no id is wrong."""
    from benchmarks.experiments.identification import PX_PER_SEP
    from pipeline.vision.dtrc import read_from_rest

    design = DESIGNS["square121"]
    pts, truth, _, rest = _occluded_first_frame("square121", 58)
    coding = code_rings(_blobs(pts), design)
    shifted = rest + PX_PER_SEP * np.asarray(shift)
    ids = read_from_rest(_blobs(pts), design, coding, (shifted, np.arange(len(rest), dtype=np.int64))).ids
    assert np.array_equal(ids, coding.ids)
    assert _wrong(ids, truth) == 0


@settings(derandomize=True, database=None, max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=designs, seed=seeds)
def test_no_wrong_pair_in_pressed_stereo_views_with_different_defects(name, seed):
    design = DESIGNS[name]
    rec = run_trial(design, "press_stereo", np.random.default_rng(seed), nominal_calibration(design))
    assert rec["wrong"] == 0


@settings(derandomize=True, database=None, max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=designs, seed=seeds)
def test_no_wrong_pair_in_a_pressed_first_frame_read_as_the_runner_reads_it(name, seed):
    design = DESIGNS[name]
    rec = run_trial(design, "press_first_frame", np.random.default_rng(seed), nominal_calibration(design))
    assert rec["wrong"] == 0


# trial 956 of the benchmark's circular217_dome press_first_frame stream (seed 0): the generator's state before it
_AMBIGUOUS_SLOT_TRIAL = {"bit_generator": "PCG64", "state": {"state": 334678701277411116790805303987063991864,
                                                             "inc": 230820474182415846913427658499246408031},
                         "has_uint32": 1, "uinteger": 90625060}


def test_a_first_frame_read_from_rest_leaves_open_what_ring_coding_found_ambiguous(monkeypatch):
    """circular217 pressed 4.4 mm (sigma 3.8 mm, 3.3 mm off the axis): in the right view ring coding leaves marker
    166 open, a spurious blob standing 0.33 separations from it ("two blobs near its predicted position"). The
    reading from the rest pattern, which extends ring coding's, must not settle that slot: it gave the spurious
    blob the id, and the stereo check kept the pair with the left view's marker 166. 199 of the 203 markers present
    in both views are paired (200 before an id the rest pattern's motion alone gave was left open where another free
    blob near it meets the other view's marker too, ``pipeline.cross_view._motion_settled``, which also leaves the
    spurious blob's id open where the reading from rest is let settle the slot)."""
    import importlib

    tracking = importlib.import_module("pipeline.vision.dtrc.tracking")
    design = DESIGNS["circular217_dome"]
    calib = nominal_calibration(design)

    def trial():
        rng = np.random.default_rng()
        rng.bit_generator.state = _AMBIGUOUS_SLOT_TRIAL
        return run_trial(design, "press_first_frame", rng, calib)

    rec = trial()
    assert rec["wrong"] == 0 and rec["correct"] >= 199 and rec["present"] == 203
    monkeypatch.setattr(tracking, "_keep_ambiguous", lambda coding, again: again)
    assert trial()["wrong"] == 0            # the id the rest pattern's motion gave is left open across the views
    monkeypatch.setattr(importlib.import_module("pipeline.cross_view"), "_motion_settled", lambda pts, coding, *a: coding)
    assert trial()["wrong"] == 1


def test_a_pressed_circular_first_frame_is_read_from_the_rest_pattern_where_ring_coding_reads_nothing():
    """circular217 pressed 5 mm by a sigma 3 mm Gaussian off the axis (0.2 lateral bulge, 3 % + 3 % defects a view):
    ring coding anchors a circular pattern by its first three rings, which the press bends beyond its gates, and
    pairs none of the 203 markers present in both views; the runner reading it as a sequence's first frame (the
    rest pattern where ring coding leaves a view short, then the stereo check) pairs 192, none wrong."""
    from benchmarks.experiments.identification import score_pairs, stereo_views_with_defects
    from pipeline.geometry.refraction import project_through_stack
    from pipeline.io.synthetic import gaussian_press_markers
    from pipeline.runner import Reconstructor

    design = DESIGNS["circular217_dome"]
    calib = nominal_calibration(design)
    rng = np.random.default_rng(0)
    centre = (float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)))
    xyz = gaussian_press_markers(design, 5.0, sigma_mm=3.0, centre_xy_mm=centre, lateral=0.2)
    sides = stereo_views_with_defects(project_through_stack(xyz, calib, design), rng, 0.03)
    left, right = _blobs(sides[0][0]), _blobs(sides[1][0])
    ring = score_pairs(match_stereo(left, right, design), sides)
    first = score_pairs(Reconstructor(design, calib, view_threads=1).identify(left, right), sides)
    assert ring["correct"] == ring["wrong"] == 0 and first["present"] == 203
    assert first["wrong"] == 0 and first["correct"] >= 0.9 * first["present"]


@pytest.mark.parametrize("name", ["hexagon127", "square121", "circular217_dome"])
def test_a_reading_shifted_along_the_lattice_or_turned_past_the_limit_is_withdrawn(name):
    """Locally perfect but globally wrong readings: the true reading moved by one ring-1 step (a
    lattice shift; on a circular pattern a reading centred on a ring-1 marker) is not anchored;
    the true reading of a pattern turned by half its symmetry angle is ambiguous."""
    design = DESIGNS[name]
    lat = lattice_of(design)
    rng = np.random.default_rng(4)
    uv = view_px(design, rng, rot_deg=3.0)
    truth = np.arange(len(uv))
    reason = np.zeros(len(uv), np.int64)
    assert np.array_equal(certify(uv, truth, lat, reason), truth)   # the truth itself is certain
    centre = int(np.flatnonzero(lat.layer_of == 0)[0])
    step = lat.xy[int(np.flatnonzero(lat.layer_of == 1)[0])] - lat.xy[centre]
    from scipy.spatial import cKDTree

    d, shifted = cKDTree(lat.xy).query(lat.xy + step)
    prop = np.where(d < 0.5 * lat.pitch, shifted, -1)
    u, cnt = np.unique(prop[prop >= 0], return_counts=True)
    prop[np.isin(prop, u[cnt > 1])] = -1
    reason = np.zeros(len(uv), np.int64)
    out = certify(uv, prop, lat, reason)
    assert np.all(out[out >= 0] == truth[out >= 0])           # whatever survives is right ...
    assert np.count_nonzero(out >= 0) == 0                    # ... and nothing does
    turned = view_px(design, rng, rot_deg=lat.alpha_deg / 2)
    reason = np.zeros(len(uv), np.int64)
    assert np.count_nonzero(certify(turned, truth, lat, reason) >= 0) == 0
    assert set(reason[reason > 0]) <= {R_ROTATION, R_ANCHOR}
    assert rotation_limit_deg(lat) >= 15.0


def test_unmatched_ids_carry_their_reasons():
    design = DESIGNS["hexagon127"]
    rng = np.random.default_rng(9)
    uv = view_px(design, rng)
    drop = np.array([3, 40, 90])
    keep = np.setdiff1d(np.arange(len(uv)), drop)
    ghost = uv[60] + np.array([0.3, 0.0]) * 36.0 * 0.2   # 0.06 separations from marker 60: ambiguous
    coding = code_rings(_blobs(np.vstack([uv[keep], ghost])), design)
    reasons = dict(zip(coding.unmatched_ids.tolist(), coding.unmatched_reasons))
    for i in drop:
        assert reasons[int(i)] == REASONS[1]                  # "no blob at its predicted position"
    assert "two blobs" in reasons[60]
    assert coding.ids[-1] == -1


@pytest.mark.parametrize("name", PATTERN_DESIGNS)
def test_coverage_at_three_percent_missing_and_spurious(name):
    """The coverage target: >= 99 % of the present markers identified with 3 % missing + 3 %
    spurious blobs (mean of 12 seeded trials; the benchmark runs 1000)."""
    design = DESIGNS[name]
    rng = np.random.default_rng(123)
    cov = []
    for _ in range(12):
        pts, truth, _ = add_defects(view_px(design, rng), rng, missing=0.03, spurious=0.03)
        ids = code_rings(_blobs(pts), design).ids
        assert _wrong(ids, truth) == 0
        cov.append(np.count_nonzero((ids >= 0) & (ids == truth)) / np.count_nonzero(truth >= 0))
    assert np.mean(cov) >= 0.99


def test_stereo_pairs_only_ids_certain_in_both_views():
    design = DESIGNS["hexagon127"]
    rng = np.random.default_rng(17)
    left, right = view_px(design, rng), view_px(design, rng) + np.array([-20.0, 0.0])
    pl, tl, _ = add_defects(left, rng, missing=0.05)
    pr, tr, _ = add_defects(right, rng, missing=0.05)
    m = match_stereo(_blobs(pl), _blobs(pr), design)
    present = np.intersect1d(tl[tl >= 0], tr[tr >= 0])
    assert set(m.ids.tolist()) <= set(present.tolist())
    np.testing.assert_array_equal(m.left_px, left[m.ids])
    np.testing.assert_array_equal(m.right_px, right[m.ids])
    assert len(m.ids) >= 0.95 * len(present)


@pytest.mark.parametrize("name", ["hexagon127", "circular217_dome"])
@pytest.mark.parametrize("step_sep", [0.2, 0.8])
def test_tracker_proposes_previous_ids_without_ever_relabelling(name, step_sep):
    """A sequence: a clean frame, then the pattern moved by ``step_sep`` separations with 8 %
    missing + 8 % spurious blobs in each view. Ids carried from the previous frame are proposals:
    a small step carries them to the right blobs, a step of 0.8 separations carries every id to a
    neighbour (the nearest-neighbour tracker's failure), and the certainty rule must withdraw those.
    """
    from pipeline.vision.dtrc import DTRCTracker, carry_ids

    design = DESIGNS[name]
    rng = np.random.default_rng(21)
    tracker = DTRCTracker(design)
    left0, right0 = view_px(design, rng, rot_deg=2.0), view_px(design, rng, rot_deg=2.0) - [25.0, 0.0]
    m0 = tracker.update(_blobs(left0), _blobs(right0))
    np.testing.assert_array_equal(m0.ids, np.arange(len(left0)))
    shift = np.array([step_sep * 36.0, 0.0])
    pl, tl, _ = add_defects(left0 + shift, rng, missing=0.08, spurious=0.08)
    pr, tr, _ = add_defects(right0 + shift, rng, missing=0.08, spurious=0.08)
    carried = carry_ids(left0, np.arange(len(left0)), pl)
    if step_sep > 0.5:
        assert np.count_nonzero((carried >= 0) & (carried != tl)) > 0.3 * len(left0)  # wrong proposals
    m1 = tracker.update(_blobs(pl), _blobs(pr))
    lookup_l = {tuple(p): t for p, t in zip(pl.tolist(), tl.tolist())}
    lookup_r = {tuple(p): t for p, t in zip(pr.tolist(), tr.tolist())}
    assert all(lookup_l[tuple(a)] == i and lookup_r[tuple(b)] == i
               for i, a, b in zip(m1.ids.tolist(), m1.left_px.tolist(), m1.right_px.tolist()))
    present = np.intersect1d(tl[tl >= 0], tr[tr >= 0])
    assert len(m1.ids) >= 0.9 * len(present)


def _pressed_view(name, depth_mm, sigma_mm, lateral, centre_xy_mm=(0.0, 0.0)):
    """The left view (px, canonical id order) of an analytic Gaussian press (centred at ``centre_xy_mm``)
    through the nominal calibration and the refracting stack."""
    from pipeline.geometry.refraction import project_through_stack
    from pipeline.io.synthetic import gaussian_press_markers

    design = DESIGNS[name]
    xyz = gaussian_press_markers(design, depth_mm, sigma_mm=sigma_mm, lateral=lateral, centre_xy_mm=centre_xy_mm)
    return np.ascontiguousarray(project_through_stack(xyz, nominal_calibration(design), design)[0])


def _without_fans(lat):
    from pipeline.vision.identity import Lattice

    return Lattice(**{**lat.__dict__, "fan": np.full_like(lat.fan, -1)})


@pytest.mark.parametrize("name, sigma_mm, lateral", [("hexagon127", 1.3, 0.3), ("hexagon127", 1.3, 0.6),
                                                     ("square121", 1.3, 0.6), ("hexagon217_sep180", 2.0, 0.3)])
def test_deformed_but_complete_neighbourhoods_are_certified(name, sigma_mm, lateral):
    """A 5 mm press of a sharp Gaussian crowds and shears the markers near its tip so strongly that
    the leave-one-out affine fits withdraw correct ids (the twin's pressed frames lost 3-14 markers
    per view that way). The markers are all there and each one's design fan is intact in the image:
    the fan test certifies the true reading whole, and ring coding of the view emits no wrong id."""
    design = DESIGNS[name]
    lat = lattice_of(design)
    uv = _pressed_view(name, 5.0, sigma_mm, lateral)
    truth = np.arange(len(uv))
    loo_only = certify(uv, truth, _without_fans(lat), np.zeros(len(uv), np.int64))
    assert np.count_nonzero(loo_only >= 0) < len(uv)                 # the affine fits alone withdraw some
    assert np.array_equal(certify(uv, truth, lat, np.zeros(len(uv), np.int64)), truth)
    ids = code_rings(_blobs(uv), design).ids
    assert _wrong(ids, truth) == 0
    assert np.count_nonzero(ids >= 0) >= np.count_nonzero(loo_only >= 0)


@settings(derandomize=True, database=None, max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(seed=seeds, name=st.sampled_from(["hexagon127", "square121", "hexagon217_sep180"]),
       sigma=st.floats(1.0, 2.5), lateral=st.floats(0.0, 0.6), rate=st.floats(0.0, 0.1))
def test_no_wrong_id_in_sharply_pressed_views_with_defects(seed, name, sigma, lateral, rate):
    """The fan test under defects: sharply pressed views (5 mm, sigma 1-2.5 mm) with missing and
    spurious blobs (spurious also right next to markers near the tip) never give a wrong id.
    Views where two markers converge to less than half the median separation are out of scope:
    such pins touch and merge in detection, and with one of them missing the other sits where
    the missing one should be (indistinguishable, as in the benchmark's notes)."""
    pts, truth, in_scope = _pressed_view_with_defects(seed, name, sigma, lateral, rate)
    assume(in_scope)
    assert _wrong(code_rings(_blobs(pts), DESIGNS[name]).ids, truth) == 0


def _pressed_view_with_defects(seed, name, sigma, lateral, rate, centre_xy_mm=(0.0, 0.0)):
    """A view pressed 5 mm by a Gaussian (sigma mm, lateral bulge, centred at ``centre_xy_mm``) with ``rate``
    missing and spurious blobs drawn from ``seed``: (blobs, true id per blob, whether the view is in the
    property's scope: no two markers closer than half the median separation)."""
    from benchmarks.identity_search import pressed_view

    return pressed_view(DESIGNS[name], seed, sigma, lateral, rate, centre_xy_mm)


def _dense_view_with_defects():
    """hexagon217_sep180 pressed 5 mm by a sigma 1.0 mm Gaussian (left view), 8.2 % missing + 8.2 %
    spurious blobs (defect seed 17782): (blobs, true id per blob)."""
    pts, truth, _ = _pressed_view_with_defects(17782, "hexagon217_sep180", 1.0, 0.0, 0.082)
    return pts, truth


def test_no_wrong_id_in_a_sharply_pressed_dense_view_with_defects():
    """A falsifying example the property test above once drew (nearest pair 0.68 of the median
    separation). The centre pin, pressed 4 mm deeper than its six neighbours, shows 0.36 separations
    off their affine prediction in the oblique view, and a spurious blob stands 0.15 separations from
    that prediction, 0.5 from the pin: the spurious blob must not take the centre's id (it did,
    199 of 217 identified, one wrong), and the rest of the view is still identified."""
    pts, truth = _dense_view_with_defects()
    ids = code_rings(_blobs(pts), DESIGNS["hexagon217_sep180"]).ids
    assert _wrong(ids, truth) == 0
    assert np.count_nonzero(ids >= 0) >= 198


def _assert_no_wrong_id_in_scope(seed, name, sigma, lateral, rate):
    """The property above on one view it drew: in scope, no wrong id, and at least 85 % of the present
    markers identified."""
    pts, truth, in_scope = _pressed_view_with_defects(seed, name, sigma, lateral, rate)
    assert in_scope
    ids = code_rings(_blobs(pts), DESIGNS[name]).ids
    assert _wrong(ids, truth) == 0
    assert np.count_nonzero(ids >= 0) >= 0.85 * np.count_nonzero(truth >= 0)


def test_the_half_way_registration_is_a_first_frames_search(monkeypatch):
    """The placements anchored half-way out cost 35-90 ms a view where they run: a view read below 90 %
    with no id carried from a previous frame (a first frame) tries them; the same view with the previous
    frame's ids carried does not (a crowded sequence would pay it every frame)."""
    import pipeline.vision.dtrc.proposals as proposals

    calls = []
    real = proposals.register_seed

    def spy(pts, lat, **kw):
        calls.append(bool(kw.get("spread")))
        return real(pts, lat, **kw)

    monkeypatch.setattr(proposals, "register_seed", spy)
    seed, name, *_ = _CROWDED_MIDDLE_VIEWS[0]
    pts, truth, _ = _pressed_view_with_defects(*_CROWDED_MIDDLE_VIEWS[0])
    first = code_rings(_blobs(pts), DESIGNS[name])
    assert True in calls
    calls.clear()
    known = first.ids >= 0
    code_rings(_blobs(pts), DESIGNS[name], previous=(pts[known][:20], first.ids[known][:20]))
    assert True not in calls


# views a wider local search of the property above found (defect seed, pattern, sigma, lateral, rate);
# in each, a slot near the tip predicted from one side only (two or three of its six immediate
# neighbours identified) had its real pin 0.41-0.48 separations off the extrapolated prediction,
# while another blob stood within 0.15 of it: its inner neighbour's pin (first four) or a spurious
# blob (the last, the centre slot)
_EXTRAPOLATED_VIEWS = [(3977083489, "hexagon217_sep180", 2.2163, 0.4401, 0.0151),
                       (3117160162, "hexagon217_sep180", 2.1723, 0.4092, 0.0329),
                       (1541645081, "hexagon217_sep180", 2.1557, 0.4466, 0.0248),
                       (4011403959, "hexagon217_sep180", 2.1010, 0.4359, 0.0215),
                       (3792783512, "hexagon217_sep180", 1.0712, 0.3201, 0.0525)]


@pytest.mark.parametrize("seed, name, sigma, lateral, rate", _EXTRAPOLATED_VIEWS)
def test_no_wrong_id_where_a_prediction_is_extrapolated_towards_a_press_tip(seed, name, sigma, lateral, rate):
    """An affine prediction extrapolated across a wide gap errs more the farther the slot lies from
    its identified neighbours (the press crowds the pins ahead): a free blob within the widened reach
    competes for the slot, which is then left open rather than given to the wrong blob."""
    _assert_no_wrong_id_in_scope(seed, name, sigma, lateral, rate)


# views a wider search with other draws found (numpy default_rng(20261125), 4,000 draws, 2,755 in scope,
# with both competing-blob reaches): 6 wrong ids in 6 views, each a slot near the tip whose marker is
# missing (or, in the second and fourth, present but crowded 0.5-0.9 of the median separation from its
# neighbours) given to another blob 0.40-0.75 separations from the marker's true position: a spurious
# blob (first four) or its outer neighbour's pin, slot 210 read as 198 (last two).
_MISSING_SLOT_VIEWS = [(2161590097, "hexagon217_sep180", 1.0517, 0.3463, 0.0419),
                       (2361457184, "square121", 2.4059, 0.3268, 0.0726),
                       (594499511, "hexagon217_sep180", 2.1096, 0.4038, 0.0614),
                       (1858549753, "hexagon217_sep180", 2.1746, 0.4301, 0.0785)]
# views of a later search of the same space (4,000 draws, 2,755 in scope), found with the placements
# anchored half-way out: a spurious blob 0.01-0.33 separations from the prediction of a slot near the tip
# (its marker missing, or present 0.32-0.36 off), with every or all but two of the slot's neighbours
# identified (the last: one of the views that ring coding alone left without any id)
_NEAR_PREDICTION_VIEWS = [(1218274663, "square121", 1.1246, 0.3664, 0.0937),
                          (498893891, "hexagon127", 1.2151, 0.1206, 0.0271),
                          (4090610520, "hexagon217_sep180", 1.3734, 0.1955, 0.0996)]
# Four of them stay wrong: the slot's marker missing, nothing else within a separation of its prediction,
# and the blob that takes it where a displaced pin would sit (both square121 views, hexagon217_sep180); and
# the centre of a hexagon127 view whose six neighbours fit an affine map to 0.012 separations, with a
# spurious blob 0.007 from the prediction and the deepest pin of the press 0.27 off it (a bend the
# neighbourhood does not show).
_UNDECIDED_SLOT_VIEWS = [_MISSING_SLOT_VIEWS[1], _MISSING_SLOT_VIEWS[3], *_NEAR_PREDICTION_VIEWS[:2]]
# one more such view, in which ring coding read 174 of 196 markers, one wrong: the placements anchored
# half-way out (``register_seed(spread=True)``, tried below 90 %) certify 182, and that reading, the
# largest, leaves the slot open. The slot's case is not settled by a rule, only outread.
_MISSING_SLOT_VIEW_OUTREAD = (2884193572, "hexagon217_sep180", 2.4579, 0.2771, 0.0947)


def test_a_view_whose_wrong_id_a_larger_reading_leaves_out():
    _assert_no_wrong_id_in_scope(*_MISSING_SLOT_VIEW_OUTREAD)


# and one in which the spurious blob took slot 207 (its marker missing) with two of the slot's six
# neighbours identified
_THINLY_HELD_VIEW = (1301021084, "hexagon217_sep180", 2.2615, 0.3363, 0.0270)


def test_an_interior_id_held_by_two_identified_neighbours_is_withdrawn():
    """An interior marker needs three of its immediate design neighbours identified to keep its id
    (``HELD_BY``): the spurious blob's slot is left open, with that reason, and the rest of the view
    is identified."""
    from pipeline.vision.identity import REASONS
    from pipeline.vision.identity.constants import R_FEW

    _assert_no_wrong_id_in_scope(*_THINLY_HELD_VIEW)
    seed, name, *_ = _THINLY_HELD_VIEW
    coding = code_rings(_blobs(_pressed_view_with_defects(*_THINLY_HELD_VIEW)[0]), DESIGNS[name])
    assert REASONS[R_FEW] == dict(zip(coding.unmatched_ids.tolist(), coding.unmatched_reasons))[207]


@pytest.mark.parametrize("seed, name, sigma, lateral, rate",
                         [v for v in (*_MISSING_SLOT_VIEWS, *_NEAR_PREDICTION_VIEWS) if v not in _UNDECIDED_SLOT_VIEWS])
def test_no_wrong_id_where_a_slot_near_the_tip_lost_its_marker(seed, name, sigma, lateral, rate):
    """Near a sharp tip the neighbourhood bends, and the bend its leave-one-out residuals show displaces
    the slot's own pin too: a free blob within the growth gate widened by that bend (as far as the bend
    may displace the pin) is a rival for the slot, which the certified reading leaves open
    (``certify._unrivalled``). No wrong id, most of the view read."""
    _assert_no_wrong_id_in_scope(seed, name, sigma, lateral, rate)


@pytest.mark.xfail(strict=True, reason="known wrong ids: a slot near a sharp press tip whose marker is missing "
                   "(or displaced by a bend its neighbours do not show) taken by the one blob near its prediction")
@pytest.mark.parametrize("seed, name, sigma, lateral, rate", _UNDECIDED_SLOT_VIEWS)
def test_no_wrong_id_where_nothing_competes_for_a_slot_near_the_tip(seed, name, sigma, lateral, rate):
    """The property above on the four views no rule of a single view settles: no wrong id."""
    pts, truth, in_scope = _pressed_view_with_defects(seed, name, sigma, lateral, rate)
    assert in_scope
    assert _wrong(code_rings(_blobs(pts), DESIGNS[name]).ids, truth) == 0


# circular217_dome views of a search of sharper and farther off-axis presses than the identification
# benchmark's (5,000 draws: sigma 1-5 mm, centre up to 6 mm off the axis, lateral bulge 0-0.6, 0-10 % missing
# and spurious blobs; 3,881 in scope, 21.9 % of their markers identified): one wrong id in each once
_OFF_AXIS_CIRCULAR_VIEWS = [(4081341151, 1.0855, 0.1260, 0.0262, (2.0699, -1.4722)),
                            (4068980117, 2.3353, 0.4554, 0.0145, (-0.6122, -5.4672)),
                            (3263411013, 1.7301, 0.2942, 0.0065, (2.0789, -2.0529)),
                            (2505379748, 1.8715, 0.4586, 0.0203, (-2.1424, -5.4759)),
                            (3946439973, 1.0768, 0.2365, 0.0819, (3.0347, -4.4807)),
                            (2685176651, 1.6003, 0.0727, 0.0772, (5.2454, -3.2993)),
                            (2958509890, 1.4968, 0.5346, 0.0050, (-0.7799, -4.3543))]


# and a view of the seed-777 search below pressed by a sigma 1.15 mm tip almost on the axis, read from the rings
# about its crowded centre: a spurious blob 0.09 separations from the centre slot's prediction took it, with the
# centre pin 0.46 off (its three identified neighbours' residuals up to 0.29)
_NEAR_AXIS_CIRCULAR_VIEW = (224097057, 1.1466, 0.2132, 0.0184, (-0.0164, -0.1358))


def test_a_rival_displaced_by_the_bend_leaves_the_centre_open(monkeypatch):
    """The near-axis view: the certified reading gives the centre slot to a spurious blob 0.09 separations from
    its prediction, while the centre pin stands 0.46 off, beyond the growth gate, with its three identified
    neighbours' residuals up to 0.29. That pin is a rival within the bend-widened gate: the centre is left open
    with that reason and nothing else is withdrawn (without the test, the same reading with one wrong id)."""
    import importlib

    from pipeline.vision.identity.constants import R_AMBIGUOUS

    certify_module = importlib.import_module("pipeline.vision.identity.certify")
    design = DESIGNS["circular217_dome"]
    seed, sigma, lateral, rate, centre = _NEAR_AXIS_CIRCULAR_VIEW
    pts, truth, _ = _pressed_view_with_defects(seed, "circular217_dome", sigma, lateral, rate, centre)
    coding = code_rings(_blobs(pts), design)
    centre_id = design.marker_count - 1
    assert REASONS[R_AMBIGUOUS] == dict(zip(coding.unmatched_ids.tolist(), coding.unmatched_reasons))[centre_id]
    assert _wrong(coding.ids, truth) == 0 and centre_id not in coding.ids.tolist()
    monkeypatch.setattr(certify_module, "_unrivalled", lambda pts, slot_of, lat, reason: slot_of)
    unguarded = code_rings(_blobs(pts), design).ids
    wrong = (unguarded >= 0) & (unguarded != truth)
    assert unguarded[wrong].tolist() == [centre_id] and truth[wrong].tolist() == [-1]
    assert np.count_nonzero(unguarded >= 0) == np.count_nonzero(coding.ids >= 0) + 1


# two of the seven gave an interior slot held by one identified immediate neighbour of six a blob 0.19 separations
# off its prediction, its own pin 0.69 off or absent
_THINLY_HELD_CIRCULAR_VIEWS = [_OFF_AXIS_CIRCULAR_VIEWS[2], _OFF_AXIS_CIRCULAR_VIEWS[5]]


@pytest.mark.parametrize("seed, sigma, lateral, rate, centre",
                         [v for v in (*_OFF_AXIS_CIRCULAR_VIEWS, _NEAR_AXIS_CIRCULAR_VIEW)
                          if v not in _THINLY_HELD_CIRCULAR_VIEWS])
def test_no_wrong_id_in_a_circular_view_pressed_sharply_off_the_axis(seed, sigma, lateral, rate, centre):
    """The property on circular views the benchmark's presses do not reach: no wrong id, and most of the
    view read. Each once gave one wrong id: a blob on a slot's prediction in a bent neighbourhood while
    the slot's pin stood just beyond the growth gate, now a rival that leaves the slot open."""
    pts, truth, in_scope = _pressed_view_with_defects(seed, "circular217_dome", sigma, lateral, rate, centre)
    assert in_scope
    ids = code_rings(_blobs(pts), DESIGNS["circular217_dome"]).ids
    assert _wrong(ids, truth) == 0
    assert np.count_nonzero(ids >= 0) >= 0.85 * np.count_nonzero(truth >= 0)


@pytest.mark.parametrize("view, slot, read", [(_THINLY_HELD_CIRCULAR_VIEWS[0], 197, 207),
                                              (_THINLY_HELD_CIRCULAR_VIEWS[1], 178, 193)])
def test_an_interior_circular_id_held_by_one_identified_neighbour_is_withdrawn(view, slot, read):
    """An interior marker of a circular pattern keeps its id only with two of its immediate design neighbours
    identified (``HELD_BY_RINGS``; the markers about a hidden centre keep theirs along their rings). In each view a
    blob took an interior slot held by one identified neighbour of six (197: the pin of 209; 178: a spurious blob):
    that slot is left open with that reason, no id is wrong, and every other id stays (one id fewer than before)."""
    from pipeline.vision.dtrc.proposals import HELD_BY_RINGS
    from pipeline.vision.identity.constants import R_FEW

    seed, sigma, lateral, rate, centre = view
    pts, truth, in_scope = _pressed_view_with_defects(seed, "circular217_dome", sigma, lateral, rate, centre)
    assert in_scope and HELD_BY_RINGS == 2
    coding = code_rings(_blobs(pts), DESIGNS["circular217_dome"])
    assert _wrong(coding.ids, truth) == 0
    assert slot not in coding.ids.tolist()
    assert dict(zip(coding.unmatched_ids.tolist(), coding.unmatched_reasons))[slot] == REASONS[R_FEW]
    assert np.count_nonzero(coding.ids >= 0) == read


# found by a further search of that space (numpy default_rng(777), 4,000 draws, 3,206 in scope): a view read
# whole with its centre on a marker of ring 1, all of its 158 ids wrong
_CENTRED_ONE_OFF_VIEW = (857963295, 2.9907, 0.1232, 0.0205, (0.6557, -0.0716))


def test_a_circular_reading_centred_on_a_ring_one_marker_is_withdrawn(monkeypatch):
    """circular217 pressed 5 mm by a sigma 3 mm Gaussian 0.66 mm off the axis, 2 % missing and spurious blobs:
    ring coding reads the view with its centre one marker off, and its rings 1-3 (two of them at the
    coverage the centre test allows) pass the per-ring gates. The same blobs read with the centre on the
    true centre fit those rings 12x better, so the reading is withdrawn: no id rather than 158 wrong ones;
    the view without defects is read whole."""
    import importlib

    anchoring = importlib.import_module("pipeline.vision.identity.anchoring")

    design = DESIGNS["circular217_dome"]
    seed, sigma, lateral, rate, centre = _CENTRED_ONE_OFF_VIEW
    pts, truth, in_scope = _pressed_view_with_defects(seed, "circular217_dome", sigma, lateral, rate, centre)
    assert in_scope
    assert _wrong(code_rings(_blobs(pts), design).ids, truth) == 0
    clean = code_rings(_blobs(_pressed_view("circular217_dome", 5.0, sigma, lateral, centre)), design).ids
    np.testing.assert_array_equal(clean, np.arange(design.marker_count))
    monkeypatch.setattr(anchoring, "_no_better_centre", lambda *a: True)   # without it the shifted reading is certified
    assert _wrong(code_rings(_blobs(pts), design).ids, truth) > 100


def test_the_identity_search_draws_the_views_of_these_tests(capsys):
    """``benchmarks.identity_search`` (the searches docs/IDENTIFICATION.md records, rerun from the CLI; this
    module's pressed views are its views) places every present blob at its marker's analytic projection, and a
    short search reports what it drew."""
    from benchmarks.identity_search import main, pressed_view, search

    seed, sigma, lateral, rate, centre = _CENTRED_ONE_OFF_VIEW
    pts, truth, _ = pressed_view(DESIGNS["circular217_dome"], seed, sigma, lateral, rate, centre)
    present = truth >= 0                              # each present blob is its marker's analytic projection
    projected = _pressed_view("circular217_dome", 5.0, sigma, lateral, centre)
    np.testing.assert_array_equal(pts[present], projected[truth[present]])
    res = search("circular217_dome", 6, 777)
    assert res["in_scope"] == len(res["views"]) <= 6 and res["wrong_ids"] == 0
    assert all(v["correct"] + v["wrong"] <= v["present"] + round(v["rate"] * 217) for v in res["views"])
    assert main(["--draws", "0"]) == 2 and "at least one draw" in capsys.readouterr().err
    # a glare spot over the middle: the hidden markers are gone, and the true readings' twist is measured
    design = DESIGNS["circular217_dome"]
    pts, truth, _ = pressed_view(design, seed, sigma, lateral, 0.0, centre, hidden=0.15)
    centre_id = int(np.argmin(np.hypot(*design.rest_markers_mm()[:, :2].T)))
    assert np.count_nonzero(truth >= 0) == 217 - round(0.15 * 217) and centre_id not in truth.tolist()
    res = search("circular217_dome", 4, 29, sigma=(1.5, 6.0), off_mm=3.0, rate=0.05, hidden=(0.1, 0.2))
    assert res["wrong_ids"] == 0 and 0 < res["twist"]["readings"] <= res["in_scope"]
    assert res["twist"]["max"] < 0.5 and all(0.1 <= v["hidden"] <= 0.2 for v in res["views"])


_STEREO_KEPT = pytest.mark.xfail(strict=True, reason="known wrong pairs: the spurious blob stands where the other "
                                 "view's marker's rays meet the skin, within the stereo check's gates")


@pytest.mark.parametrize("seed, name, sigma, lateral, rate",
                         [*_MISSING_SLOT_VIEWS, _MISSING_SLOT_VIEW_OUTREAD, _THINLY_HELD_VIEW,
                          *(pytest.param(*v, marks=_STEREO_KEPT) for v in _NEAR_PREDICTION_VIEWS[:2]),
                          _NEAR_PREDICTION_VIEWS[2]])
def test_a_wrong_id_of_one_view_does_not_survive_the_stereo_check(seed, name, sigma, lateral, rate):
    """Each view above paired with the other camera's view of the same press (its blobs complete): a
    wrong id of one view pairs with the other view's marker of that id, whose rays miss the first
    view's blob or meet it outside the gel (2 mm beyond the rest depth in two of the five), or the
    other view leaves the id open. The reconstruction's stereo check keeps no wrong pair. Not so in
    two of the later search's views (xfail): their spurious blob, 0.01-0.33 separations from the
    slot's prediction, pairs with the other view's marker within the gates."""
    from pipeline.geometry.refraction import project_through_stack
    from pipeline.io.synthetic import gaussian_press_markers
    from pipeline.runner import Reconstructor

    design = DESIGNS[name]
    calib = nominal_calibration(design)
    pts, truth, _ = _pressed_view_with_defects(seed, name, sigma, lateral, rate)
    assert _wrong(code_rings(_blobs(pts), design).ids, truth) <= 1
    right = project_through_stack(gaussian_press_markers(design, 5.0, sigma_mm=sigma, lateral=lateral), calib,
                                  design)[1]
    kept = Reconstructor(design, calib)._stereo_check(match_stereo(_blobs(pts), _blobs(right), design))[0]
    owner = {tuple(p): int(t) for p, t in zip(pts.tolist(), truth.tolist())}
    assert len(kept.ids) >= 0.8 * np.count_nonzero(truth >= 0)
    assert all(owner[tuple(p)] == i for i, p in zip(kept.ids.tolist(), kept.left_px.tolist()))
    np.testing.assert_array_equal(kept.right_px, right[kept.ids])


# views of the same space (defect seed, pattern, sigma, lateral, rate) in which the sharp press crowds the
# middle of the view so much that ring peeling fails there and no placement anchored on the central blobs
# is certified: nothing was identified in them (0 of 208, 112 and 196 present markers)
_CROWDED_MIDDLE_VIEWS = [(3, "hexagon217_sep180", 1.0517, 0.3463, 0.0419),
                         (1, "square121", 2.4059, 0.3268, 0.0726),
                         (1, "hexagon217_sep180", 2.4579, 0.2771, 0.0947)]


@pytest.mark.parametrize("seed, name, sigma, lateral, rate", _CROWDED_MIDDLE_VIEWS)
def test_a_view_crowded_in_the_middle_is_registered_half_way_out(seed, name, sigma, lateral, rate):
    """Placements anchored half-way out (``register_seed(spread=True)``) sit on skin the press barely
    moved: the view is identified to at least 85 % of its present markers, with no wrong id, where the
    central placements alone certify nothing."""
    from pipeline.vision.identity import R_NO_BLOB, consistent, grow, register_seed

    pts, truth, in_scope = _pressed_view_with_defects(seed, name, sigma, lateral, rate)
    assert in_scope
    lat = lattice_of(DESIGNS[name])
    for proposal in register_seed(pts, lat):
        reason = np.full(len(lat.xy), R_NO_BLOB)
        assert np.count_nonzero(certify(pts, grow(pts, consistent(pts, proposal, lat, reason), lat, reason), lat,
                                        reason) >= 0) == 0
    ids = code_rings(_blobs(pts), DESIGNS[name]).ids
    assert _wrong(ids, truth) == 0
    assert np.count_nonzero(ids >= 0) >= 0.85 * np.count_nonzero(truth >= 0)


# views the same search found (defect seed, pattern, sigma, lateral, rate): at the tip of the press a
# spurious blob stood 0.04 separations from the deepest slot's prediction (slot 120, then 116; seven
# or eight of its eight immediate neighbours identified, their largest residual 0.07, then 0.29)
# while the slot's pin, displaced 0.28-0.30 separations by its extra depth, was free
_DISPLACED_TIP_VIEWS = [
    (3956665288, "square121", 1.4587250402798522, 0.009258003440031425, 0.08156003854850498),
    (3332246714, "square121", 1.4661746013689307, 0.3730787191385763, 0.06325229000972109)]


@pytest.mark.parametrize("seed, name, sigma, lateral, rate", _DISPLACED_TIP_VIEWS)
def test_no_wrong_id_where_a_press_tip_displaces_its_pin_off_its_prediction(seed, name, sigma, lateral, rate):
    """A free blob no farther from a slot's prediction than the bend its neighbours' residuals show
    may displace the slot's pin competes with a blob sitting on the prediction: the slot is left
    open rather than given to the spurious blob."""
    _assert_no_wrong_id_in_scope(seed, name, sigma, lateral, rate)


def test_a_displaced_marker_and_a_free_blob_near_its_prediction_leave_the_slot_open():
    """The leave-one-out test's ratio rule gives a slot to the blob nearest its prediction. With a free
    blob within the growth gate of the prediction, that holds only for a blob that sits where its
    neighbourhood puts it: the dense view's spurious blob, labelled as the pressed centre pin (which
    stands 0.36 separations off the prediction, the spurious blob 0.15, every neighbour's residual
    <= 0.05), is ambiguous, and the centre slot stays open (the pin is beyond the gate). The same
    proposal without the pin's blob certifies the spurious blob: nothing competes there, and nothing
    in the geometry tells it from the pin displaced (the module notes' "indistinguishable" case). A
    spurious blob 0.3 separations from a marker of an unpressed view, within the growth gate of its
    prediction too, leaves the marker its id (it sits on its prediction)."""
    lat = lattice_of(DESIGNS["hexagon217_sep180"])
    pts, truth = _dense_view_with_defects()
    centre = int(np.flatnonzero(lat.layer_of == 0)[0])
    pin = int(np.flatnonzero(truth == centre)[0])
    spurious = np.flatnonzero(truth < 0)
    ghost = int(spurious[np.argmin(np.hypot(*(pts[spurious] - pts[pin]).T))])
    proposal = truth.copy()
    proposal[pin], proposal[ghost] = -1, centre
    ids = certify(pts, proposal, lat)
    assert ids[ghost] < 0 and centre not in ids
    others = (truth >= 0) & (truth != centre)
    assert np.count_nonzero(ids[others] == truth[others]) >= 195
    alone = np.delete(np.arange(len(pts)), pin)
    assert certify(pts[alone], proposal[alone], lat)[np.searchsorted(alone, ghost)] == centre

    design = DESIGNS["hexagon127"]
    lat = lattice_of(design)
    uv = view_px(design, np.random.default_rng(3))
    b = int(np.flatnonzero(lat.layer_of == 2)[0])
    step = uv[lat.nbr[b, 0]] - uv[b]
    pts = np.vstack([uv, uv[b] + 0.3 * np.array([-step[1], step[0]])])
    ids = certify(pts, np.append(np.arange(len(uv)), -1), lat)
    assert np.array_equal(ids, np.append(np.arange(len(uv)), -1))


def test_fan_test_rejects_swapped_neighbours_and_a_blob_inside_the_fan():
    """The fan test is topological: two neighbours' ids swapped fold the fans that contain them, and
    a blob inside a marker's fan (a spurious blob beside it) breaks its emptiness."""
    from pipeline.vision.dtrc.mesh import _nn_and_mesh
    from pipeline.vision.identity import use_triangulation
    from pipeline.vision.identity.consistency import _blob_of
    from pipeline.vision.identity.fans import _embedded
    from pipeline.vision.identity.neighbours import _adj

    name = "hexagon127"
    lat = lattice_of(DESIGNS[name])
    uv = _pressed_view(name, 5.0, 1.3, 0.3)
    truth = np.arange(len(uv))
    centre = int(np.flatnonzero(lat.layer_of == 0)[0])

    def intact(pts, labels, b):
        use_triangulation(pts, _nn_and_mesh(pts)[1][0])
        adj = _adj(pts)
        ring = np.empty(lat.fan.shape[1], np.int64)
        near = np.empty(24, np.int64)
        return _embedded(pts, True, adj[0], adj[1], b, labels[b], _blob_of(labels, len(lat.xy)),
                         lat.xy, lat.fan, lat.fan_closed, lat.pitch, 0.35, ring, near, np.empty(24), np.empty(12))

    assert intact(uv, truth, centre) == 1
    a, b = lat.fan[centre, 0], lat.fan[centre, 1]
    swapped = truth.copy()
    swapped[[a, b]] = swapped[[b, a]]
    assert intact(uv, swapped, centre) == 0
    ghost = np.vstack([uv, uv[centre] + 0.3 * (uv[a] - uv[centre])])
    assert intact(ghost, np.append(truth, -1), centre) == 0


@pytest.mark.parametrize("name, sigma_mm", [("hexagon217_sep180", 2.0), ("hexagon217_sep180", 1.2),
                                            ("square121", 2.0)])
def test_temporal_certification_follows_crowded_markers_through_a_press(name, sigma_mm):
    """A press sequence from rest to 5 mm (11 frames, analytic, lateral bulge 0.3): in the deepest
    frames ring coding and the local tests leave markers of the crowded tip unidentified; following
    them from the previous frame identifies every marker, and no id is ever wrong."""
    from pipeline.vision.dtrc import DTRCTracker
    from pipeline.geometry.refraction import project_through_stack
    from pipeline.io.synthetic import gaussian_press_markers

    design = DESIGNS[name]
    calib = nominal_calibration(design)
    tracked, single = DTRCTracker(design), DTRCTracker(design, temporal=False)
    for depth in np.linspace(0.0, 5.0, 11):
        xyz = gaussian_press_markers(design, float(depth), sigma_mm=sigma_mm, lateral=0.3)
        left, right = project_through_stack(xyz, calib, design)
        m = tracked.update(_blobs(left), _blobs(right))
        s = single.update(_blobs(left), _blobs(right))
        for res in (m, s):
            np.testing.assert_array_equal(res.left_px, left[res.ids])     # every emitted id is right
            np.testing.assert_array_equal(res.right_px, right[res.ids])
    assert len(s.ids) < design.marker_count                     # one frame alone leaves some out ...
    assert len(m.ids) == design.marker_count                    # ... the sequence identifies them all


@pytest.mark.parametrize("name", PATTERN_DESIGNS)
def test_tabulated_leave_one_out_fits_are_the_full_fits(name):
    """Where a slot's whole design neighbourhood is identified, the leave-one-out test takes the
    design half of its affine fits from a per-pattern table. Those fits must be the full fits bit for
    bit, so that no status depends on which path computed it: on a pressed, noisy view (complete,
    with two neighbours swapped, with 10 % of the blobs removed), every blob's status is the same
    with and without the table, and every tabulated fit returns exactly the full fit's numbers."""
    from pipeline.vision.identity import GATE
    from pipeline.vision.identity.consistency import _blob_of, _consistency
    from pipeline.vision.identity.fits import _fit, _fit_sums, _fit_tab

    design = DESIGNS[name]
    lat = _without_fans(lattice_of(design))          # every blob through the leave-one-out fits
    rng = np.random.default_rng(3)
    uv = _pressed_view(name, 3.0, 3.0, 0.3) + rng.normal(0.0, 0.3, (len(lat.xy), 2))
    n = len(uv)
    n_imm = np.count_nonzero(lat.nbr >= 0, axis=1)
    assert all(np.array_equal(lat.nbr2[s, :n_imm[s]], lat.nbr[s, :n_imm[s]]) for s in range(n))
    swapped = np.arange(n)
    a, b = 0, int(lat.nbr[0, 0])
    swapped[[a, b]] = swapped[[b, a]]
    kept = np.sort(rng.permutation(n)[: int(0.9 * n)])
    untabulated = np.full(n, -1, np.int64)            # matches no neighbourhood size: full fits only
    for pts, slot_of in ((uv, np.arange(n)), (uv, swapped), (np.ascontiguousarray(uv[kept]), kept.copy())):
        blob_of = _blob_of(slot_of, n)
        order = np.arange(len(pts))
        args = (lat.fan, lat.fan_closed, lat.pitch, GATE, order, 0, slot_of < 0)
        st_tab = _consistency(pts, True, np.zeros(len(pts) + 1, np.int64), np.zeros(0, np.int64), slot_of,
                              blob_of, lat.xy, lat.nbr, lat.nbr2, lat.loo_m, lat.loo_tab, *args)
        st_full = _consistency(pts, True, np.zeros(len(pts) + 1, np.int64), np.zeros(0, np.int64), slot_of,
                               blob_of, lat.xy, lat.nbr, lat.nbr2, untabulated, lat.loo_tab, *args)
        assert np.array_equal(st_tab, st_full)
    # the fits themselves, for every slot and left-out point of the complete view
    acc = np.empty(12)
    n_ok = 0
    for s in range(n):
        slots = np.r_[s, lat.nbr2[s, : lat.loo_m[s] - 1]].astype(np.int64)
        blobs = slots.copy()
        _fit_sums(lat.xy, uv, slots, blobs, len(slots), lat.xy[s, 0], lat.xy[s, 1], uv[s, 0], uv[s, 1], acc)
        for q in range(n_imm[s] + 1):
            full = _fit(lat.xy, uv, slots, blobs, acc, q, lat.xy[s, 0], lat.xy[s, 1], uv[s, 0], uv[s, 1], lat.pitch)
            tab = _fit_tab(lat.xy, uv, slots, blobs, acc, q, lat.xy[s, 0], lat.xy[s, 1], uv[s, 0], uv[s, 1],
                           lat.loo_tab[s, q])
            assert full == tab, (s, q)
            n_ok += full[0] == 1
    assert n_ok > 0.9 * sum(n_imm[s] + 1 for s in range(n))
