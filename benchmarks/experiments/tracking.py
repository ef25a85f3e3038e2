"""tracking: DTRC vs nearest-neighbour marker tracking under the paper's three letter motions.

Paper (Sec. IV-B, Fig. 9): "G" pressed twice by 1 mm from 1 mm depth (3 frames); "e" moved laterally
twice by 1 mm at 3 mm depth (3 frames); "o" moved rapidly 2 mm down and 2 mm sideways from touch
(2 frames). Nearest-neighbour tracking copes with the small steps of "G"; DTRC keeps identities
under the large and rapid displacements of "e" and "o". Here the twin's motion frames are run
through one :class:`pipeline.runner.Reconstructor` per tracker; a reported id counts as correct when
the nearest truth marker to its 3-D position carries that id (within half a separation).
"""

from __future__ import annotations

import numpy as np

from benchmarks.experiments._common import identity_correct, make_indenter, reconstruct, twin_calibration
from benchmarks.registry import Context, Finding, Result, register
from benchmarks.results import PAGE_IN, paper_style, save_figure

MOTIONS = (("G", "tracking-G"), ("e", "tracking-e"), ("o", "tracking-o"))
TRACKERS = ("dtrc", "nn")


@register(
    "tracking",
    tags=("quick", "paper"),
    metrics={
        "dtrc_correct_rate_min": "1",
        "nn_correct_rate_min": "1",
        **{f"{t}_correct_rate_{c}": "1" for t in TRACKERS for c, _ in MOTIONS},
        "frames": "1",
    },
    requires=("pipeline.runner", "twin.simulate", "twin.render", "twin.indenters"),
)
def run(ctx: Context) -> Result:
    """Letters G / e / o under slow, lateral and rapid motions: correct-identity rate of DTRC vs NN."""
    from twin.simulate import run_motion

    design = ctx.design()
    calib = twin_calibration(design)
    n = design.marker_count
    out = Result(designs=[design])
    letters = ctx.param("letters", "Geo")
    rows, tracks = [], {}
    n_frames = 0
    for char, motion in ctx.bar([m for m in MOTIONS if m[0] in letters], desc="tracking"):
        seq = run_motion(design, make_indenter("letter", char=char), motion, rng=ctx.rng(f"tracking/{motion}"))
        frames, truths = [f for f, _ in seq], [t for _, t in seq]
        n_frames += len(frames)
        for tracker in TRACKERS:
            results = reconstruct(design, calib, frames, tracker=tracker)
            correct = []
            for k, (fr, truth) in enumerate(zip(results, truths)):
                ok = identity_correct(fr.corrected.ids, fr.corrected.xyz_mm, truth, design.pattern.separation_mm / 2)
                correct.append(int(ok.sum()))
                rows.append({"letter": char, "motion": motion, "tracker": tracker, "frame": k,
                             "reported": int(len(fr.corrected.ids)), "correct": int(ok.sum()), "markers": n,
                             "correct_rate": ok.sum() / n})
            rate = sum(correct) / (n * len(frames))
            out.metric(f"{tracker}_correct_rate_{char}", rate, "1")
            tracks[(char, tracker)] = (results, truths)
    out.metric("frames", n_frames, "1")
    for t in TRACKERS:
        rates = [v for k, (v, _) in out.metrics.items() if k.startswith(f"{t}_correct_rate_") and k[-1] in "Geo"]
        out.metric(f"{t}_correct_rate_min", min(rates), "1")
    out.tables["per_frame"] = rows
    out.notes.append("Correct id: the nearest truth marker (3-D, corrected cloud) has the reported id and lies "
                     "within separation/2; missing markers count as not correct. Calibration: the twin's true cameras.")
    d, nn = out.metrics["dtrc_correct_rate_min"][0], out.metrics["nn_correct_rate_min"][0]
    out.findings.append(Finding("DTRC keeps every marker's identity under all three motions",
                                f"DTRC lowest correct-id rate {d:.3f}", bool(d >= 0.99)))
    if "o" in letters and "G" in letters:
        g_nn, o_nn = out.metrics["nn_correct_rate_G"][0], out.metrics["nn_correct_rate_o"][0]
        o_d = out.metrics["dtrc_correct_rate_o"][0]
        out.findings.append(Finding(
            "nearest-neighbour copes with the slow 'G' steps but confuses markers under the rapid 'o' motion, "
            "where DTRC does not",
            f"NN: G {g_nn:.3f}, o {o_nn:.3f}; DTRC o {o_d:.3f}", bool(g_nn >= 0.99 and o_nn < o_d)))

    with paper_style() as plt:
        chars = [c for c, _ in MOTIONS if c in letters]
        fig, axes = plt.subplots(2, len(chars), figsize=(PAGE_IN, 4.6), squeeze=False)
        for j, char in enumerate(chars):
            for i, tracker in enumerate(TRACKERS):
                ax = axes[i][j]
                results, truths = tracks[(char, tracker)]
                paths: dict[int, list] = {}
                for fr, truth in zip(results, truths):
                    ok = identity_correct(fr.corrected.ids, fr.corrected.xyz_mm, truth, design.pattern.separation_mm / 2)
                    for mid, p, good in zip(np.asarray(fr.corrected.ids), np.asarray(fr.corrected.xyz_mm), ok):
                        paths.setdefault(int(mid), []).append((p, good))
                for mid, pts in paths.items():
                    xy = np.array([p[:2] for p, _ in pts])
                    bad = not all(g for _, g in pts)
                    ax.plot(xy[:, 0], xy[:, 1], "-", color="C3" if bad else "0.3", lw=0.6)
                    ax.plot(xy[-1, 0], xy[-1, 1], "o", color="C3" if bad else "C0", ms=1.5)
                rate = out.metrics[f"{tracker}_correct_rate_{char}"][0]
                ax.set_title(f"'{char}' — {tracker.upper()}: {rate:.3f} correct")
                ax.set_aspect("equal")
                ax.set_xlabel("x (mm)")
                ax.set_ylabel("y (mm)")
        fig.suptitle("marker tracks in the x-y plane (red: an identity error somewhere on the track)")
        out.figures.append(save_figure(fig, ctx.figure_path("tracking")))
    return out
