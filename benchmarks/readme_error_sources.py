"""The README's ``error-sources`` block: the ``patterns`` and ``gaussian`` figures of estimated quick runs that
each keep some of the calibration's error sources, one column per run, and the builds behind them (drawn stack,
chessboard calibration and press-fitted index). Registered in :data:`benchmarks.readme_blocks.BLOCKS`.
"""

from __future__ import annotations

import math
import re
from typing import Any, Callable, Mapping

from benchmarks.readme_render import Records
from benchmarks.report import invalid_cells
from benchmarks.results import ResultsError

__all__ = ["error_sources_markdown"]

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


def error_sources_markdown(records: Records, source: str, others: list[tuple[str, Records]]) -> str:
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
