"""identification: marker ids under missing, spurious, occluded, jittered, rotated and pressed markers.

The contract of :mod:`pipeline.vision.identity`: an id is emitted only when it is certain, so **wrong ids
are zero** in every trial; coverage (the fraction of the markers present in the view that get their
correct id) is what the defects cost. Each trial draws one view (or a stereo pair) of a design's
markers in pixels, applies the condition's defects and runs the unchanged
:func:`pipeline.vision.dtrc.code_rings` (:func:`pipeline.vision.dtrc.match_stereo` for the stereo pair).

Views: the design's rest x-y scaled to 36 px per separation, turned by a uniform in-plane rotation
in +-15 deg, bulged radially by up to 15 % about the centre (an indentation seen from below), a
perspective-like x-scaling of +-5 %, and centre noise uniform in a disc of 0.02 separations
(0.7 px; the detector's error on real frames is ~0.2 px).

Conditions:

* ``defects_R``: R % of the markers removed at random and R % spurious blobs added (R = 0, 1, 3,
  5, 10). Half of the spurious blobs are uniform over the pattern's bounding box (+1 separation),
  half right next to a present marker (0.25-0.8 separations from it). A blob within 0.25
  separations of a marker would merge with it in detection; a blob within 0.5 separations of a
  *missing* marker's slot is indistinguishable from that marker displaced (the certainty rule's
  growth gate is 0.4): neither is drawn. "Separation" is the local one (the marker's nearest-
  neighbour distance in the view), as a press stretches and crowds the pattern.
* ``occlusion_15``: the 15 % of the markers nearest a random point of the pattern are removed (a
  contiguous patch; at the rim half the time). ``coverage_complete_neighbourhood`` counts only the
  visible markers whose design neighbours (within 1.5 separations) are all visible.
* ``occlusion_15_rest``: the same patch in a sensor's first frame read as the runner reads one
  (:func:`pipeline.vision.dtrc.read_from_rest`): ring coding, then, where it leaves a blob
  unidentified, coded again with the rest pattern (where the calibration puts the undeformed skin's
  markers) as the previous frame; that reading replaces ring coding's where ring coding left more than
  a tenth unidentified, and elsewhere only extends it (the same id on every blob ring coding
  identified, and more of them). The view is the rest pattern bulged as above and turned by
  at most +-2 deg (a calibration's error; the cameras are fixed to the skin, so the pattern does not
  turn by the +-15 deg the other conditions draw), without the perspective term (the rest pattern is
  projected through the same cameras).
* ``jitter_30``: centre noise uniform in a disc of 0.3 separations, no other defect.
* ``rotation_30``: the pattern turned by exactly +30 or -30 deg (half the symmetry angle of
  hexagonal and circular patterns: a reading turned by 60 deg is equally good), no other defect.
* ``press_stereo``: both views of an analytic Gaussian press (depth 1-5 mm, sigma 3-6 mm, centre
  within 0.3 pattern radii, lateral bulge 0-0.3) projected through the nominal calibration and the
  refracting stack, each view with its own 3 % missing + 3 % spurious and 0.2 px noise;
  :func:`match_stereo` pairs the ids; a pair is wrong if either view's blob is not that marker.
* ``press_first_frame``: the same presses, the skin also turned by at most +-2 deg about the sensor axis against
  where the calibration puts it, read as ``reconstruct`` reads a sequence's first frame
  (:meth:`pipeline.runner.Reconstructor.identify` on a fresh runner: ring coding, the reading from the rest
  pattern where ring coding leaves a view short, the stereo check).
* ``twin_sequence``: the twin's skin pressed from rest to 5 mm in five frames by Gaussians and sines, read in
  order as ``reconstruct`` reads recorded frames (the previous frame's ids, the stereo check), 3 % missing +
  3 % spurious blobs per view and frame (:mod:`benchmarks.experiments.identification_twin`); a trial is a
  frame. Left out, with a note, where MuJoCo is not installed.

Designs: every built-in marker pattern (the skin variants of hexagon127 share its pattern).
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.registry import Context, Finding, Result, register
from benchmarks.results import PAGE_IN, paper_style, save_figure

#: The coverage each defect condition must reach (mean over trials, every pattern), with zero wrong ids: a marker
#: that cannot be identified is reported unmatched, and these bound how often that may happen.
COVERAGE_GOALS = {"defects_3": 0.99, "defects_10": 0.95}
PATTERN_DESIGNS = ("hexagon61_sep354", "hexagon127", "hexagon217_sep180", "square121", "circular217_dome")
DEFECT_RATES = (0, 1, 3, 5, 10)
CONDITIONS = tuple(f"defects_{r}" for r in DEFECT_RATES) + ("occlusion_15", "occlusion_15_rest", "jitter_30",
                                                             "rotation_30", "press_stereo", "press_first_frame",
                                                             "twin_sequence")
REST_TURN_DEG = 2.0     # occlusion_15_rest: the view's in-plane turn against the rest pattern (a calibration's error)
PX_PER_SEP = 36.0
BASE_JITTER_SEP = 0.02
MERGE_SEP = 0.25        # closer to a marker than this, a blob is that marker (detection merges them)
MISSING_CLEAR_SEP = 0.5  # closer to a missing marker's slot than this, a blob is that marker displaced

__all__ = ["PATTERN_DESIGNS", "CONDITIONS", "view_px", "add_defects", "stereo_views_with_defects", "score_pairs",
           "run_trial"]


def _key(name: str) -> str:
    return name.replace("_dome", "").replace("_sep354", "").replace("_sep180", "")


def rest_px(design) -> np.ndarray:
    """Where a view without press, turn or perspective puts the design's markers (N, 2) px: the rest
    pattern of ``occlusion_15_rest``."""
    return design.rest_markers_mm()[:, :2] * PX_PER_SEP / design.pattern.separation_mm + np.array([320.0, 240.0])


def view_px(design, rng: np.random.Generator, *, rot_deg: float | None = None, jitter_sep: float = BASE_JITTER_SEP,
            perspective: bool = True) -> np.ndarray:
    """One view of the design's markers (N, 2) px in canonical id order (see the module notes)."""
    xy = design.rest_markers_mm()[:, :2]
    R = design.pattern_radius_mm()
    r = np.hypot(*xy.T)
    xy = xy * (1 + rng.uniform(0, 0.15) * np.exp(-(r / (0.5 * R)) ** 2))[:, None]
    t = np.radians(rng.uniform(-15, 15) if rot_deg is None else rot_deg)
    xy = xy @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T
    if perspective:
        xy = xy / (1 + rng.uniform(-0.05, 0.05) * xy[:, 0] / R)[:, None]
    uv = xy * PX_PER_SEP / design.pattern.separation_mm + np.array([320.0, 240.0])
    a = rng.uniform(0, 2 * np.pi, len(uv))
    d = jitter_sep * PX_PER_SEP * np.sqrt(rng.uniform(0, 1, len(uv)))
    return uv + np.column_stack([np.cos(a), np.sin(a)]) * d[:, None]


def add_defects(uv: np.ndarray, rng: np.random.Generator, *, missing: float = 0.0, spurious: float = 0.0,
                occlusion: float = 0.0, px_per_sep: float = PX_PER_SEP, hidden=()):
    """Remove and add blobs (``hidden``: ids removed besides, as an occluded patch). Returns (blob centres
    (M, 2) in random order, true id per blob (-1 spurious), ids removed)."""
    from scipy.spatial import cKDTree

    n = len(uv)
    gone = set(rng.choice(n, int(round(missing * n)), replace=False).tolist()) if missing else set()
    gone |= {int(i) for i in hidden}
    if occlusion:
        centre = uv[rng.integers(n)] if rng.random() < 0.5 else uv[np.argmax(np.hypot(*(uv - uv.mean(0)).T))]
        gone |= set(np.argsort(np.hypot(*(uv - centre).T))[:int(round(occlusion * n))].tolist())
    gone_ids = np.array(sorted(gone), np.int64)
    keep = np.setdiff1d(np.arange(n), gone_ids)
    extra = []
    n_sp = int(round(spurious * n))
    if n_sp:
        t_keep = cKDTree(uv[keep])
        t_gone = cKDTree(uv[gone_ids]) if len(gone_ids) else None
        # "a separation" is the local one: a press stretches and crowds the pattern in the image
        local = cKDTree(uv).query(uv, k=2)[0][:, 1]
        lo, hi = uv.min(axis=0) - px_per_sep, uv.max(axis=0) + px_per_sep
        for _ in range(1000 * n_sp):
            if len(extra) == n_sp:
                break
            if rng.random() < 0.5:
                c = uv[keep[rng.integers(len(keep))]]
                a = rng.uniform(0, 2 * np.pi)
                q = c + rng.uniform(MERGE_SEP, 0.8) * px_per_sep * np.array([np.cos(a), np.sin(a)])
            else:
                q = rng.uniform(lo, hi)
            dk, jk = t_keep.query(q)
            if dk < MERGE_SEP * local[keep[jk]]:
                continue
            if t_gone is not None:
                dg, jg = t_gone.query(q)
                if dg < MISSING_CLEAR_SEP * local[gone_ids[jg]]:
                    continue
            extra.append(q)
    pts = np.vstack([uv[keep], np.asarray(extra).reshape(-1, 2)])
    truth = np.concatenate([keep, np.full(len(extra), -1, np.int64)])
    perm = rng.permutation(len(pts))
    return pts[perm], truth[perm], gone_ids


def stereo_views_with_defects(views, rng: np.random.Generator, rate: float, noise_px: float = 0.2) -> list:
    """Both views' marker projections (px) with ``noise_px`` centre noise and each view's own ``rate``
    missing + ``rate`` spurious blobs (:func:`add_defects`, the separation the view's median nearest-neighbour
    distance): [(pts, truth) left, (pts, truth) right]."""
    sides = []
    for uv in views:
        uv = uv + rng.normal(0, noise_px, uv.shape)
        nn = np.sort(np.hypot(*(uv[:, None, :] - uv[None, :, :]).transpose(2, 0, 1)), axis=1)[:, 1]
        sides.append(add_defects(uv, rng, missing=rate, spurious=rate, px_per_sep=float(np.median(nn)))[:2])
    return sides


def score_pairs(m, sides: list) -> dict:
    """{"wrong", "correct", "present"} of the pairs ``m`` (MarkerMatches) against the views' truth ``sides``
    (:func:`stereo_views_with_defects`): a pair is wrong if either view's blob is not that marker; present
    counts the markers present in both views."""
    owner = [{tuple(p): t for p, t in zip(pts.tolist(), truth.tolist())} for pts, truth in sides]
    ok = np.array([owner[0][tuple(a)] == i and owner[1][tuple(b)] == i
                   for i, a, b in zip(m.ids.tolist(), m.left_px.tolist(), m.right_px.tolist())], bool)
    present = len(set(sides[0][1][sides[0][1] >= 0].tolist()) & set(sides[1][1][sides[1][1] >= 0].tolist()))
    return {"wrong": int((~ok).sum()), "correct": int(ok.sum()), "present": present}


def _blobs(pts):
    from pipeline.types import Blobs

    return Blobs(np.ascontiguousarray(pts), np.full(len(pts), 3.0), np.ones(len(pts)))


def _complete_neighbourhood(design, gone_ids: np.ndarray) -> np.ndarray:
    """Ids whose design neighbours within 1.5 separations are all present (and which are present)."""
    from pipeline.vision.identity import lattice_of

    lat = lattice_of(design)
    ok = np.ones(len(lat.xy), bool)
    ok[gone_ids] = False
    nb = lat.nbr
    full = ok.copy()
    full &= np.all((nb < 0) | ok[np.maximum(nb, 0)], axis=1)
    return np.flatnonzero(full)


def run_trial(design, condition: str, rng: np.random.Generator, calib=None) -> dict:
    """One trial: {"wrong": ids emitted for the wrong blob, "correct": right ids, "present": markers
    present (in both views for stereo), and for occlusion "complete"/"complete_correct"}."""
    from pipeline.vision.dtrc import code_rings, match_stereo, read_from_rest

    if condition in ("press_stereo", "press_first_frame"):
        from pipeline.geometry.refraction import project_through_stack
        from pipeline.io.synthetic import gaussian_press_markers

        R = design.pattern_radius_mm()
        c = rng.uniform(-0.3, 0.3, 2) * R
        xyz = gaussian_press_markers(design, rng.uniform(1.0, 5.0), sigma_mm=rng.uniform(3.0, 6.0),
                                     centre_xy_mm=(float(c[0]), float(c[1])), lateral=rng.uniform(0.0, 0.3))
        if condition == "press_first_frame":
            # the skin turned about the sensor axis against where the calibration puts it (a calibration's error)
            t = np.radians(rng.uniform(-REST_TURN_DEG, REST_TURN_DEG))
            xyz = xyz @ np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]]).T
        sides = stereo_views_with_defects(project_through_stack(xyz, calib, design), rng, 0.03)
        left, right = _blobs(sides[0][0]), _blobs(sides[1][0])
        if condition == "press_stereo":
            return score_pairs(match_stereo(left, right, design), sides)
        from pipeline.runner import Reconstructor

        return score_pairs(Reconstructor(design, calib, view_threads=1).identify(left, right), sides)
    kw: dict = {}
    rot = None
    jitter = BASE_JITTER_SEP
    if condition.startswith("defects_"):
        r = int(condition.split("_")[1]) / 100
        kw = {"missing": r, "spurious": r}
    elif condition in ("occlusion_15", "occlusion_15_rest"):
        kw = {"occlusion": 0.15}
    elif condition == "jitter_30":
        jitter = 0.3
    elif condition == "rotation_30":
        rot = 30.0 if rng.random() < 0.5 else -30.0
    else:
        raise ValueError(f"unknown condition {condition!r}")
    from_rest = condition == "occlusion_15_rest"
    if from_rest:
        rot = rng.uniform(-REST_TURN_DEG, REST_TURN_DEG)
    uv = view_px(design, rng, rot_deg=rot, jitter_sep=jitter, perspective=not from_rest)
    pts, truth, gone = add_defects(uv, rng, **kw)
    coding = code_rings(_blobs(pts), design)
    if from_rest:
        rest = rest_px(design)
        coding = read_from_rest(_blobs(pts), design, coding, (rest, np.arange(len(rest), dtype=np.int64)))
    ids = coding.ids
    coded = ids >= 0
    out = {"wrong": int(np.sum(ids[coded] != truth[coded])), "correct": int(np.sum(ids[coded] == truth[coded])),
           "present": int(np.sum(truth >= 0))}
    if condition.startswith("occlusion_15"):
        full = _complete_neighbourhood(design, gone)
        got = set(ids[coded & (ids == truth)].tolist())
        out["complete"] = len(full)
        out["complete_correct"] = len(got & set(full.tolist()))
    return out


@register(
    "identification",
    tags=("quick", "cheap"),
    metrics={
        "wrong_ids_total": "1",
        "wrong_ids_rotation_30": "1",
        "wrong_ids_jitter_30": "1",
        "coverage_defects_0_min": "1",
        "coverage_defects_3_min": "1",
        "coverage_defects_10_min": "1",
        "coverage_occlusion_15_min": "1",
        "coverage_complete_neighbourhood_occlusion_15_min": "1",
        "coverage_occlusion_15_rest_min": "1",
        "coverage_complete_neighbourhood_occlusion_15_rest_min": "1",
        "coverage_press_stereo_min": "1", "coverage_press_first_frame_min": "1",
        "coverage_twin_sequence_min": "1",
        "wrong_ids_twin_sequence": "1",
        "twin_sequence_presses": "1",
        "twin_sequence_frames_invalid": "1",
        "trials_per_condition": "1",
        "trials_total": "1",
        **{f"coverage_defects_3_{_key(d)}": "1" for d in PATTERN_DESIGNS},
        **{f"coverage_defects_10_{_key(d)}": "1" for d in PATTERN_DESIGNS},
    },
    requires=("pipeline.vision.dtrc", "pipeline.vision.identity"),
)
def run(ctx: Context) -> Result:
    """Marker ids under missing/spurious/occluded/jittered/rotated/pressed markers: wrong ids (must be 0) and coverage."""
    from pipeline.io.synthetic import nominal_calibration

    n_trials = int(ctx.param("n_trials", 1000, quick=12))
    names = tuple(ctx.param("designs", PATTERN_DESIGNS))
    conditions = tuple(ctx.param("conditions", CONDITIONS))
    designs = ctx.designs(names)
    out = Result(designs=designs)
    from benchmarks.experiments import identification_twin as twin_cond

    sequences = twin_cond.press_all(ctx, out, designs) if "twin_sequence" in conditions else {}
    twin_trials = int(ctx.param("twin_trials", n_trials, quick=30))
    if "twin_sequence" in conditions and not sequences:
        conditions = tuple(c for c in conditions if c != "twin_sequence")
    rows, twin_rows = [], []
    total = len(designs) * sum(twin_trials if c == "twin_sequence" else n_trials for c in conditions)
    bar = ctx.bar(total=total, desc="identification")
    for design in designs:
        calib = nominal_calibration(design)
        for cond in conditions:
            rng = ctx.rng(f"{design.name}/{cond}")
            t0 = time.perf_counter()
            recs = []
            if cond == "twin_sequence":
                recs = twin_cond.read_trials(design, calib, sequences[design.name], rng, twin_trials, bar)
                twin_rows.extend(twin_cond.table_rows(design, recs))
            for _ in range(n_trials if cond != "twin_sequence" else 0):
                recs.append(run_trial(design, cond, rng, calib))
                bar.update(1)
            cov = np.array([r["correct"] / max(r["present"], 1) for r in recs])
            row = {"design": design.name, "condition": cond, "trials": len(recs),
                   "wrong_ids": int(sum(r["wrong"] for r in recs)),
                   "trials_with_wrong_ids": int(sum(r["wrong"] > 0 for r in recs)),
                   "coverage_mean": float(cov.mean()), "coverage_min": float(cov.min()),
                   "coverage_p05": float(np.percentile(cov, 5)),
                   "ms_per_trial": 1e3 * (time.perf_counter() - t0) / n_trials}
            if cond.startswith("occlusion_15"):
                cc = np.array([r["complete_correct"] / max(r["complete"], 1) for r in recs])
                row["coverage_complete_neighbourhood_mean"] = float(cc.mean())
            rows.append(row)
    bar.close()
    out.tables["conditions"] = rows
    if twin_rows:
        out.tables["twin_sequence"] = twin_rows

    def rows_of(cond):
        return [r for r in rows if r["condition"] == cond]

    out.metric("wrong_ids_total", sum(r["wrong_ids"] for r in rows), "1")
    for cond in ("rotation_30", "jitter_30", "twin_sequence"):
        if rows_of(cond):
            out.metric(f"wrong_ids_{cond}", sum(r["wrong_ids"] for r in rows_of(cond)), "1")
    for cond in ("defects_0", "defects_3", "defects_10", "occlusion_15", "occlusion_15_rest", "press_stereo",
                 "press_first_frame", "twin_sequence"):
        if rows_of(cond):
            out.metric(f"coverage_{cond}_min", min(r["coverage_mean"] for r in rows_of(cond)), "1")
    for cond in ("occlusion_15", "occlusion_15_rest"):
        if rows_of(cond):
            out.metric(f"coverage_complete_neighbourhood_{cond}_min",
                       min(r["coverage_complete_neighbourhood_mean"] for r in rows_of(cond)), "1")
    for cond in ("defects_3", "defects_10"):
        for r in rows_of(cond):
            if r["design"] in PATTERN_DESIGNS:
                out.metric(f"coverage_{cond}_{_key(r['design'])}", r["coverage_mean"], "1")
    out.metric("trials_per_condition", n_trials, "1")
    out.metric("trials_total", total, "1")
    out.notes.append(f"{n_trials} seeded trials per condition and design; coverage = markers present in the "
                     "view (both views for the stereo conditions) that got their correct id, mean over trials; spurious "
                     f"blobs are kept >= {MERGE_SEP} separations from present markers and >= {MISSING_CLEAR_SEP} "
                     "from missing markers' slots (module notes).")
    wrong = sum(r["wrong_ids"] for r in rows)
    out.findings.append(Finding("an id is emitted only when it is certain: zero wrong ids",
                                f"{wrong} wrong ids in {total} trials", wrong == 0))

    with paper_style() as plt:
        fig, axes = plt.subplots(1, 2, figsize=(PAGE_IN, 2.4))
        rates = [r for r in DEFECT_RATES if rows_of(f"defects_{r}")]
        for k, design in enumerate(designs):
            cov = [next(x["coverage_mean"] for x in rows_of(f"defects_{r}") if x["design"] == design.name) for r in rates]
            wr = [next(x["wrong_ids"] for x in rows_of(f"defects_{r}") if x["design"] == design.name) for r in rates]
            axes[0].plot(rates, cov, "o-", color=f"C{k}", label=design.name, ms=3)
            axes[1].plot(rates, wr, "o-", color=f"C{k}", label=design.name, ms=3)
        for goal in COVERAGE_GOALS.values():
            axes[0].axhline(goal, color="k", ls=":", lw=0.6)
        axes[0].set_xlabel("missing = spurious blobs (% of markers)")
        axes[0].set_ylabel("coverage (correct ids / present)")
        axes[1].set_xlabel("missing = spurious blobs (% of markers)")
        axes[1].set_ylabel(f"wrong ids (sum over {n_trials} trials)")
        axes[0].legend(fontsize=5)
        fig.tight_layout()
        out.figures.append(save_figure(fig, ctx.figure_path("identification")))
    return out
