"""tracking: DTRC vs nearest-neighbour marker tracking under the paper's three letter motions.

Paper (Sec. IV-B, Fig. 9): "G" pressed twice by 1 mm from 1 mm depth (3 frames); "e" moved laterally
twice by 1 mm at 3 mm depth (3 frames); "o" moved rapidly 2 mm down and 2 mm sideways from touch
(2 frames). Nearest-neighbour tracking copes with the small steps of "G"; DTRC keeps identities
under the large and rapid displacements of "e" and "o". Here the twin's robot (``twin.robot``,
``twin.physics.SkinSim``, Coulomb friction μ = FRICTION, face contact, letters LETTER_HEIGHT_MM tall) drives
the letter through exactly those captured poses, preceded by one rest frame (1 mm clear of the skin) that
starts both trackers; the rendered frames are run through one :class:`pipeline.runner.Reconstructor` per
tracker. A reported id counts as correct when the nearest truth marker to its 3-D position carries that id
(within half a separation). The largest true marker displacement between consecutive frames is recorded
beside the rates: it is what decides whether nearest-neighbour matching can work (it cannot beyond about
half a separation).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from benchmarks.experiments._common import calibration_note, identity_correct, make_indenter, reconstruct
from benchmarks.registry import Context, Finding, Result, register
from benchmarks.results import PAGE_IN, paper_style, save_figure

MOTIONS = (("G", "tracking-G"), ("e", "tracking-e"), ("o", "tracking-o"))
TRACKERS = ("dtrc", "nn")
REST_DEPTH_MM = -1.0        # the rest frame: indenter 1 mm clear of the skin
FRICTION = 1.0              # skin/letter Coulomb coefficient: within the μ ≈ 0.5-1.5 usually quoted for silicone-type
                            # elastomers on hard smooth polymers (not measured for Agilus30 on a printed letter);
                            # it is what drags the skin sideways under the lateral and rapid motions
LETTER_HEIGHT_MM = 4.0      # the letters' extrusion above their backing plate (the glyph raster's 3 mm margin,
                            # twin.indenters). At 3 mm (the indenter's default) the plate comes down to the skin's rest
                            # level at 3 mm depth, where the gel pushed aside by the letter bulges the skin 0.37 mm
                            # above it: once 'e' has slid 2 mm the plate's corner cut the skin faces bulging past its
                            # edge, 0.197 mm deep (measured; the letter itself 0.000 mm), the one invalid frame of 11.
                            # A finer skin did not help (same frame 0.105 mm on a 0.75 mm mirrored mesh, 98 s instead of
                            # 20 s; 1.0 mm: 0.082 and the 1 mm slide 0.107 too). At 4 mm the plate stays 1 mm clear at
                            # the deepest press and every frame is valid (max 0.000 mm, settled, no MuJoCo warning)
# The paper's captured poses (x_mm, depth_mm, fast) after the rest frame; "fast" = the rapid move.
PAPER_POSES = {
    "G": ((0.0, 1.0, False), (0.0, 2.0, False), (0.0, 3.0, False)),
    "e": ((0.0, 3.0, False), (1.0, 3.0, False), (2.0, 3.0, False)),
    "o": ((0.0, 0.0, False), (2.0, 2.0, True)),
}


def _paper_motion(char: str):
    """The letter's paper motion as a ``twin.robot.Motion`` (rest frame first)."""
    from twin import robot

    wps = [robot.Waypoint(0.0, 0.0, REST_DEPTH_MM)]
    wps += [robot.Waypoint(x, 0.0, d, speed_mm_s=robot.RAPID_SPEED_MM_S if fast else robot.ROBOT_SPEED_MM_S)
            for x, d, fast in PAPER_POSES[char]]
    return robot.Motion(f"tracking-{char}", tuple(wps))


def _letter_sim(design, char: str, friction: float = FRICTION):
    """The twin's skin under the letter ``char``, as the experiment simulates it (``twin.physics.SkinSim``)."""
    from twin.physics import MeshSpec, SkinSim

    return SkinSim(design, make_indenter("letter", char=char, height_mm=LETTER_HEIGHT_MM), friction=friction,
                   mesh=MeshSpec(face_contact=True))


def _simulate(design, char: str, rng, friction: float = FRICTION):
    """Physics + rendering of one letter motion: list of (StereoFrame, Truth)."""
    from twin import robot
    from twin.simulate import render_truths

    res = robot.execute(_letter_sim(design, char, friction), _paper_motion(char))
    truths = [t for _, _, t in res]
    frames = render_truths(design, truths, rng=rng, timestamps_s=[ts for ts, _, _ in res])
    return list(zip(frames, truths))


def _max_step_mm(truths) -> float:
    """Largest true LATERAL (x-y) marker displacement (mm) between consecutive frames: the image motion a
    nearest-neighbour tracker has to bridge (the cameras look along z, so z motion barely moves a blob)."""
    steps = [np.linalg.norm((b.marker_xyz_mm - a.marker_xyz_mm)[:, :2], axis=1).max()
             for a, b in zip(truths, truths[1:])]
    return float(max(steps)) if steps else 0.0


@register(
    "tracking",
    tags=("quick", "paper"),
    metrics={
        "dtrc_correct_rate_min": "1",
        "nn_correct_rate_min": "1",
        **{f"{t}_correct_rate_{c}": "1" for t in TRACKERS for c, _ in MOTIONS},
        **{f"max_lateral_step_mm_{c}": "mm" for c, _ in MOTIONS},
        **{f"{t}_wrong_ids": "1" for t in TRACKERS},
        "frames": "1",
        "invalid_frames": "1",
        "friction": "1",
    },
    requires=("pipeline.runner", "twin.simulate", "twin.render", "twin.indenters"),
)
def run(ctx: Context) -> Result:
    """Letters G / e / o under slow, lateral and rapid motions: correct-identity rate of DTRC vs NN."""
    setup = ctx.sensor_setup(ctx.design())   # the twin simulates setup.twin_design; the pipeline gets setup.design
    design = setup.design
    out = Result(designs=[design], setups=[setup.provenance])
    letters = ctx.param("letters", "Geo")
    friction = float(ctx.param("friction", FRICTION))
    runs = [_track_letter(setup, char, motion, ctx.rng(f"tracking/{motion}"), friction)
            for char, motion in ctx.bar([m for m in MOTIONS if m[0] in letters], desc="tracking")]
    _report_rates(out, runs, friction)
    _notes(out, setup, friction)
    _findings(out, runs, design, letters)
    out.figures.append(_plot(ctx, runs, design, out))
    return out


class _Track(NamedTuple):
    """One tracker on one letter: the pipeline's frame results and how many ids were right."""

    results: list           # FrameResult per frame
    rows: list              # the "per_frame" table rows
    correct_rate: float     # correct ids over markers × frames
    wrong: int              # reported ids that are wrong, over the frames


class _LetterRun(NamedTuple):
    """One letter's motion: the twin's truths and both trackers' results."""

    char: str
    truths: list
    max_step_mm: float      # largest true lateral marker step between frames
    invalid: int            # frames failing the twin's physics checks
    tracks: dict            # tracker -> _Track


def _track_letter(setup, char: str, motion: str, rng, friction: float) -> _LetterRun:
    """Simulate and render the letter's paper motion, then run the frames through each tracker."""
    seq = _simulate(setup.twin_design, char, rng, friction)
    frames, truths = [f for f, _ in seq], [t for _, t in seq]
    tracks = {tracker: _score_tracker(setup, char, motion, frames, truths, tracker) for tracker in TRACKERS}
    return _LetterRun(char, truths, _max_step_mm(truths), sum(1 for t in truths if t.physics_valid is False), tracks)


def _score_tracker(setup, char: str, motion: str, frames: list, truths: list, tracker: str) -> _Track:
    """Reconstruct the frames in order with ``tracker`` and count each frame's correct and wrong ids."""
    design = setup.design
    n = design.marker_count
    results = reconstruct(design, setup.calib, frames, tracker=tracker, **setup.reconstructor_kw())
    rows, correct, wrong = [], [], 0
    for k, (fr, truth) in enumerate(zip(results, truths)):
        ok = identity_correct(fr.corrected.ids, fr.corrected.xyz_mm, truth, design.pattern.separation_mm / 2)
        correct.append(int(ok.sum()))
        wrong += int((~ok).sum())
        rows.append({"letter": char, "motion": motion, "tracker": tracker, "frame": k,
                     "reported": int(len(fr.corrected.ids)), "correct": int(ok.sum()),
                     "wrong": int((~ok).sum()), "markers": n, "correct_rate": ok.sum() / n,
                     "physics_valid": truth.physics_valid})
    return _Track(results, rows, sum(correct) / (n * len(frames)), wrong)


def _report_rates(out: Result, runs: list[_LetterRun], friction: float) -> None:
    """Per letter and tracker: correct-id rates and largest steps; totals of frames, invalid frames, wrong ids."""
    for lr in runs:
        out.metric(f"max_lateral_step_mm_{lr.char}", lr.max_step_mm, "mm")
        for tracker in TRACKERS:
            out.metric(f"{tracker}_correct_rate_{lr.char}", lr.tracks[tracker].correct_rate, "1")
    out.metric("frames", sum(len(lr.truths) for lr in runs), "1")
    out.metric("invalid_frames", sum(lr.invalid for lr in runs), "1")
    for t in TRACKERS:
        out.metric(f"{t}_wrong_ids", sum(lr.tracks[t].wrong for lr in runs), "1")
    out.metric("friction", friction, "1")
    for t in TRACKERS:
        rates = [v for k, (v, _) in out.metrics.items() if k.startswith(f"{t}_correct_rate_") and k[-1] in "Geo"]
        out.metric(f"{t}_correct_rate_min", min(rates), "1")
    out.tables["per_frame"] = [row for lr in runs for tracker in TRACKERS for row in lr.tracks[tracker].rows]


def _notes(out: Result, setup, friction: float) -> None:
    """What counts as a correct id, the calibration, and the twin's friction."""
    out.notes.append("Correct id: the nearest truth marker (3-D, corrected cloud) has the reported id and lies "
                     "within separation/2; missing markers count as not correct. "
                     "Nearest-neighbour matching can only fail where a marker moves laterally by more than about "
                     "half a separation between frames (max_lateral_step_mm_*).")
    out.notes.append(calibration_note([setup]))
    out.notes.append(f"Twin contact with Coulomb friction mu = {friction:g} (stick/slip at the outer vertices, "
                     "twin.physics): lateral letter motions drag the skin under the letter. Frames failing their "
                     "physics checks are counted in invalid_frames.")


def _findings(out: Result, runs: list[_LetterRun], design, letters: str) -> None:
    """DTRC keeps identities under every motion; NN copes with 'G' but not with the rapid 'o'."""
    m = {k: v for k, (v, _) in out.metrics.items()}
    invalid, n_frames = sum(lr.invalid for lr in runs), sum(len(lr.truths) for lr in runs)
    wrong_ids = {t: sum(lr.tracks[t].wrong for lr in runs) for t in TRACKERS}
    d = m["dtrc_correct_rate_min"]
    validity = (f"; {invalid} of {n_frames} frames fail the twin's physics checks, so these rates come from "
                "flagged frames" if invalid else "")
    out.findings.append(Finding("DTRC keeps every marker's identity under all three motions",
                                f"DTRC lowest correct-id rate {d:.3f}, {wrong_ids['dtrc']} wrong ids "
                                f"(NN: {wrong_ids['nn']}){validity}", bool(d >= 0.99 and wrong_ids["dtrc"] == 0)))
    if "o" in letters and "G" in letters:
        g_nn, o_nn, o_d = m["nn_correct_rate_G"], m["nn_correct_rate_o"], m["dtrc_correct_rate_o"]
        out.findings.append(Finding(
            "nearest-neighbour copes with the slow 'G' steps but confuses markers under the rapid 'o' motion, "
            "where DTRC does not",
            f"NN: G {g_nn:.3f}, o {o_nn:.3f}; DTRC o {o_d:.3f}; largest true lateral marker step between frames: "
            f"G {m['max_lateral_step_mm_G']:.2f} mm, o {m['max_lateral_step_mm_o']:.2f} mm "
            f"(separation {design.pattern.separation_mm:g} mm)", bool(g_nn >= 0.99 and o_nn < o_d)))


def _plot(ctx: Context, runs: list[_LetterRun], design, out: Result):
    """Each tracker's marker tracks per letter in the x-y plane; red where an identity is wrong somewhere."""
    with paper_style() as plt:
        fig, axes = plt.subplots(2, len(runs), figsize=(PAGE_IN, 4.6), squeeze=False)
        for j, lr in enumerate(runs):
            for i, tracker in enumerate(TRACKERS):
                ax = axes[i][j]
                paths: dict[int, list] = {}
                for fr, truth in zip(lr.tracks[tracker].results, lr.truths):
                    ok = identity_correct(fr.corrected.ids, fr.corrected.xyz_mm, truth, design.pattern.separation_mm / 2)
                    for mid, p, good in zip(np.asarray(fr.corrected.ids), np.asarray(fr.corrected.xyz_mm), ok):
                        paths.setdefault(int(mid), []).append((p, good))
                for mid, pts in paths.items():
                    xy = np.array([p[:2] for p, _ in pts])
                    bad = not all(g for _, g in pts)
                    ax.plot(xy[:, 0], xy[:, 1], "-", color="C3" if bad else "0.3", lw=0.6)
                    ax.plot(xy[-1, 0], xy[-1, 1], "o", color="C3" if bad else "C0", ms=1.5)
                rate = out.metrics[f"{tracker}_correct_rate_{lr.char}"][0]
                ax.set_title(f"'{lr.char}' — {tracker.upper()}: {rate:.3f} correct")
                ax.set_aspect("equal")
                ax.set_xlabel("x (mm)")
                ax.set_ylabel("y (mm)")
        fig.suptitle("marker tracks in the x-y plane (red: an identity error somewhere on the track)")
        return save_figure(fig, ctx.figure_path("tracking"))
