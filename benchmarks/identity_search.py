"""A search for wrong ids beyond the identification benchmark's conditions: single views pressed 5 mm by
sharp Gaussians, off the axis, with missing and spurious blobs.

The identification benchmark holds the certainty rule to zero wrong ids in its own conditions; the searches
recorded in docs/IDENTIFICATION.md drew wider. This module draws searches of that kind from a seed, so a change
to the rule can be run against them (the off-axis circular217 searches recorded there are these draws: seed
777, 4,000 draws, and seed 20261127, 1,000; the earlier sharp-press searches drew patterns and parameters in
another order)::

    python -m benchmarks.identity_search --design circular217_dome --draws 4000 --seed 777

Each draw: a defect seed, sigma uniform in ``--sigma`` (mm), lateral bulge in [0, ``--lateral``], missing
and spurious rate each in [0, ``--rate``], press centre uniform in angle and radius in [0, ``--off``] mm; the
left view of the analytic press (:func:`pipeline.io.synthetic.gaussian_press_markers` through the nominal
calibration and the refracting stack) with the defects of the identification benchmark
(:func:`benchmarks.experiments.identification.add_defects`). A view is in scope when no two markers are
closer than half the median separation (such pins merge in detection). Prints the views in scope, the wrong
ids and the views holding them, and the coverage; ``--out FILE`` writes every view's figures as JSON.

``--hidden LOW HIGH`` also hides, in each draw, a fraction of the markers in that range about a point within
``--hidden-within`` separations of the pattern's centre (1.5 unless given; a glare spot; no spurious blob within
half a separation of a hidden marker, as for a missing one), and on a circular pattern reports the twist of
every true reading that lacks the centre rings: what the centre test of such a reading bounds
(``ANNULUS_TWIST``; the search recorded in docs/IDENTIFICATION.md: ``--draws 4000 --seed 29 --sigma 1.5 6 --off 3
--rate 0.05 --lateral 0.5 --hidden 0.05 0.25``).

``--sequences`` draws press sequences instead, read in stereo through one runner as a recording is
(:func:`dragged_sequence`, :func:`sequence_search`): a Gaussian tip deepened 1 mm a frame to 5 mm while it
slides up to 2 mm a frame, each view of each frame with its own missing and spurious blobs; the k-th sequence is
drawn from seed ``--seed`` + k, and the figures are the frames' pairs (wrong: either view's blob is not that
marker) against the markers present in both views (the search recorded in docs/IDENTIFICATION.md: ``--sequences
--design D --draws 120 --seed 5000``, each pattern)::

    python -m benchmarks.identity_search --sequences --design hexagon217_sep180 --draws 120 --seed 5000
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from pipeline.errors import UserError

__all__ = ["dragged_sequence", "pressed_view", "search", "sequence_search"]

DEPTH_MM = 5.0


def pressed_view(design, seed: int, sigma_mm: float, lateral: float, rate: float,
                 centre_xy_mm: tuple[float, float] = (0.0, 0.0), hidden: float = 0.0,
                 hidden_at: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, bool]:
    """(blob centres px, true id per blob (-1 spurious), in scope) of one draw (module notes); ``hidden``: the
    fraction of the markers hidden (a glare spot), those nearest the view of the pattern's centre moved by
    ``hidden_at`` median separations."""
    from benchmarks.experiments.identification import add_defects
    from pipeline.geometry.refraction import project_through_stack
    from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration

    xyz = gaussian_press_markers(design, DEPTH_MM, sigma_mm=sigma_mm, lateral=lateral, centre_xy_mm=centre_xy_mm)
    uv = np.ascontiguousarray(project_through_stack(xyz, nominal_calibration(design), design)[0])
    nn = np.sort(np.hypot(*(uv[:, None, :] - uv[None, :, :]).transpose(2, 0, 1)), axis=1)[:, 1]
    spot = uv[np.argmin(np.hypot(*design.rest_markers_mm()[:, :2].T))] + np.asarray(hidden_at) * np.median(nn)
    hide = np.argsort(np.hypot(*(uv - spot).T))[:int(round(hidden * len(uv)))]
    pts, truth, _ = add_defects(uv, np.random.default_rng(seed), missing=rate, spurious=rate,
                                px_per_sep=float(np.median(nn)), hidden=hide)
    return pts, truth, bool(nn.min() >= 0.5 * np.median(nn))


def search(design_name: str, draws: int, seed: int, *, sigma=(1.0, 5.0), lateral: float = 0.6, rate: float = 0.1,
           off_mm: float = 6.0, hidden=(0.0, 0.0), hidden_within: float = 1.5, progress: bool = False) -> dict:
    """Run the search; returns {"in_scope", "wrong_ids", "wrong_views", "coverage", "seconds", "views": [...]}.

    With ``hidden`` (a fraction range, upper bound above 0) each draw also hides a fraction of the markers in
    that range about a point within ``hidden_within`` separations of the pattern's centre, and, for a circular
    pattern, each view whose true reading lacks the centre rings records that reading's twist
    (:func:`pipeline.vision.identity.centring.annulus_twist`: what the certainty rule's centre test measures;
    the result adds "twist": {"readings", "max", "p99", "refused"})."""
    from tqdm import tqdm

    from pipeline.design import load_design
    from pipeline.types import Blobs
    from pipeline.vision.dtrc import code_rings

    if draws < 1:
        raise UserError(f"--draws {draws}: at least one draw")
    if not 0 < sigma[0] <= sigma[1]:
        raise UserError(f"--sigma {sigma[0]:g} {sigma[1]:g}: need 0 < low <= high (mm)")
    if not (0 <= lateral and 0 <= rate < 0.5 and 0 <= off_mm):
        raise UserError("--lateral, --rate and --off must be >= 0 (rate below 0.5)")
    if not 0 <= hidden[0] <= hidden[1] < 0.5:
        raise UserError(f"--hidden {hidden[0]:g} {hidden[1]:g}: need 0 <= low <= high < 0.5")
    if not hidden_within >= 0:
        raise UserError(f"--hidden-within {hidden_within:g}: need >= 0 (separations)")
    design = load_design(design_name)
    rng = np.random.default_rng(seed)
    views, t0 = [], time.perf_counter()
    for _ in tqdm(range(draws), desc=f"search {design.name}", disable=not progress, leave=False):
        s = int(rng.integers(2**32))
        sg, lt, rt = float(rng.uniform(*sigma)), float(rng.uniform(0, lateral)), float(rng.uniform(0, rate))
        r, a = float(rng.uniform(0, off_mm)), float(rng.uniform(0, 2 * np.pi))
        centre = (r * np.cos(a), r * np.sin(a))
        hide, at = 0.0, (0.0, 0.0)
        if hidden[1] > 0:
            hide, ra = float(rng.uniform(*hidden)), float(rng.uniform(0, hidden_within))
            aa = float(rng.uniform(0, 2 * np.pi))
            at = (ra * np.cos(aa), ra * np.sin(aa))
        pts, truth, in_scope = pressed_view(design, s, sg, lt, rt, centre, hide, at)
        if not in_scope:
            continue
        ids = code_rings(Blobs(pts, np.full(len(pts), 3.0), np.ones(len(pts))), design).ids
        coded = ids >= 0
        views.append({"seed": s, "sigma_mm": sg, "lateral": lt, "rate": rt, "centre_mm": list(centre),
                      "present": int(np.count_nonzero(truth >= 0)),
                      "correct": int(np.count_nonzero(ids[coded] == truth[coded])),
                      "wrong": int(np.count_nonzero(ids[coded] != truth[coded]))})
        if hidden[1] > 0:
            views[-1].update(hidden=hide, hidden_at=list(at), twist=_true_twist(pts, truth, design))
    present = sum(v["present"] for v in views)
    out = {"design": design.name, "draws": draws, "seed": seed, "in_scope": len(views),
           "wrong_ids": sum(v["wrong"] for v in views), "wrong_views": sum(v["wrong"] > 0 for v in views),
           "coverage": sum(v["correct"] for v in views) / present if present else float("nan"),
           "seconds": time.perf_counter() - t0, "views": views}
    if hidden[1] > 0:
        from pipeline.vision.identity.constants import ANNULUS_TWIST

        tw = np.array([v["twist"] for v in views if v["twist"] is not None])
        out["twist"] = {"readings": len(tw), "max": float(tw.max()) if len(tw) else None,
                        "p99": float(np.percentile(tw, 99)) if len(tw) else None,
                        "refused": int(np.count_nonzero(tw > ANNULUS_TWIST))}
    return out


def dragged_sequence(design, seed: int, frames: int = 5, calib=None, runner=None) -> list[dict]:
    """One sequence of the sequence search (module notes), drawn from ``seed``: a Gaussian tip (sigma uniform in
    1-6 mm, centre uniform in [-5, 5] mm in x and y) deepened 1 mm a frame while it slides (uniform in [0, 2] mm a
    frame in x and in y), bulge in [0, 0.5], each view of each frame with its own missing and spurious blobs
    (rate in [0, 0.1]) and 0.2 px centre noise, read frame by frame through one runner
    (:meth:`pipeline.runner.Reconstructor.identify`). Per frame: {"wrong", "correct", "present"} of its pairs
    (:func:`benchmarks.experiments.identification.score_pairs`)."""
    from benchmarks.experiments.identification import _blobs, score_pairs, stereo_views_with_defects
    from pipeline.geometry.refraction import project_through_stack
    from pipeline.io.synthetic import gaussian_press_markers, nominal_calibration
    from pipeline.runner import Reconstructor

    calib = nominal_calibration(design) if calib is None else calib
    rng = np.random.default_rng(seed)
    sigma, (cx, cy), slide, rate, lateral = (rng.uniform(1.0, 6.0), rng.uniform(-5, 5, 2), rng.uniform(0, 2.0, 2),
                                             rng.uniform(0, 0.1), rng.uniform(0, 0.5))
    rec = Reconstructor(design, calib, view_threads=1) if runner is None else runner
    out = []
    for k in range(1, frames + 1):
        xyz = gaussian_press_markers(design, float(k), sigma_mm=sigma, lateral=lateral,
                                     centre_xy_mm=(cx + slide[0] * k, cy + slide[1] * k))
        sides = stereo_views_with_defects(project_through_stack(xyz, calib, design), rng, rate, 0.2)
        out.append(score_pairs(rec.identify(_blobs(sides[0][0]), _blobs(sides[1][0])), sides))
    return out


def sequence_search(design_name: str, sequences: int, seed: int, *, progress: bool = False) -> dict:
    """The sequence search: ``sequences`` draws of :func:`dragged_sequence`, the k-th from seed ``seed + k``;
    returns {"frames", "wrong_pairs", "wrong_sequences", "coverage" (correct pairs over markers present in both
    views), "seconds", "sequences": [{"seed", "wrong", "correct", "present"}]}."""
    from tqdm import tqdm

    from pipeline.design import load_design
    from pipeline.io.synthetic import nominal_calibration

    if sequences < 1:
        raise UserError(f"--draws {sequences}: at least one draw")
    design = load_design(design_name)
    calib = nominal_calibration(design)
    rows, t0 = [], time.perf_counter()
    for k in tqdm(range(sequences), desc=f"sequences {design.name}", disable=not progress, leave=False):
        s = seed + k
        frames = dragged_sequence(design, s, calib=calib)
        rows.append({"seed": s, **{k: [f[k] for f in frames] for k in ("wrong", "correct", "present")}})
    present = sum(sum(r["present"]) for r in rows)
    return {"design": design.name, "draws": sequences, "seed": seed, "frames": sum(len(r["wrong"]) for r in rows),
            "wrong_pairs": sum(sum(r["wrong"]) for r in rows), "wrong_sequences": sum(sum(r["wrong"]) > 0 for r in rows),
            "coverage": sum(sum(r["correct"]) for r in rows) / present if present else float("nan"),
            "seconds": time.perf_counter() - t0, "sequences": rows}


def _true_twist(pts: np.ndarray, truth: np.ndarray, design) -> float | None:
    """The twist the centre test measures on the view's true reading when it lacks the centre rings (circular
    patterns), else None."""
    from pipeline.vision.identity import lattice_of
    from pipeline.vision.identity.centring import annulus_twist, centre_rings_covered

    lat = lattice_of(design)
    members = np.flatnonzero(truth >= 0)
    if lat.translation_lattice or centre_rings_covered(truth, members, lat.layer_of):
        return None
    return annulus_twist(pts, truth, members, lat)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.identity_search", description=__doc__.split("\n\n")[0])
    ap.add_argument("--design", default="circular217_dome")
    ap.add_argument("--draws", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--sigma", type=float, nargs=2, default=(1.0, 5.0), metavar=("LOW", "HIGH"))
    ap.add_argument("--lateral", type=float, default=0.6)
    ap.add_argument("--rate", type=float, default=0.1)
    ap.add_argument("--off", type=float, default=6.0, help="largest distance of the press centre from the axis, mm")
    ap.add_argument("--hidden", type=float, nargs=2, default=(0.0, 0.0), metavar=("LOW", "HIGH"),
                    help="hide a fraction of the markers in this range about a point near the pattern's centre")
    ap.add_argument("--hidden-within", type=float, default=1.5, metavar="SEPS",
                    help="the hidden patch's centre lies within this many median separations of the pattern's "
                         "centre (default 1.5; the pattern's radius in separations puts it anywhere, the rim included)")
    ap.add_argument("--sequences", action="store_true",
                    help="draw press sequences read in stereo through one runner instead of single views (the "
                         "sequence search; --draws sequences, the other draw options do not apply)")
    ap.add_argument("--out", default=None, help="write every view's figures as JSON")
    args = ap.parse_args(argv)
    if args.sequences:
        try:
            res = sequence_search(args.design, args.draws, args.seed, progress=sys.stderr.isatty())
        except UserError as exc:
            print(f"identity_search: {exc}", file=sys.stderr)
            return 2
        print(f"{res['design']}: {res['draws']} sequences, {res['frames']} frames, {res['wrong_pairs']} wrong "
              f"pair(s) in {res['wrong_sequences']} sequence(s), coverage {100 * res['coverage']:.2f} %, "
              f"{res['seconds']:.0f} s")
        for r in res["sequences"]:
            if sum(r["wrong"]):
                print(f"  wrong: sequence seed {r['seed']}: wrong pairs per frame {r['wrong']}")
        if args.out:
            from pipeline.io.atomic import atomic_write_json

            atomic_write_json(args.out, res, indent=1)
        return 0
    try:
        res = search(args.design, args.draws, args.seed, sigma=tuple(args.sigma), lateral=args.lateral,
                     rate=args.rate, off_mm=args.off, hidden=tuple(args.hidden), hidden_within=args.hidden_within,
                     progress=sys.stderr.isatty())
    except UserError as exc:
        print(f"identity_search: {exc}", file=sys.stderr)
        return 2
    print(f"{res['design']}: {res['in_scope']} of {res['draws']} views in scope, {res['wrong_ids']} wrong id(s) in "
          f"{res['wrong_views']} view(s), coverage {100 * res['coverage']:.1f} %, {res['seconds']:.0f} s")
    if "twist" in res:
        tw = res["twist"]
        print(f"  true readings without the centre rings: {tw['readings']}, their twist at most "
              f"{tw['max'] if tw['max'] is None else round(tw['max'], 3)} (99 % below "
              f"{tw['p99'] if tw['p99'] is None else round(tw['p99'], 3)}), {tw['refused']} beyond the rule's bound")
    for v in res["views"]:
        if v["wrong"]:
            print(f"  wrong: seed {v['seed']}, sigma {v['sigma_mm']:.4f} mm, lateral {v['lateral']:.4f}, rate "
                  f"{v['rate']:.4f}, centre ({v['centre_mm'][0]:.4f}, {v['centre_mm'][1]:.4f}) mm: {v['wrong']} of "
                  f"{v['correct'] + v['wrong']}")
    if args.out:
        from pipeline.io.atomic import atomic_write_json

        atomic_write_json(args.out, res, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
