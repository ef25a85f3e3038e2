"""The README's figures, written from benchmark records (``stereotactip report DIR --readme README.md``).

A generated block in the README is the text between two marker lines::

    <!-- report:NAME:begin (written by `stereotactip report DIR --readme README.md --block NAME`; do not edit) -->
    ...
    <!-- report:NAME:end -->

and :data:`BLOCKS` names what each block is made of: the gate figures of a quick run (``gate-figures``, every
metric ``benchmarks/thresholds.toml`` guards), the quick run's experiments (``quick-experiments``, one row per
experiment: the paper's figures and claims beside the run's), the twin's speed and fidelity table
(``twin-speed``, from a ``bench twin`` record), the identification coverage table (``identification-coverage``,
from a ``bench identification`` record), the tracking table (``tracking-identity``, from a ``bench tracking``
record), an oracle and an estimated quick run side by side (``oracle-vs-estimated``, ``report DIR --against
DIR2``) and each error source of the estimated calibration alone (``error-sources``, three ``bench
patterns,gaussian --quick --calibration estimated --error-sources SOURCE`` runs: ``report DIR --against DIR2
--against DIR3``). Each block's first line names the results directories it was written from;
the records behind the README's headline blocks are kept in ``docs/records/`` so that
``tests/test_benchmarks.py`` can write each block again and fail when the README has drifted from them.

Over ~400 lines on purpose: one renderer per block, each holding the README's wording next to the record
fields it reads, all sharing the marker, provenance and number helpers above them and registered in one
table; a reader looking for where a README figure comes from finds every block here.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from benchmarks.report import (_fmt, _md_escape, _verdict, calibration_mode, comparison_table, designs_used,
                               invalid_cells, paper_figures)
from benchmarks.results import ResultsError, load_records
from benchmarks.thresholds import bounds_text, check, load_thresholds

__all__ = ["BLOCKS", "CALIBRATION_METRICS", "ReadmeBlock", "begin_marker", "end_marker", "render_block", "update_readme",
           "readme_blocks", "gate_figures_markdown", "README_BEGIN", "README_END"]

Records = Mapping[str, Mapping[str, Any]]


@dataclass(frozen=True)
class ReadmeBlock:
    """One generated README block: its ``name`` (the marker's), the ``experiment`` whose record it needs (None:
    every quick record in the directory) and ``body(records, source) -> str`` the Markdown between the markers.
    A block that compares runs (``against`` > 0: how many other runs besides DIR) is written by
    ``body(records, source, others)``, ``others`` the list of (directory, records) from ``report DIR --against
    DIR2 [--against DIR3]``."""

    name: str
    experiment: str | None
    body: Callable[..., str]
    about: str
    against: int = 0


def begin_marker(name: str) -> str:
    """The line that opens block ``name`` (the gate figures keep their original, shorter command)."""
    against = "".join(f" --against DIR{k + 2}" for k in range(BLOCKS[name].against if name in BLOCKS else 0))
    command = (f"stereotactip report DIR{against} --readme README.md"
               + ("" if name == "gate-figures" else f" --block {name}"))
    return f"<!-- report:{name}:begin (written by `{command}`; do not edit) -->"


def end_marker(name: str) -> str:
    return f"<!-- report:{name}:end -->"




def _value(rec: Mapping[str, Any], metric: str, digits: int = 3) -> str:
    m = (rec.get("metrics") or {}).get(metric) or {}
    unit = m.get("unit", "")
    return f"{_fmt(m.get('value'), digits)} {unit if unit != '1' else ''}".strip()


def _provenance(rec: Mapping[str, Any], source: str) -> str:
    """Where a block's figures come from: directory, commit, quick or full, calibration mode and seed."""
    mode = (rec.get("calibration") or {}).get("mode", "oracle")
    return (f"`{rec['experiment']}` record in `{source}` (commit {str(rec.get('commit', 'unknown'))[:10]}, "
            f"{'quick' if rec.get('quick') else 'full'} run, calibration {mode}, seed {rec.get('seed')})")


# ----- gate-figures: every metric the CI gate guards ---------------------------------------------

def gate_figures_markdown(records: Records, source: str) -> str:
    """The quick gate's figures as a Markdown table: every metric ``benchmarks/thresholds.toml`` guards, the
    value the records in ``source`` give it, its golden and sanity bounds and whether it passes."""
    thresholds = load_thresholds()
    recs = {n: r for n, r in sorted(records.items()) if r.get("quick")}
    if not recs:
        raise ResultsError(f"{source}: no quick records: the gate figures come from a --quick run")
    commits = sorted({str(r.get("commit", "unknown"))[:10] for r in recs.values()})
    modes = sorted({(r.get("calibration") or {}).get("mode", "oracle") for r in recs.values()})
    violations = {(v.experiment, v.metric) for v in check(recs, thresholds, experiments=list(recs))}
    lines = [f"Quick gate figures from `{source}` (commit {', '.join(commits)}, calibration "
             f"{', '.join(modes)}, seed {', '.join(sorted({str(r.get('seed')) for r in recs.values()}))}):", "",
             "| experiment | metric | this run | golden | sanity | kind | gate |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for exp, table in thresholds.items():
        rec = recs.get(exp)
        if rec is None:
            continue
        mode = (rec.get("calibration") or {}).get("mode", "oracle")
        for th in table.values():
            if th.mode is not None and th.mode != mode:
                continue
            m = rec.get("metrics", {}).get(th.metric) or {}
            unit = m.get("unit", "")
            shown = th.metric if th.mode is None else f"{th.metric} ({th.mode})"
            value = f"{_fmt(m.get('value'))} {unit if unit != '1' else ''}".strip()
            golden = bounds_text(th.golden_min, th.golden_max, table=True)
            sanity = bounds_text(th.min, th.max, table=True)
            ok = "**fails**" if (exp, shown) in violations else "passes"
            lines.append(f"| {exp} | {shown} | {value} | {golden} | {sanity} | {th.kind or '—'} | {ok} |")
    return "\n".join(lines)


# ----- quick-experiments: one row per experiment of a quick run --------------------------------------

def _quick_experiments(records: Records, source: str) -> str:
    """One row per experiment of a quick run: its designs, the twin cells that failed the physics checks, and
    the paper's figures and claims (or the twin's goals) beside this run's, with the verdict: the same
    facts as the report's summary and "Paper figure vs this run" tables, taken from the same helpers."""
    recs = {n: r for n, r in sorted(records.items()) if r.get("quick")}
    if not recs:
        raise ResultsError(f"{source}: no quick records: the experiments table comes from a --quick run")
    commits = sorted({str(r.get("commit", "unknown"))[:10] for r in recs.values()})
    modes = sorted({(r.get("calibration") or {}).get("mode", "oracle") for r in recs.values()})
    seeds = sorted({str(r.get("seed")) for r in recs.values()})
    lines = [f"Quick-run records in `{source}` (commit {', '.join(commits)}, calibration {', '.join(modes)}, "
             f"seed {', '.join(seeds)}); each claim is the paper's (or, for `twin`, the twin's goal), each "
             "figure the experiment's own record:", "",
             "| experiment | designs | invalid twin cells | paper / goal | this run | verdict |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, r in recs.items():
        paper, run, verdict = [], [], []
        for metric, value, measured, unit, where in paper_figures(r):
            unit = "" if unit == "1" else f" {unit}"
            paper.append(f"{metric} {value}{unit} ({where})")
            run.append(f"{metric} {measured}{unit}")
            verdict.append("—")
        for f in r.get("findings", []):
            paper.append(f["claim"])
            run.append(f["observed"])
            verdict.append(_verdict(f["agrees"]))
        if r.get("status") != "ok":
            run.append(f"status {r.get('status')}")
        cells = ["<br>".join(_md_escape(x) for x in col) or "—" for col in (paper, run, verdict)]
        lines.append(f"| {name} | {_md_escape(designs_used(r))} | {invalid_cells(r)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ----- oracle-vs-estimated: the accuracy a user gets ------------------------------------------------

# The figures that show what a user's calibration costs: the markers at rest (patterns), the pressed skin
# (gaussian), the fitted index and depth (refraction), and the experiments that reconstruct through the twin.
CALIBRATION_METRICS: dict[str, tuple[str, ...]] = {
    "patterns": ("localisation_rms_mm_circular", "localisation_rms_mm_hexagon", "localisation_rms_mm_square",
                 "localisation_max_mm", "identity_correct_fraction_min"),
    "gaussian": ("rms_vs_true_skin_mm", "rms_vs_cad_mm", "centre_error_mm_skin050", "centre_error_mm_skin150",
                 "matched_fraction_min"),
    "refraction": ("n_fit", "exact_depth_error_rms_mm", "exact_absolute_error_rms_mm", "linear_depth_error_rms_mm"),
    "tracking": ("dtrc_correct_rate_min", "dtrc_wrong_ids", "nn_correct_rate_min", "nn_wrong_ids"),
    "sine": ("valid_cells", "upper_rms_mm", "lowest_point_rms_mm", "wrong_ids"),
    "terrain": ("rms_err_mm_mean_all", "rms_err_reachable_mm_mean_all", "resolved_fraction_all"),
}


def _oracle_vs_estimated(records: Records, source: str, others: list[tuple[str, Records]]) -> str:
    """The :data:`CALIBRATION_METRICS` of two quick runs side by side (``report DIR --against DIR2``, the report's
    own comparison table): typically DIR run with ``--calibration oracle`` and DIR2 with ``estimated``."""
    [(against_source, against)] = others
    def run(recs: Records, where: str) -> tuple[str, str]:
        chosen = [r for n, r in sorted(recs.items()) if n in CALIBRATION_METRICS]
        if not chosen:
            raise ResultsError(f"{where}: none of the records {', '.join(CALIBRATION_METRICS)}")
        modes = sorted({calibration_mode(r) for r in chosen})
        commits = sorted({str(r.get("commit", "unknown"))[:10] for r in chosen})
        seeds = sorted({str(r.get("seed")) for r in chosen})
        quick = {bool(r.get("quick")) for r in chosen}
        kind = "quick" if quick == {True} else "full" if quick == {False} else "quick and full"
        return " / ".join(modes), (f"{' / '.join(modes)} records in `{where}` (commit {', '.join(commits)}, "
                                   f"{kind}, seed {', '.join(seeds)})")

    mode_a, about_a = run(records, source)
    mode_b, about_b = run(against, against_source)
    table = comparison_table(records, against, CALIBRATION_METRICS, columns=(mode_a, mode_b))
    if not table:
        raise ResultsError(f"{source} and {against_source}: no experiment of {', '.join(CALIBRATION_METRICS)} "
                           "ran in both")
    return "\n".join([f"The {about_a} beside the {about_b}:", ""] + table)


# ----- error-sources: each error source of the estimated calibration alone ------------------------

_ABLATED = ("patterns", "gaussian")     # the experiments an ablation run holds


def _fixed(value: Any, unit: str = "", signed: bool = False, digits: int = 3) -> str:
    """A figure at the block's fixed resolution (3 decimals: µm for mm), "—" when absent or not finite."""
    if not isinstance(value, (int, float)) or not math.isfinite(value):
        return "—"
    text = f"{value:{'+' if signed else ''}.{digits}f}".replace("-", "−")
    return text + ("" if not unit else unit if unit == "°" else f" {unit}")


def _metric(rec: Mapping[str, Any], name: str) -> Any:
    return ((rec.get("metrics") or {}).get(name) or {}).get("value")


def _run_sources(recs: Records, where: str) -> tuple[str, ...]:
    """The error sources an estimated run kept (the same for every setup of its records)."""
    from benchmarks.estimated import SOURCES

    found = set()
    for name, r in recs.items():
        cal = r.get("calibration") or {}
        if cal.get("mode") != "estimated":
            raise ResultsError(f"{where}: the {name} record ran with calibration {cal.get('mode', 'oracle')}: the "
                               "error-sources block is written from --calibration estimated runs")
        found |= {tuple(s.get("sources") or ()) for s in cal.get("setups") or ()}
    if len(found) != 1:
        raise ResultsError(f"{where}: the records keep different error sources ({found or 'none recorded'})")
    (kept,) = found
    return tuple(s for s in SOURCES if s in kept)


def _build_setups(recs: Records) -> list[tuple[str, str, Mapping[str, Any]]]:
    """(experiment, design, calibration setup) of a run's patterns and gaussian records, design by design."""
    out = []
    for e in _ABLATED:
        designs = recs[e].get("designs_used") or []
        setups = (recs[e].get("calibration") or {}).get("setups") or []
        if len(designs) != len(setups):
            raise ResultsError(f"{e} record: {len(setups)} calibration setups for {len(designs)} designs")
        out += [(e, d, st) for d, st in zip(designs, setups)]
    return out



def _error_sources(records: Records, source: str, others: list[tuple[str, Records]]) -> str:
    """The ``patterns`` and ``gaussian`` figures of estimated quick runs that each keep some of the error sources
    (``bench patterns,gaussian --quick --calibration estimated --error-sources SOURCE``), one column per run in
    the order given, and the builds behind them: each design's drawn stack, chessboard calibration and
    press-fitted index, each taken from the run that kept that source."""
    from fractions import Fraction

    from benchmarks.estimated import SOURCES

    runs = []
    for where, recs in [(source, records), *others]:
        missing = [e for e in _ABLATED if e not in recs]
        if missing:
            raise ResultsError(f"{where}: no {', '.join(missing)} record: the error-sources block is written from "
                               "`stereotactip bench patterns,gaussian --quick --calibration estimated "
                               "--error-sources SOURCE` runs")
        bad = [e for e in _ABLATED if recs[e].get("status") != "ok"]
        if bad:
            raise ResultsError(f"{where}: the {', '.join(bad)} record did not run to the end (status "
                               f"{recs[bad[0]].get('status')})")
        kept = _run_sources({e: recs[e] for e in _ABLATED}, where)
        runs.append((where, recs, kept, "all sources" if kept == SOURCES else " + ".join(kept) + " only"))

    def facts(recs: Records, key: str) -> str:
        return ", ".join(sorted({str(recs[e].get(key, "unknown"))[:10] for e in _ABLATED}))

    about = "; ".join(f"{label}: records in `{where}` (commit {facts(recs, 'commit')}, "
                      f"{'quick' if all(recs[e].get('quick') for e in _ABLATED) else '**not quick**'}, "
                      f"seed {facts(recs, 'seed')})" for where, recs, _, label in runs)

    def row(what: str, cell: Callable[[Mapping[str, Any], Mapping[str, Any]], str]) -> str:
        return f"| {what} | " + " | ".join(cell(recs["patterns"], recs["gaussian"]) for _, recs, _, _ in runs) + " |"

    def ids(p: Mapping[str, Any]) -> str:
        correct = _metric(p, "identity_correct_fraction_min")
        return "all" if correct == 1 else f"{_fixed(100 * correct if correct is not None else None, '%', digits=1)}"

    first = runs[0][1]
    lines = ["Estimated-calibration quick runs of `patterns` and `gaussian`, one column per run by the error "
             f"sources it kept (a source left out takes the twin's exact value) — {about}:", "",
             "| metric (quick) | " + " | ".join(label for *_, label in runs) + " |",
             "| --- | " + " | ".join("---" for _ in runs) + " |"]
    for k, r in enumerate((first["patterns"].get("tables") or {}).get("per_pattern") or []):
        what = ("patterns: 3-D localisation RMS at rest, " if k == 0 else "patterns: ") + f"{r['design']} (mm)"
        lines.append(row(what, lambda p, g, kind=r["kind"]: _fixed(_metric(p, f"localisation_rms_mm_{kind}"))))
    lines.append(row("patterns: max error (mm); ids correct",
                     lambda p, g: f"{_fixed(_metric(p, 'localisation_max_mm'))}; {ids(p)}"))
    lines.append(row("gaussian: reconstruction vs twin skin RMS (mm)",
                     lambda p, g: _fixed(_metric(g, "rms_vs_true_skin_mm"))))
    lines.append(row("gaussian: vs CAD RMS, physically valid cells (mm)",
                     lambda p, g: _fixed(_metric(g, "rms_vs_cad_mm"))))
    skins = sorted((int(m.group(1)) / 100, m.group(0)) for m in
                   (re.fullmatch(r"centre_error_mm_skin(\d{3})", n) for n in first["gaussian"].get("metrics") or {})
                   if m)
    if skins:
        cells = (first["gaussian"].get("tables") or {}).get("cells") or []
        sharpest = Fraction(min(c["sigma2_mm2"] for c in cells)).limit_denominator(12) if cells else None
        tip = "the sharpest σ²" if sharpest is None else f"σ² = {sharpest}"
        lines.append(row(f"gaussian: tip error {tip}, skin {' / '.join(f'{t:g}' for t, _ in skins)} mm (mm)",
                         lambda p, g: " / ".join(_fixed(_metric(g, name)) for _, name in skins)))
    lines.append(row("gaussian: matched fraction min", lambda p, g: _fixed(_metric(g, "matched_fraction_min"))))
    lines.append(row("gaussian: physically invalid twin cells", lambda p, g: invalid_cells(g)))

    # the builds: every run draws the same stack and chessboard poses (seeded by design and seed); each column
    # comes from the first run that kept its source (a run without it records zeros or the exact route)
    by_source = {s: _build_setups(recs) for s in SOURCES for _, recs, kept, _ in reversed(runs) if s in kept}
    seeds = ", ".join(sorted({str(recs[e].get("seed")) for _, recs, _, _ in runs for e in _ABLATED}))
    lines += ["", f"The builds behind them (seed {seeds}; each run draws the same stack and chessboard poses for a "
              "design, each column is taken from the run that kept its source; the index is fitted from a "
              "skin-less board press through that run's cameras and stack):", "",
              "| build | gel thickness | acrylic thickness | gel index built → press-fit | chessboard RMS | "
              "baseline error | focal error max | rotation error |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for k, (e, d, _) in enumerate(_build_setups(first)):
        def setup(src: str) -> Mapping[str, Any]:
            rows = by_source.get(src) or []
            return rows[k][2] if k < len(rows) and rows[k][:2] == (e, d) else {}

        drawn = setup("thickness").get("drawn") or {}
        fit = (setup("index").get("index") or {}).get("n")
        built = (setup("index").get("true_stack") or {}).get("gel_n")
        index = "—" if fit is None or built is None else \
            f"{_fixed(built, digits=4)} → {_fixed(fit, digits=4)} ({_fixed(fit - built, signed=True, digits=4)})"
        cal = setup("calibration").get("calibration") or {}
        lines.append(f"| {e}: {d} | {_fixed(drawn.get('gel_thickness_mm'), 'mm', signed=True)} | "
                     f"{_fixed(drawn.get('acrylic_thickness_mm'), 'mm', signed=True)} | {index} | "
                     f"{_fixed(cal.get('rms_px'), 'px')} | {_fixed(cal.get('baseline_error_mm'), 'mm', signed=True)} | "
                     f"{_fixed(cal.get('focal_error_max_px'), 'px', digits=2)} | "
                     f"{_fixed(cal.get('rotation_error_deg'), '°')} |")
    return "\n".join(lines)


# ----- twin-speed: the twin's headline figures ----------------------------------------------------

def _twin_speed(records: Records, source: str) -> str:
    """Seconds per press, ms per frame, gap and penetration of one ``bench twin`` record against the goals
    :data:`benchmarks.twin_bench.GOALS` (the one place they are set)."""
    from benchmarks.twin_bench import GOALS

    rec = records["twin"]
    metric = lambda name: ((rec.get("metrics") or {}).get(name) or {}).get("value")    # noqa: E731

    def verdict(*pairs: tuple[str, str]) -> str:
        met = [metric(m) is not None and metric(m) <= GOALS[g] for m, g in pairs]
        return "met" if all(met) else "**not met**"

    dofs = metric("mesh_dofs")
    mu = metric("friction")
    pen_goal = f"≤ {GOALS['penetration_max_mm']:g} mm"
    rows = [
        (f"5 mm press to equilibrium on σ² = 10 mm² (default design, {_fmt(dofs)} dofs, μ = {_fmt(mu)}: the path "
         "followed to the captured pose)",
         f"{_value(rec, 'press_s_median')} median",
         f"≤ {GOALS['press_s']:g} s — {verdict(('press_s_median', 'press_s'))}"),
        ("the same press frictionless: the captured pose solved directly / the followed path",
         f"{_value(rec, 'frictionless_direct_press_s')} / {_value(rec, 'followed_press_s')}; markers within "
         f"{_value(rec, 'direct_vs_followed_marker_max_mm')} of each other", "(comparison)"),
        ("rendered stereo frame (flat shading, 640×480 × 2)", f"{_value(rec, 'frame_ms_median')} median",
         f"≤ {GOALS['frame_ms']:g} ms — {verdict(('frame_ms_median', 'frame_ms'))}"),
        ("skin–indenter gap on σ² = 10 mm² (contacting vertices)",
         f"{_value(rec, 'gap_max_mm')} max, {_value(rec, 'gap_rms_mm')} RMS",
         f"≤ {GOALS['gap_max_mm']:g} mm — {verdict(('gap_max_mm', 'gap_max_mm'))}"),
        ("default mesh (1.5 mm, vertex contact): outer skin inside the indenter, face level, σ² = 10 / 5/3",
         f"{_value(rec, 'penetration_max_mm')} (vertices {_value(rec, 'penetration_vertex_max_mm')}) / "
         f"{_value(rec, 'sharp_penetration_max_mm')}; {_value(rec, 'press_s_median')} / {_value(rec, 'sharp_press_s')}",
         f"{pen_goal} — {verdict(('penetration_max_mm', 'penetration_max_mm'), ('sharp_penetration_max_mm', 'penetration_max_mm'))}"),
        ("the same mesh with face contact, σ² = 10 / 5/3",
         f"{_value(rec, 'face_contact_penetration_max_mm')} / {_value(rec, 'face_contact_sharp_penetration_max_mm')} "
         f"inside; apex {_value(rec, 'face_contact_apex_beyond_tip_mm')} beyond the σ² = 10 tip; "
         f"{_value(rec, 'face_contact_press_s')} / {_value(rec, 'face_contact_sharp_press_s')}",
         f"{pen_goal} — {verdict(('face_contact_penetration_max_mm', 'penetration_max_mm'), ('face_contact_sharp_penetration_max_mm', 'penetration_max_mm'))}; "
         f"≤ {GOALS['face_contact_press_s']:g} / {GOALS['face_contact_sharp_press_s']:g} s — "
         f"{verdict(('face_contact_press_s', 'face_contact_press_s'), ('face_contact_sharp_press_s', 'face_contact_sharp_press_s'))}"),
        ("the axis contact mesh (0.5 mm core, mirrored split, face contact), σ² = 10 / 5/3",
         f"{_value(rec, 'axis_mesh_penetration_max_mm')} / {_value(rec, 'axis_mesh_sharp_penetration_max_mm')} "
         f"inside; apex {_value(rec, 'axis_mesh_apex_beyond_tip_mm')} beyond the σ² = 10 tip; "
         f"{_value(rec, 'axis_mesh_press_s')} / {_value(rec, 'axis_mesh_sharp_press_s')}",
         f"{pen_goal} — {verdict(('axis_mesh_penetration_max_mm', 'penetration_max_mm'), ('axis_mesh_sharp_penetration_max_mm', 'penetration_max_mm'))}; "
         f"≤ {GOALS['axis_mesh_press_s']:g} / {GOALS['axis_mesh_sharp_press_s']:g} s — "
         f"{verdict(('axis_mesh_press_s', 'axis_mesh_press_s'), ('axis_mesh_sharp_press_s', 'axis_mesh_sharp_press_s'))}"),
    ]
    lines = [f"Twin figures from the {_provenance(rec, source)}; speed is this machine's (2 shared cores):", "",
             "| what | measured | goal |", "| --- | --- | --- |"]
    lines += [f"| {what} | {measured} | {goal} |" for what, measured, goal in rows]
    return "\n".join(lines)


# ----- identification-coverage: coverage per condition and pattern --------------------------------

# The README's words for the benchmark's conditions (benchmarks.experiments.identification.CONDITIONS).
_CONDITION_LABELS = {
    "defects_0": "clean", "defects_1": "1 % missing + 1 % spurious", "defects_3": "3 % + 3 %",
    "defects_5": "5 % + 5 %", "defects_10": "10 % + 10 %", "occlusion_15": "contiguous 15 % patch occluded",
    "jitter_30": "centre jitter 0.3 separations", "rotation_30": "turned ±30°",
    "press_stereo": "Gaussian press 1–5 mm, stereo, 3 % + 3 % per view",
}
_DESIGN_LABELS = {"hexagon61_sep354": "hex 61", "hexagon127": "hex 127", "hexagon217_sep180": "hex 217",
                  "square121": "sq 121", "circular217_dome": "circ 217"}


def _identification_coverage(records: Records, source: str) -> str:
    """Wrong ids and mean coverage per condition (rows) and pattern (columns) of one ``bench identification``
    record's ``conditions`` table."""
    rec = records["identification"]
    rows = (rec.get("tables") or {}).get("conditions") or []
    if not rows:
        raise ResultsError(f"{source}: the identification record has no conditions table")
    designs = list(dict.fromkeys(r["design"] for r in rows))
    conditions = [c for c in _CONDITION_LABELS if any(r["condition"] == c for r in rows)]
    conditions += [c for c in dict.fromkeys(r["condition"] for r in rows) if c not in conditions]
    cell = {(r["condition"], r["design"]): r for r in rows}
    trials = sorted({int(r["trials"]) for r in rows})
    lines = [f"Identification from the {_provenance(rec, source)}: {', '.join(map(str, trials))} seeded trials per "
             f"condition and pattern, {sum(int(r['trials']) for r in rows):,} in all; coverage = present markers "
             "given their correct id, mean over trials:", "",
             "| condition | wrong ids | " + " | ".join(_DESIGN_LABELS.get(d, d) for d in designs) + " |",
             "| --- | --- | " + " | ".join("---" for _ in designs) + " |"]
    for c in conditions:
        cov = [f"{100 * cell[c, d]['coverage_mean']:.2f} %" if (c, d) in cell else "—" for d in designs]
        wrong = sum(int(cell[c, d]["wrong_ids"]) for d in designs if (c, d) in cell)
        lines.append(f"| {_CONDITION_LABELS.get(c, c)} | {wrong} | " + " | ".join(cov) + " |")
    return "\n".join(lines)


_LETTER_MOTIONS = {"G": "rest; pressed 1, 2, 3 mm", "e": "rest; 3 mm, then slid 1 and 2 mm",
                   "o": "rest; touch, then a rapid 2 mm + 2 mm diagonal"}


def _tracking_identity(records: Records, source: str) -> str:
    """Per letter of one ``bench tracking`` record: DTRC's and nearest neighbour's correct-id rates and wrong ids,
    the largest lateral marker step between frames, and the frames that failed the twin's physics checks."""
    rec = records["tracking"]
    rows = (rec.get("tables") or {}).get("per_frame") or []
    if not rows:
        raise ResultsError(f"{source}: the tracking record has no per_frame table")
    letters = list(dict.fromkeys(r["letter"] for r in rows))
    mu = ((rec.get("metrics") or {}).get("friction") or {}).get("value")
    lines = [f"Tracking from the {_provenance(rec, source)}; skin/letter friction μ = {_fmt(mu)}; a frame's id is "
             "correct when the nearest true marker has it within half a separation:", "",
             "| letter | motion | frames (invalid) | DTRC correct rate, wrong ids | nearest neighbour correct rate, "
             "wrong ids | largest lateral marker step |", "| --- | --- | --- | --- | --- | --- |"]
    def rate(rs) -> str:      # one tracker's frames of one letter: worst correct rate, wrong ids in all
        return (f"{_fmt(min(r['correct_rate'] for r in rs))} (worst frame), {sum(int(r['wrong']) for r in rs)}"
                if rs else "—")

    for ch in letters:
        dtrc, nn = ([r for r in rows if r["letter"] == ch and r["tracker"] == t] for t in ("dtrc", "nn"))
        invalid = sum(1 for r in dtrc if not r.get("physics_valid", True))
        lines.append(f"| {ch} | {_LETTER_MOTIONS.get(ch, '')} | {len(dtrc)} ({invalid}) | {rate(dtrc)} | "
                     f"{rate(nn)} | {_value(rec, f'max_lateral_step_mm_{ch}')} |")
    return "\n".join(lines)


BLOCKS: dict[str, ReadmeBlock] = {b.name: b for b in (
    ReadmeBlock("gate-figures", None, gate_figures_markdown, "every metric the CI gate guards, from a quick run"),
    ReadmeBlock("quick-experiments", None, _quick_experiments,
                "one row per experiment of a quick run: the paper's figures and claims beside this run's"),
    ReadmeBlock("oracle-vs-estimated", None, _oracle_vs_estimated,
                "the calibration-sensitive figures of an oracle and an estimated quick run side by side",
                against=1),
    ReadmeBlock("error-sources", None, _error_sources,
                "patterns and gaussian figures of estimated quick runs that each keep one error source, with "
                "each run's drawn build, chessboard calibration and press-fitted index",
                against=2),
    ReadmeBlock("twin-speed", "twin", _twin_speed, "the twin's press and frame times, gap and penetration"),
    ReadmeBlock("identification-coverage", "identification", _identification_coverage,
                "wrong ids and coverage per defect condition and pattern"),
    ReadmeBlock("tracking-identity", "tracking", _tracking_identity,
                "DTRC vs nearest-neighbour ids per letter motion, with the frames' physics verdicts"),
)}


README_BEGIN = begin_marker("gate-figures")
README_END = end_marker("gate-figures")


def render_block(name: str, records: Records, source: str,
                 against: Sequence[tuple[str, Records]] = ()) -> str:
    """Block ``name`` written from ``records`` (the results directory ``source``; for a block that compares
    runs, also ``against``, the (directory, records) of each other run), marker lines included."""
    block = BLOCKS.get(name)
    if block is None:
        raise ResultsError(f"README block {name!r}: unknown; known blocks: {', '.join(BLOCKS)}")
    if block.experiment is not None and block.experiment not in records:
        raise ResultsError(f"{source}: no {block.experiment!r} record: the {name} block is written from a "
                           f"`stereotactip bench {block.experiment}` results directory")
    if len(against) != block.against:
        command = begin_marker(name).split("`")[1]
        runs = f"compares {('two', 'three')[block.against - 1]} runs" if block.against else "is written from one run"
        raise ResultsError(f"README block {name}: {runs}: `{command}`")
    body = block.body(records, source, list(against)) if block.against else block.body(records, source)
    return "\n".join([begin_marker(name), "", body, "", end_marker(name)])


_BEGIN = re.compile(r"^<!-- report:([a-z0-9-]+):begin\b.*-->$", re.M)


def readme_blocks(text: str) -> dict[str, str]:
    """The generated blocks of a README's text, by name, marker lines included (as :func:`render_block`
    writes them)."""
    out = {}
    for m in _BEGIN.finditer(text):
        end = text.find(end_marker(m.group(1)), m.end())
        if end >= 0:
            out[m.group(1)] = text[m.start():end + len(end_marker(m.group(1)))]
    return out


def update_readme(readme: Path, records_dir: Path, blocks: tuple[str, ...] = ("gate-figures",),
                  against_dir: Path | Sequence[Path] | None = None) -> Path:
    """Rewrite the named ``blocks`` of ``readme`` from the records in ``records_dir`` (and, for a block that
    compares runs, the other runs' directories ``against_dir``) atomically; everything else is kept. Each block
    must stand exactly once, its begin line before its end line."""
    from pipeline.io.atomic import atomic_write_text

    readme = Path(readme)
    try:
        text = readme.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ResultsError(f"README {readme}: unreadable ({type(exc).__name__})") from None
    records = load_records(Path(records_dir))
    against_dirs = [] if against_dir is None else [against_dir] if isinstance(against_dir, (str, Path)) \
        else list(against_dir)
    against = [(str(d), load_records(Path(d))) for d in against_dirs]
    for name in blocks:
        begin, end = begin_marker(name), end_marker(name)
        if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
            raise ResultsError(f"README {readme}: needs exactly one {name} block, the line {begin!r} "
                               f"followed by {end!r}")
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        others = against if name in BLOCKS and BLOCKS[name].against else ()
        text = head + render_block(name, records, str(records_dir), others) + tail
    atomic_write_text(readme, text)
    return readme
