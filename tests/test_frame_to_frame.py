"""Carried ids certified by the frame-to-frame map (pipeline/vision/identity/temporal.py), against
analytic truth: a press sequence that crowds the pins into columns (as under a narrow sine's crests)
beyond what the design-to-image rule can read in one frame, with and without missing and spurious
blobs, and the defects the frame-to-frame gates exist for (a blob that jumps, a missing blob, a
spurious blob beside a marker, a blob merged with a neighbour that was lost)."""

import numpy as np
import pytest

from benchmarks.experiments.identification import PX_PER_SEP, add_defects, view_px
from pipeline.design import load_design
from pipeline.types import Blobs
from pipeline.vision.dtrc import DTRCTracker, code_rings
from pipeline.vision.identity import frame_to_frame, lattice_of
from pipeline.vision.identity.reacquire import reacquire


def _blobs(pts):
    return Blobs(np.ascontiguousarray(pts), np.full(len(pts), 3.0), np.ones(len(pts)))


def _crowding(rest, rng, amplitude):
    """A press that crowds the pins into columns: x -> x - t·a·λ/2π·sin(2π(x - φ)/λ), λ = 4-7 separations.
    At t = 1 the columns' spacing shrinks to 1 - a of the rest spacing across x (a stretch ratio of
    1/(1 - a) in the local map, beyond the rule's limits for a > 0.5), smoothly in t."""
    lam = rng.uniform(4, 7) * PX_PER_SEP
    phase = rng.uniform(0, lam)

    def at(t):
        out = rest.copy()
        out[:, 0] -= t * amplitude * lam / (2 * np.pi) * np.sin(2 * np.pi * (rest[:, 0] - phase) / lam)
        return out
    return at


def _run(name, seed, n_frames, amplitude, rate):
    """A press sequence through one tracker; returns (ids emitted per frame, wrong ids per frame, ids a
    single frame gives at the deepest pose)."""
    design = load_design(name)
    rng = np.random.default_rng(seed)
    rest = view_px(design, rng, rot_deg=float(rng.uniform(-10, 10)), jitter_sep=0.0)
    at = _crowding(rest, rng, amplitude)
    tracker = DTRCTracker(design)
    counts, wrong = [], []
    for k, t in enumerate(np.linspace(0.0, 1.0, n_frames)):
        views = []
        for offset in ([0.0, 0.0], [25.0, 0.0]):
            p = at(t) - offset + rng.normal(0, 0.2, rest.shape)
            views.append(add_defects(p, rng, missing=rate if k else 0.0, spurious=rate if k else 0.0)[:2])
        m = tracker.update(_blobs(views[0][0]), _blobs(views[1][0]))
        n_wrong = 0
        for (pts, truth), px in zip(views, (m.left_px, m.right_px)):
            look = {tuple(a): b for a, b in zip(pts.tolist(), truth.tolist())}
            n_wrong += sum(look[tuple(a)] != i for a, i in zip(px.tolist(), m.ids.tolist()))
        counts.append(len(m.ids))
        wrong.append(n_wrong)
    single = code_rings(_blobs(views[0][0]), design).coded
    return counts, wrong, single


@pytest.mark.parametrize("name, seed", [("hexagon127", 1), ("hexagon217_sep180", 0), ("square121", 1),
                                        ("circular217_dome", 0)])
def test_a_press_that_crowds_the_pins_beyond_the_rule_is_followed_whole(name, seed):
    """11 frames to a crowding of 0.65 (columns at a third of the rest spacing): one frame alone
    identifies nothing at the deepest pose; the sequence identifies every marker in every frame, none
    wrong. (In some other sequences ring coding of one deep frame reads a patch one column over; the
    two certifications then disagree and that frame keeps only their agreement, e.g. 33 of 127.)"""
    design = load_design(name)
    counts, wrong, single = _run(name, seed, 11, 0.65, 0.0)
    assert single == 0
    assert counts == [design.marker_count] * 11
    assert wrong == [0] * 11


@pytest.mark.parametrize("name", ["hexagon127", "hexagon217_sep180", "square121", "circular217_dome",
                                  "hexagon61_sep354"])
@pytest.mark.parametrize("n_frames, amplitude, rate", [(11, 0.75, 0.03), (6, 0.8, 0.05), (4, 0.85, 0.03)])
def test_no_wrong_id_in_crowding_press_sequences_with_defects(name, n_frames, amplitude, rate):
    """Missing and spurious blobs in every frame and view (independently), steps of up to a third of
    the press, crowding down to 0.15 of the rest spacing (pins that would touch): ids are lost, never
    wrong (measured over 6 seeds x 3 schedules x 5 patterns: 0 wrong; the mean-motion following this
    replaced gave 6)."""
    for seed in range(3):
        _, wrong, _ = _run(name, seed, n_frames, amplitude, rate)
        assert wrong == [0] * n_frames, (seed, wrong)


def _lattice_step(name="hexagon127"):
    """Rest positions of a view and an analytic increment (a smooth, non-affine bulge of ~0.1
    separations)."""
    design = load_design(name)
    rng = np.random.default_rng(3)
    prev = view_px(design, rng, rot_deg=4.0, jitter_sep=0.0)
    c = prev.mean(axis=0)
    r2 = ((prev - c) ** 2).sum(axis=1) / (3 * PX_PER_SEP) ** 2
    cur = prev + 0.1 * PX_PER_SEP * (prev - c) / (3 * PX_PER_SEP) * np.exp(-r2)[:, None] + [2.0, -1.0]
    return design, prev, cur


def test_frame_to_frame_follows_every_marker_of_a_smooth_step():
    _, prev, cur = _lattice_step()
    ids = np.arange(len(prev))
    order = np.random.default_rng(0).permutation(len(cur))
    out = frame_to_frame(prev, ids, cur[order])
    np.testing.assert_array_equal(out, order)


def test_a_step_bent_over_two_spacings_is_followed_from_the_first_shell(monkeypatch):
    """An increment affine over one spacing but not over two (columns shifted by 0.12 separations in a
    sine of 3.5 separations across x, as where a press bends the skin over a flank): the fit over two
    shells fails its residual test where the bend is strongest, the first shell's passes, and every
    marker is followed (without the first-shell fit 4 are not); with 5 % missing and 5 % spurious
    blobs, none is wrong."""
    import pipeline.vision.identity.temporal as temporal

    design = load_design("hexagon217_sep180")
    lat = lattice_of(design)
    prev = view_px(design, np.random.default_rng(3), rot_deg=4.0, jitter_sep=0.0)
    cur = prev.copy()
    cur[:, 0] += 0.12 * PX_PER_SEP * np.sin(2 * np.pi * prev[:, 0] / (3.5 * PX_PER_SEP))
    ids = np.arange(len(prev))
    out = frame_to_frame(prev, ids, cur, None, lat.nbr)
    np.testing.assert_array_equal(out, ids)
    for seed in range(4):
        pts, truth, _ = add_defects(cur, np.random.default_rng(seed), missing=0.05, spurious=0.05)
        out = frame_to_frame(prev, ids, pts, None, lat.nbr)
        assert np.all((out < 0) | (out == truth)), seed
    monkeypatch.setattr(temporal, "F2F_SHELL", 0)
    assert np.count_nonzero(frame_to_frame(prev, ids, cur, None, lat.nbr) >= 0) < len(ids)


def test_frame_to_frame_withholds_jumped_missing_and_ambiguous_markers():
    """A blob that jumped 0.3 separations off its neighbours' motion loses its id; a missing blob
    leaves its marker out (its neighbour is not taken instead); a marker with a spurious blob as near
    to its prediction as its own (0.06 separations either side) is ambiguous. A spurious blob 0.15
    separations beside a marker predicted to within a few hundredths does not hide it. Every other
    marker keeps its id."""
    design, prev, cur = _lattice_step()
    ids = np.arange(len(prev))
    jumped, gone, twin, beside = 40, 60, 80, 20
    cur = cur.copy()
    cur[jumped] += [0.3 * PX_PER_SEP, 0.0]
    keep = np.setdiff1d(ids, [gone])
    extra = np.array([cur[twin] - [0.06 * PX_PER_SEP, 0.0], cur[beside] + [0.0, 0.15 * PX_PER_SEP]])
    cur[twin] += [0.06 * PX_PER_SEP, 0.0]
    pts = np.vstack([cur[keep], extra])
    truth = np.append(keep, [-1, -1])
    out = frame_to_frame(prev, ids, pts)
    assert np.all((out < 0) | (out == truth))
    assert jumped not in out and gone not in out and twin not in out
    assert beside in out
    assert np.count_nonzero(out >= 0) >= len(prev) - 4


def _beside_a_lost_neighbour(marker=50):
    """The smooth step with ``marker``'s blob moved 0.15 separations towards its first design neighbour:
    (lattice, previous, current, ids, marker, that neighbour)."""
    design, prev, cur = _lattice_step()
    lat = lattice_of(design)
    lost = int(lat.nbr[marker][0])
    cur = cur.copy()
    cur[marker] += 0.15 * (cur[lost] - cur[marker])
    return lat, prev, cur, np.arange(len(prev)), marker, lost


def test_a_blob_beside_a_lost_neighbour_needs_the_tight_gate():
    """A marker whose design neighbour was not followed into the previous frame may share its blob
    with that neighbour (crowded pins the detector no longer separates): 0.15 separations off its
    prediction it is not taken, while with every neighbour followed it is."""
    lat, prev, cur, ids, marker, lost = _beside_a_lost_neighbour()
    with_all = frame_to_frame(prev, ids, cur, design_nbr=lat.nbr)
    assert with_all[marker] == marker
    keep = ids != lost
    without = frame_to_frame(prev[keep], ids[keep], cur, design_nbr=lat.nbr)
    assert marker not in without
    assert np.all((without < 0) | (without == ids))


def test_a_lost_neighbour_whose_blob_is_back_does_not_need_the_tight_gate():
    """The same marker, 0.15 separations off its prediction, beside a neighbour missing from the previous
    frame (its blob lost to glare or a spurious blob beside it) whose blob is back now, where the marker's
    neighbourhood puts it: the two cannot share one blob, so the marker is taken at the usual gate. With
    that neighbour's blob missing now too, the tight gate holds and it is not."""
    lat, prev, cur, ids, marker, lost = _beside_a_lost_neighbour()
    keep = ids != lost
    back = frame_to_frame(prev[keep], ids[keep], cur, design_nbr=lat.nbr, design_xy=lat.xy)
    assert back[marker] == marker
    assert np.all((back < 0) | (back == ids))
    gone = frame_to_frame(prev[keep], ids[keep], cur[keep], design_nbr=lat.nbr, design_xy=lat.xy)
    assert marker not in gone


def test_a_wrongly_carried_id_does_not_propagate():
    """Two neighbours' ids swapped in the previous frame, a frame with 5 % missing and 5 % spurious
    blobs: the rule's reading contradicts the carried one, and the swapped ids are neither emitted nor
    carried on (they were, before the frame-to-frame map was checked against the rule's reading from
    before the previous frame's ids withdrew the two right ids)."""
    design = load_design("hexagon127")
    rng = np.random.default_rng(5)
    view = view_px(design, rng, rot_deg=2.0)
    ids = np.arange(len(view))
    swapped = ids.copy()
    a, b = 30, int(lattice_of(design).nbr[30][0])
    swapped[[a, b]] = swapped[[b, a]]
    pts, truth, _ = add_defects(view + [1.5, 0.5], rng, missing=0.05, spurious=0.05)
    c = code_rings(_blobs(pts), design, previous=(view, swapped))
    assert np.all((c.ids < 0) | (c.ids == truth))
    assert np.all((c.carried < 0) | (c.carried == truth))


def _lost_marker_step(marker=50):
    """An earlier frame with every marker certified, and the current frame (the smooth step of
    :func:`_lattice_step` taken twice) in which every marker but ``marker`` is certified again."""
    design, prev, cur = _lattice_step()
    cur = prev + 2 * (cur - prev)
    ids = np.arange(len(prev))
    now = ids.copy()
    now[marker] = -1
    return design, prev, cur, ids, now


def test_a_marker_lost_for_a_frame_is_reacquired_from_its_neighbours_motion():
    """A marker certified two frames ago and lost since (its blob merged or not followed) is taken
    back on its blob when the neighbours' motion over both frames puts it there; no other blob is
    given an id."""
    design, prev, cur, ids, now = _lost_marker_step()
    out = reacquire([(prev, ids)], now, cur, lattice_of(design).nbr)
    assert out[50] == 50
    assert np.count_nonzero(out >= 0) == 1


def test_a_reacquired_marker_never_takes_a_wrong_blob():
    """The lost marker's prediction with, in turn: its blob gone and a spurious blob 0.3 separations
    off (beyond the gate); a spurious blob 0.06 separations from it as near as its own (ambiguous);
    its blob gone and a neighbour's (identified) blob nearest; its blob merged with a lost neighbour's
    (the detector's centre half-way between the two); a blob beside it next to a neighbour lost
    earlier (possibly the two merged): nothing is re-acquired, and nothing wrong ever."""
    design, prev, cur, ids, now = _lost_marker_step()
    nbr = lattice_of(design).nbr
    m, n = 50, int(nbr[50][0])
    step = 0.3 * PX_PER_SEP
    # 1. blob gone, a spurious blob beyond the gate
    keep = ids != m
    pts = np.vstack([cur[keep], cur[m] + [step, 0.0]])
    out = reacquire([(prev, ids)], np.append(now[keep], -1), pts, nbr)
    assert np.all(out < 0)
    # 2. a spurious blob as near to the prediction as the marker's own
    pts = np.vstack([cur + 0.0, cur[m] - [0.06 * PX_PER_SEP, 0.0]])
    pts[m] += [0.06 * PX_PER_SEP, 0.0]
    out = reacquire([(prev, ids)], np.append(now, -1), pts, nbr)
    assert np.all(out < 0)
    # 3. blob gone: the neighbour's certified blob is never taken
    out = reacquire([(prev, ids)], now[keep], cur[keep], nbr)
    assert np.all(out < 0)
    # 4. the marker and its lost neighbour merged into one blob between them
    both = (ids != m) & (ids != n)
    pts = np.vstack([cur[both], 0.5 * (cur[m] + cur[n])])
    out = reacquire([(prev, ids)], np.append(now[both], -1), pts, nbr)
    assert np.all(out < 0)
    # 5. the neighbour lost before the frame the marker was last certified in (no prediction of it
    # to test the blob against): a blob 0.05 separations off the marker towards it may be the two
    # merged, and is not taken (with the neighbour predicted, it is: the neighbour is a spacing away)
    pts = np.vstack([cur[ids != n]])
    pts[m - (m > n)] += 0.05 * (cur[n] - cur[m])
    cur_ids = np.where(ids == m, -1, ids)[ids != n]
    older = ids != n
    out = reacquire([(prev[older], ids[older])], cur_ids, pts, nbr)
    assert np.all(out < 0)
    out = reacquire([(prev, ids)], cur_ids, pts, nbr)
    assert m in out and np.all((out < 0) | (out == ids[ids != n]))


def test_a_press_sequence_reacquires_a_marker_whose_blob_was_missing_for_a_frame():
    """The crowding press of 11 frames (one frame alone identifies nothing at the deepest poses) with
    the blob of a marker in the most crowded column missing from both views in frame 7: the marker is
    unmatched there, and from frame 8 on identified again; every other marker in every frame, none
    wrong. (Without re-acquisition it stays unmatched to the end: the frame-to-frame map follows only
    markers certified in the previous frame, and the design-to-image rule cannot read that column.)"""
    gone = 7
    n, counts = crowding_with_a_missing_marker("hexagon127", 99, lambda k: k == gone)
    assert counts == [n - (k == gone) for k in range(11)]


def crowding_with_a_missing_marker(name, marker, missing):
    """The crowding press of 11 frames (seed 1, to 0.65) through one tracker, ``marker``'s blob left out of
    both views in the frames ``k`` where ``missing(k)``; asserts that no id is wrong in any frame and returns
    (the design's marker count, the ids emitted per frame)."""
    design = load_design(name)
    rng = np.random.default_rng(1)
    rest = view_px(design, rng, rot_deg=float(rng.uniform(-10, 10)), jitter_sep=0.0)
    at = _crowding(rest, rng, 0.65)
    tracker, counts = DTRCTracker(design), []
    for k, t in enumerate(np.linspace(0.0, 1.0, 11)):
        keep = np.arange(len(rest)) != marker if missing(k) else np.ones(len(rest), bool)
        views = [at(t)[keep] - offset + rng.normal(0, 0.2, (keep.sum(), 2)) for offset in ([0.0, 0.0], [25.0, 0.0])]
        m = tracker.update(_blobs(views[0]), _blobs(views[1]))
        truth = np.flatnonzero(keep)
        for pts, px in zip(views, (m.left_px, m.right_px)):
            look = {tuple(a): b for a, b in zip(pts.tolist(), truth.tolist())}
            assert all(look[tuple(a)] == i for a, i in zip(px.tolist(), m.ids.tolist())), k
        counts.append(len(m.ids))
    return design.marker_count, counts


def _crowding_step(name, seed, amplitude=0.7):
    """Three frames of the crowding press at a half, three quarters and all of it (steps of a
    quarter of the press, the deepest where the columns crowd to 1 - amplitude of the spacing)."""
    design = load_design(name)
    rng = np.random.default_rng(seed)
    rest = view_px(design, rng, rot_deg=3.0, jitter_sep=0.0)
    at = _crowding(rest, rng, amplitude)
    before, prev, cur = (at(t) + rng.normal(0, 0.2, rest.shape) for t in (0.5, 0.75, 1.0))
    return design, before, prev, cur


@pytest.mark.parametrize("name", ["hexagon127", "hexagon217_sep180"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_last_velocity_follows_a_step_whose_increment_is_not_affine(name, seed):
    """As the columns crowd, the increment grows frame by frame and is not affine over two
    spacings: fitting the increment follows only part of the markers (measured: 57, 110, 110 of 127;
    174, 123, 88 of 217, none wrong); fitting its change from the markers' last velocity follows every
    one, none wrong."""
    design, before, prev, cur = _crowding_step(name, seed)
    ids = np.arange(len(prev))
    nbr = lattice_of(design).nbr
    increment = frame_to_frame(prev, ids, cur, None, nbr)
    velocity = frame_to_frame(prev, ids, cur, 2 * prev - before, nbr)
    assert np.all((increment < 0) | (increment == ids))
    assert np.count_nonzero(increment >= 0) <= 0.9 * len(ids)
    np.testing.assert_array_equal(velocity, ids)


def _held_at_the_rim(name, seed, amplitude=0.04):
    """The rest view and a press from it that spreads the middle and is held at the rim: each marker moves
    out radially by t·a·r·sqrt(clip((R - r) / s, 0, 1)) px (r from the pattern's centre, R the outer
    ring's, s a separation in px), so the outer ring stays while the ring inside it moves about
    t·a·(R - s): one frame's increment bends across the outermost spacing. Returns (design, rest, at)."""
    design = load_design(name)
    rng = np.random.default_rng(seed)
    rest = view_px(design, rng, rot_deg=3.0, jitter_sep=0.0)
    c = rest.mean(axis=0)
    r = np.hypot(*(rest - c).T)
    out = (rest - c) / np.maximum(r, 1e-9)[:, None]
    ramp = amplitude * r * np.sqrt(np.clip((r.max() - r) / PX_PER_SEP, 0.0, 1.0))

    def at(t):
        return rest + out * (t * ramp)[:, None] + rng.normal(0, 0.2, rest.shape)
    return design, rest, at


@pytest.mark.parametrize("name", ["hexagon127", "hexagon217_sep180"])
@pytest.mark.parametrize("seed", [0, 1])
def test_the_motion_from_rest_follows_the_second_frame_of_a_press_held_at_the_rim(name, seed):
    """The second frame of a press from rest, its first frame 0.2-0.3 separations from rest: fitting the
    increment misses outer-ring markers, whose motion the rim holds back from their neighbours'
    (measured 126 of 127, 214-215 of 217), none wrong; the first frame's motion from rest as the
    markers' velocity (``start_at_previous``: the guess only competes) follows every one."""
    design, rest, at = _held_at_the_rim(name, seed)
    lat = lattice_of(design)
    first, second = at(1.0), at(2.0)
    ids = np.arange(len(rest))
    increment = frame_to_frame(first, ids, second, None, lat.nbr, lat.xy)
    guessed = frame_to_frame(first, ids, second, 2 * first - rest, lat.nbr, lat.xy, start_at_previous=True)
    assert np.all((increment < 0) | (increment == ids))
    assert np.count_nonzero(increment >= 0) < len(ids)
    np.testing.assert_array_equal(guessed, ids)


@pytest.mark.parametrize("name", ["hexagon127", "hexagon217_sep180"])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_wrong_guess_of_the_velocity_from_rest_costs_nothing(name, seed):
    """A sequence that starts pressed and is held: the first frame's motion from rest (0.4-0.6
    separations) is no velocity at all. The fit of the motion's change then predicts only where its
    residual beats the increment's (the increment's is the noise): every marker followed, none wrong
    (measured with the guess always preferred where its fit passes: 118-121 of 127, 210-211 of 217)."""
    design, rest, at = _held_at_the_rim(name, seed)
    lat = lattice_of(design)
    first, second = at(2.0), at(2.0)
    ids = np.arange(len(rest))
    guessed = frame_to_frame(first, ids, second, 2 * first - rest, lat.nbr, lat.xy, start_at_previous=True)
    np.testing.assert_array_equal(guessed, ids)


def test_with_the_last_velocity_jumped_missing_ambiguous_and_misled_markers_are_withheld():
    """The crowding step followed at the last velocity, with a blob that jumped 0.3 local spacings, a
    missing blob, a spurious blob 0.06 separations beside a marker (its own 0.06 on the other side),
    and a marker whose last velocity is wrong by half a separation (its previous position was a
    neighbour's blob's): the jumped and the missing marker are withheld, and no marker takes a wrong
    id (the spurious blob's twin and the misled marker are withheld or right)."""
    design, before, prev, cur = _crowding_step("hexagon127", 0)
    nbr = lattice_of(design).nbr
    ids = np.arange(len(prev))
    jumped, gone, twin, misled = 40, 60, 80, 20
    cur = cur.copy()
    local = np.sort(np.linalg.norm(cur - cur[jumped], axis=1))[1]     # the crowded (or stretched) spacing there
    cur[jumped] += [0.3 * local, 0.0]
    keep = np.setdiff1d(ids, [gone])
    extra = np.array([cur[twin] - [0.06 * PX_PER_SEP, 0.0]])
    cur[twin] += [0.06 * PX_PER_SEP, 0.0]
    pts = np.vstack([cur[keep], extra])
    truth = np.append(keep, -1)
    expected = 2 * prev - before
    expected[misled] += [0.0, 0.5 * PX_PER_SEP]
    out = frame_to_frame(prev, ids, pts, expected, nbr)
    assert np.all((out < 0) | (out == truth))
    assert jumped not in out and gone not in out
    assert np.count_nonzero(out >= 0) >= len(prev) - 12
