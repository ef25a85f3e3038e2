"""The README's Pipeline and renderer tables (blocks ``pipeline-accuracy`` and ``renderer-accuracy``), written
from a ``bench accuracy`` record and, for the Pipeline table's latency row, a ``bench latency`` record of the
same directory (the README's are kept in ``docs/records/pipeline-accuracy``), and the certainty rule's headline
(``identification-summary``, from a ``bench identification`` record).

Each row names what was measured, the record's figure, the tolerance it answers to (derived in
:mod:`benchmarks.experiments.accuracy`, where the tests take them from too) and the command that reproduces it.
"""

from __future__ import annotations

from typing import Any, Mapping

from benchmarks.experiments.accuracy import (CENTRE_MAX_TOL_PX, CENTRE_RMS_TOL_PX, E2E_TOL_MM, EXACT_TOL_MM,
                                            RENDER_CENTROID_TOL_PX, TRACE_AREA_TOL, TRACE_CENTROID_TOL_PX)
from benchmarks.readme_render import _CONDITION_LABELS, _DESIGN_LABELS, Records, _provenance, _verdict_met
from benchmarks.report import _fmt
from benchmarks.results import ResultsError

__all__ = ["pipeline_accuracy_markdown", "renderer_accuracy_markdown", "identification_summary_markdown"]


def _metric(rec: Mapping[str, Any], name: str) -> float | None:
    return ((rec.get("metrics") or {}).get(name) or {}).get("value")


def _need(records: Records, name: str, block: str, source: str) -> Mapping[str, Any]:
    if name not in records:
        raise ResultsError(f"{source}: no {name!r} record: the {block} block is written from a directory holding "
                           f"a `stereotactip bench {name}` record")
    return records[name]


def _real_frames_row(acc: Mapping[str, Any]) -> tuple[str, str, str, str]:
    what = "pins found on real TacTip frames (331 pins), monocular dome parameters (`MONOCULAR_DOME`)"
    n = _metric(acc, "real_frames")
    how = "`stereotactip bench accuracy --param real_frames=DIR`; `pytest tests/test_detection.py -k real`"
    if n is None:
        return what, "not measured in this record (no `--param real_frames=DIR`)", "331", how
    rows = (acc.get("tables") or {}).get("real_frames") or []
    closest = min((r["closest_over_median"] for r in rows), default=None)
    lo, hi = int(_metric(acc, "real_found_min")), int(_metric(acc, "real_found_max"))
    found = f"{lo} on every one of the {int(n)} frames" if lo == hi else f"{lo}–{hi} on {int(n)} frames"
    med, p95 = _metric(acc, "real_detect_ms_median"), _metric(acc, "real_detect_ms_p95")
    timing = "" if med is None else f"; detection {_fmt(med)} ms a view (median; p95 {_fmt(p95)}; one thread)"
    return (what, f"{found}; closest two centres {_fmt(closest)} of the median separation; "
            f"{int(_metric(acc, 'real_in_glare'))} inside saturated LED glare{timing}",
            "331 — " + _verdict_met(lo == hi == 331), how)


def _latency_row(lat: Mapping[str, Any]) -> tuple[str, str, str, str]:
    from benchmarks.latency import GOAL_MEDIAN_MS, PAPER_LATENCY_MS

    designs = lat.get("designs_used") or []
    stages: dict[str, dict[str, float]] = {}
    for row in (lat.get("tables") or {}).get("stages") or []:
        stages.setdefault(row["design"], {})[row["stage"]] = row["median_ms"]
    parts, met = [], []
    for name in designs:
        key = "circular217" if name == "circular217_dome" else name
        med, p95 = _metric(lat, f"median_total_ms_{key}"), _metric(lat, f"p95_total_ms_{key}")
        st = stages.get(name, {})
        split = ", ".join(f"{s} {_fmt(v, 2)}" for s, v in st.items() if s != "total")
        parts.append(f"{_DESIGN_LABELS.get(name, name)} **{_fmt(med, 3)} ms** (p95 {_fmt(p95, 3)}; {split})")
        met.append(f"{_DESIGN_LABELS.get(name, name)} {_verdict_met(med is not None and med <= GOAL_MEDIAN_MS)}")
    params = lat.get("params") or {}
    load = f", {params['background_procs']} process(es) spinning beside it" if params.get("background_procs") else ""
    nice = f", frames at niceness {params['nice']}" if params.get("nice") is not None else ""
    frames = int(_metric(lat, "frames_per_design") or 0)
    views = _metric(lat, "view_threads")
    where = "one thread" if views is None or int(views) == 1 else "the two views on two threads"
    both = "; detect and match add up both views' work, views is its wall time" if where != "one thread" else ""
    what = (f"latency, raw stereo frame → surface, {where} ({frames} analytic frames a design{load}{nice}; "
            f"median per stage in ms{both})")
    got = (f"{'; '.join(parts)}; the fixed reference job ran {_fmt(_metric(lat, 'reference_ms_median'), 3)} ms "
           f"(the frame in its units: {_fmt(_metric(lat, 'total_over_reference'), 3)}, worst design)")
    return what, got, f"paper {PAPER_LATENCY_MS:g} ms; goal ≤ {GOAL_MEDIAN_MS:g} ms median — {', '.join(met)}", \
        "`stereotactip bench latency --out DIR` (`--quick`: 40 frames)"


def pipeline_accuracy_markdown(records: Records, source: str) -> str:
    """The Pipeline table: real-frame detection, sub-pixel centres, end to end, refraction models, latency."""
    acc = _need(records, "accuracy", "pipeline-accuracy", source)
    lat = _need(records, "latency", "pipeline-accuracy", source)
    tables = acc.get("tables") or {}
    sub = tables.get("subpixel") or []
    e2e = tables.get("end_to_end") or []
    ref = tables.get("refraction") or []
    ref_design = (acc.get("design") or {}).get("name", "?")
    rms, worst = _metric(acc, "centre_rms_px_max"), _metric(acc, "centre_max_px")
    e2e_max = _metric(acc, "e2e_max_mm")
    exact = _metric(acc, "exact_refraction_error_max_mm")
    designs = ", ".join(_DESIGN_LABELS.get(d, d) for d in dict.fromkeys(r["design"] for r in e2e))
    depths = " and ".join(f"{d:g}" for d in dict.fromkeys(r["depth_mm"] for r in e2e))
    matched = sum(r["matched"] for r in e2e)
    visible = sum(r["visible"] for r in e2e)
    lin = "; ".join(f"{r['depth_mm']:g} mm: {100 * r['linear_rel_error_centre']:.1f} % → "
                    f"{100 * r['linear_rel_error_outer']:.1f} %" for r in ref)
    rows = [
        _real_frames_row(acc),
        ("sub-pixel centre error, analytic discs r = " + " / ".join(f"{r['radius_px']:g}" for r in sub) + " px",
         f"RMS {' / '.join(_fmt(r['rms_px'], 2) for r in sub)} px, worst {_fmt(worst, 2)} px",
         f"RMS ≤ {CENTRE_RMS_TOL_PX:g}, worst ≤ {CENTRE_MAX_TOL_PX:g} px — "
         + _verdict_met(rms is not None and rms <= CENTRE_RMS_TOL_PX and worst <= CENTRE_MAX_TOL_PX),
         "`stereotactip bench accuracy`; `pytest tests/test_detection.py`"),
        (f"end-to-end 3-D error, analytic stereo frames through the exact stack ({designs}; {depths} mm presses)",
         f"median {_fmt(_metric(acc, 'e2e_median_mm'), 2)} mm, max {_fmt(e2e_max, 2)} mm; {matched} of {visible} "
         "visible markers matched",
         f"≤ {E2E_TOL_MM:g} mm — "
         + _verdict_met(e2e_max is not None and e2e_max <= E2E_TOL_MM and matched == visible),
         "`stereotactip bench accuracy`; `pytest tests/test_runner.py`"),
        ("the paper's linear refraction model vs the exact stack, pure depth moves of the rest pattern "
         f"({_DESIGN_LABELS.get(ref_design, ref_design)}): relative depth error on the axis → the outer ring",
         f"{lin}; the exact model {_fmt(exact, 2)} mm",
         f"grows with the angle of incidence (paper's error analysis); exact ≤ {EXACT_TOL_MM:g} mm — "
         + _verdict_met(exact is not None and exact <= EXACT_TOL_MM),
         "`stereotactip bench accuracy`; `pytest tests/test_refraction.py`"),
        _latency_row(lat),
    ]

    def run(rec: Mapping[str, Any]) -> str:
        return (f"{rec['experiment']}: commit {str(rec.get('commit', 'unknown'))[:10]}, "
                f"{'quick' if rec.get('quick') else 'full'} run, seed {rec.get('seed')}")

    lines = [f"Pipeline figures from the `accuracy` and `latency` records in `{source}` ({run(acc)}; {run(lat)}); "
             "speed is this machine's (2 shared cores):", "",
             "| what | measured | paper / goal | reproduce |", "| --- | --- | --- | --- |"]
    lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows]
    return "\n".join(lines)


def renderer_accuracy_markdown(records: Records, source: str) -> str:
    """The renderer table: rendered centroids vs the exact projection, per-vertex vs ray-traced refraction."""
    acc = _need(records, "accuracy", "renderer-accuracy", source)
    tables = acc.get("tables") or {}
    cen = tables.get("render_centres") or []
    trace = tables.get("render_trace") or []
    cmax = _metric(acc, "render_centre_max_px")
    off, mass = _metric(acc, "render_trace_offset_max_px"), _metric(acc, "render_trace_mass_error_max")
    found = sum(r["found"] for r in cen)
    expected = sum(r["expected"] for r in cen)
    rows = [
        ("rendered marker centroids vs the true calibration + exact refraction (thin markers, rest and displaced, "
         "both views)", f"worst {_fmt(cmax, 2)} px, RMS ≤ {_fmt(max((r['rms_px'] for r in cen), default=None), 2)} px; "
         f"{found} blobs for {expected} markers inside the views",
         f"≤ {RENDER_CENTROID_TOL_PX:g} px — "
         + _verdict_met(cmax is not None and cmax <= RENDER_CENTROID_TOL_PX)),
        (f"per-vertex refraction vs a per-pixel ray-traced reference ({len(trace)} marker windows)",
         f"centroids within {_fmt(off, 2)} px, bright mass within {100 * mass:.1f} %",
         f"≤ {TRACE_CENTROID_TOL_PX:g} px, ≤ {100 * TRACE_AREA_TOL:g} % — "
         + _verdict_met(off is not None and off <= TRACE_CENTROID_TOL_PX and mass <= TRACE_AREA_TOL)),
    ]
    lines = [f"Renderer figures from the {_provenance(acc, source)}:", "",
             "| what | measured | goal | reproduce |", "| --- | --- | --- | --- |"]
    lines += [f"| {a} | {b} | {c} | `stereotactip bench accuracy`; `pytest tests/test_render.py` |" for a, b, c in rows]
    return "\n".join(lines)


def identification_summary_markdown(records: Records, source: str) -> str:
    """The certainty rule's headline: wrong ids over every trial and the worst pattern's coverage per condition of
    one ``bench identification`` record, against :data:`benchmarks.experiments.identification.COVERAGE_GOALS`."""
    from benchmarks.experiments.identification import COVERAGE_GOALS

    rec = records["identification"]
    rows = (rec.get("tables") or {}).get("conditions") or []
    if not rows:
        raise ResultsError(f"{source}: the identification record has no conditions table")
    wrong = sum(int(r["wrong_ids"]) for r in rows)
    trials = sum(int(r["trials"]) for r in rows)
    parts = []
    # beyond what the rule certifies for most patterns (a square turned 30° is still within its half symmetry angle
    # minus 7.5°): these conditions test that no id is wrong, and their coverage is shown as a range
    only_wrong = ("jitter_30", "rotation_30")
    for cond in [c for c in _CONDITION_LABELS if c not in ("defects_0", *only_wrong)]:
        cells = [r for r in rows if r["condition"] == cond]
        if not cells:
            continue
        worst = min(cells, key=lambda r: r["coverage_mean"])
        goal = COVERAGE_GOALS.get(cond)
        verdict = "" if goal is None else (f" (goal ≥ {100 * goal:g} %: "
                                           f"{_verdict_met(all(r['coverage_mean'] >= goal for r in cells))})")
        complete = _metric(rec, f"coverage_complete_neighbourhood_{cond}_min")
        within = "" if complete is None else f", {100 * complete:.2f} % of the markers keeping a complete neighbourhood"
        parts.append(f"{_CONDITION_LABELS[cond]} {100 * worst['coverage_mean']:.2f} % "
                     f"({_DESIGN_LABELS.get(worst['design'], worst['design'])}{within}){verdict}")
    hard = [r for r in rows if r["condition"] in only_wrong]
    if hard:
        spans = []
        for c in only_wrong:
            cov = [r["coverage_mean"] for r in hard if r["condition"] == c]
            if cov:
                spans.append(f"{_CONDITION_LABELS[c]} {100 * min(cov):.2f}–{100 * max(cov):.2f} %")
        parts.append(" and ".join(spans) + " across the patterns (beyond what the rule can certify, these test that no "
                     f"id is wrong: {sum(int(r['wrong_ids']) for r in hard)})")
    return (f"From the {_provenance(rec, source)}: **{wrong} wrong ids** in {trials:,} seeded trials "
            f"(goal: zero — {_verdict_met(wrong == 0)}). Coverage, the worst pattern's mean over trials: "
            + "; ".join(parts) + ".")
