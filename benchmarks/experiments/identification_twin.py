"""The identification benchmark's ``twin_sequence`` condition: press sequences from the twin's physics.

The other pressed condition (``press_stereo``) displaces the markers by an analytic Gaussian; this one takes
the markers where the twin's skin put them: each pattern design pressed 5 mm from rest in
:data:`SEQUENCE_FRAMES` frames (1, 2, ... 5 mm) by the sharpest Gaussian of the paper's grid and its σ² = 10 mm²
(:mod:`benchmarks.experiments.gaussian`'s axis contact mesh, the design's friction) and by the sines
ω = 2π/15 and π/5 (:mod:`benchmarks.experiments.sine`'s plate, mesh and friction), whose crests crowd the
markers. A frame the twin flags physically invalid ends its sequence there: a skin that passed through the
indenter is not a skin the pipeline will see.

A trial is one sequence read as ``reconstruct`` reads recorded frames: one
:class:`pipeline.runner.Reconstructor` (the DTRC tracker with the calibration's rest pattern, then the stereo
check) given each frame's two views in turn, each view projected through the nominal calibration and the
refracting stack with 0.2 px noise and its own :data:`DEFECT_RATE` missing + spurious blobs, drawn again every
frame. Each frame counts as one trial of the condition: a pair is wrong if either view's blob is not that
marker, coverage is the markers present in both views that got their correct id.
"""

from __future__ import annotations

import math

import numpy as np

#: (indenter, parameter) pressed into every pattern design: Gaussian σ² (mm²), sine ω (rad/mm)
TWIN_PRESSES = (("gaussian", 5.0 / 3.0), ("gaussian", 10.0), ("sine", 2 * math.pi / 15), ("sine", math.pi / 5))
QUICK_PRESSES = TWIN_PRESSES[:1]
SEQUENCE_FRAMES = 5
DEPTH_MM = 5.0
DEFECT_RATE = 0.03      # missing = spurious blobs per view and frame (the coverage goal's 3 % + 3 %)
NOISE_PX = 0.2

__all__ = ["TWIN_PRESSES", "QUICK_PRESSES", "SEQUENCE_FRAMES", "press_sequence", "read_sequence", "twin_available"]


def twin_available() -> bool:
    """Whether the twin (MuJoCo) can run here: without it the condition is left out with a note."""
    import importlib.util

    return importlib.util.find_spec("mujoco") is not None


def label(kind: str, value: float) -> str:
    return f"gaussian σ²={value:.3g}" if kind == "gaussian" else f"sine ω={value / math.pi:.3g}π"


def press_sequence(design, kind: str, value: float) -> dict:
    """Press ``design`` from rest to 5 mm in :data:`SEQUENCE_FRAMES` frames as the paper's experiment of that
    indenter does; {"xyz": marker positions (mm) of the frames up to the first physically invalid one,
    "frames": how many were pressed, "invalid_from": the 1-based frame that ended it (0: none)}."""
    from benchmarks.experiments import gaussian, sine
    from twin.indenters import make_indenter
    from twin.physics import AXIS_CONTACT_MESH
    from twin.simulate import press_truth

    if kind == "gaussian":
        run = press_truth(design, make_indenter("gaussian", h_mm=gaussian.H_MM, sigma2_mm2=value), DEPTH_MM,
                          n_frames=SEQUENCE_FRAMES, mesh=AXIS_CONTACT_MESH)
    elif kind == "sine":
        run = press_truth(design, sine.sine_plate(value), DEPTH_MM, n_frames=SEQUENCE_FRAMES, mesh=sine.sine_mesh(),
                          friction=sine.SINE_FRICTION)
    else:
        raise ValueError(f"unknown indenter {kind!r}")
    xyz, invalid_from = [], 0
    for k, t in enumerate(run):
        if t.physics_valid is False:
            invalid_from = k + 1
            break
        xyz.append(np.asarray(t.marker_xyz_mm))
    return {"xyz": xyz, "frames": len(run), "invalid_from": invalid_from}


def read_sequence(design, calib, frames_xyz: list, rng: np.random.Generator, *,
                  rate: float = DEFECT_RATE) -> list[dict]:
    """Read one sequence (marker positions per frame) as the runner reads recorded frames; per frame
    {"wrong", "correct", "present"} (module notes)."""
    from benchmarks.experiments.identification import _blobs, score_pairs, stereo_views_with_defects
    from pipeline.geometry.refraction import project_through_stack
    from pipeline.runner import Reconstructor

    rec = Reconstructor(design, calib, view_threads=1)
    out = []
    for xyz in frames_xyz:
        sides = stereo_views_with_defects(project_through_stack(xyz, calib, design), rng, rate, NOISE_PX)
        out.append(score_pairs(rec.identify(_blobs(sides[0][0]), _blobs(sides[1][0])), sides))
    return out


def press_all(ctx, out, designs) -> dict[str, list[dict]]:
    """Every design's press sequences through the context's executor: {design name: [press_sequence(...) with
    "press" (its label)]}; the sequences with at least one valid frame. Empty when the twin cannot run here
    (a note says so) or no press gave a valid frame."""
    if not twin_available():
        out.notes.append("twin_sequence left out: the twin (MuJoCo) is not installed here.")
        return {}
    presses = ctx.param("twin_presses", TWIN_PRESSES, quick=QUICK_PRESSES)
    jobs = [(d, kind, float(v)) for d in designs for kind, v in presses]
    outcomes = ctx.run_cells(press_sequence, jobs, desc="twin press sequences")
    seqs: dict[str, list[dict]] = {d.name: [] for d in designs}
    cut, failed = [], []
    for (d, kind, v), o in zip(jobs, outcomes):
        if not o.ok:
            failed.append(f"{d.name} {label(kind, v)} ({o.error.splitlines()[0]})")
            continue
        r = dict(o.result, press=label(kind, v))
        if r["invalid_from"]:
            cut.append(f"{d.name} {label(kind, v)} from frame {r['invalid_from']}")
        if r["xyz"]:
            seqs[d.name].append(r)
    out.metric("twin_sequence_presses", len(jobs), "1")
    # the frames left out: the first invalid one of a press and every frame after it
    out.metric("twin_sequence_frames_invalid", sum(o.result["frames"] - len(o.result["xyz"]) for o in outcomes
                                                   if o.ok), "1")
    if cut:
        out.notes.append("twin_sequence: physically invalid frames end their sequence (left out): "
                         + "; ".join(cut) + ".")
    if failed:
        out.notes.append("twin_sequence: presses that raised, left out: " + "; ".join(failed) + ".")
    empty = [name for name, runs in seqs.items() if not runs]
    if empty:
        out.notes.append("twin_sequence left out: no physically valid pressed frame for " + ", ".join(empty) + ".")
        return {}
    return seqs


def read_trials(design, calib, seqs: list[dict], rng: np.random.Generator, n_trials: int, bar=None) -> list[dict]:
    """``n_trials`` frame trials of one design: its sequences read in turn (each from rest, new defects),
    until that many frames have been read; each record also names its press and frame depth."""
    recs: list[dict] = []
    k = 0
    while len(recs) < n_trials:
        s = seqs[k % len(seqs)]
        k += 1
        for i, r in enumerate(read_sequence(design, calib, s["xyz"], rng)):
            if len(recs) < n_trials:
                recs.append(dict(r, press=s["press"], depth_mm=DEPTH_MM * (i + 1) / SEQUENCE_FRAMES))
                if bar is not None:
                    bar.update(1)
    return recs


def table_rows(design, recs: list[dict]) -> list[dict]:
    """Per press and depth: frames read, wrong pairs, mean coverage."""
    rows = []
    for press in dict.fromkeys(r["press"] for r in recs):
        for depth in sorted({r["depth_mm"] for r in recs if r["press"] == press}):
            sel = [r for r in recs if r["press"] == press and r["depth_mm"] == depth]
            rows.append({"design": design.name, "press": press, "depth_mm": depth, "frames": len(sel),
                         "wrong_ids": sum(r["wrong"] for r in sel),
                         "coverage_mean": float(np.mean([r["correct"] / max(r["present"], 1) for r in sel]))})
    return rows
