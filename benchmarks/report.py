"""``stereotactip report DIR``: one Markdown page over the JSON records and figures in DIR.

The page holds a run summary, the table "paper figure vs this run" (each experiment's declared
paper values next to the measured metric, then the paper's qualitative claims with this run's
verdict), the threshold gate for quick runs, and one section per experiment with its metrics,
notes, findings and figures; sweep tables found in DIR are appended. The README's generated blocks
(``--readme``) are written by :mod:`benchmarks.readme_blocks`.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

from benchmarks.results import ResultsError, load_records
from benchmarks.thresholds import check, load_thresholds

__all__ = ["write_report", "render_report", "calibration_comparison", "calibration_mode", "comparison_table", "invalid_cells", "designs_used",
           "paper_figures"]


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        if not math.isfinite(value):
            return "—"
        return f"{value:.{digits}g}"
    return str(value)


def _verdict(agrees: bool | None) -> str:
    return {True: "agrees", False: "**disagrees**", None: "undecided"}[agrees]


def _md_escape(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def invalid_cells(rec: Mapping[str, Any]) -> str:
    """How many of a record's twin cells failed the twin's physics checks, "N of M" (bold when any did), or "—"
    for an experiment that does not count them."""
    inv, val = ((rec.get("metrics") or {}).get(k, {}).get("value") for k in ("invalid_cells", "valid_cells"))
    if inv is None:
        return "—"
    if val is not None and inv:
        return f"**{inv:g}** of {inv + val:g}"
    return f"{inv:g}" + (f" of {inv + val:g}" if val is not None else "")


def designs_used(rec: Mapping[str, Any]) -> str:
    """The sensor designs a record's cells ran on, comma-separated."""
    return ", ".join(rec.get("designs_used") or [rec["design"].get("name", "?")])


def paper_figures(rec: Mapping[str, Any]) -> list[tuple[str, str, str, str, str]]:
    """A record's declared paper figures next to its measurement: (metric, paper value, this run's value, unit,
    where in the paper), values formatted."""
    out = []
    for metric, p in (rec.get("paper") or {}).items():
        m = (rec.get("metrics") or {}).get(metric)
        out.append((metric, _fmt(p["value"]), _fmt(m["value"] if m else None), p["unit"], p["text"]))
    return out


def calibration_mode(rec: Mapping[str, Any]) -> str:
    """The calibration a record's pipeline was given: "oracle" (the twin's exact sensor) or "estimated"."""
    return (rec.get("calibration") or {}).get("mode", "oracle")


def comparison_table(records: Mapping[str, Mapping[str, Any]], against: Mapping[str, Mapping[str, Any]],
                     metrics: Mapping[str, tuple[str, ...]] | None = None,
                     columns: tuple[str, str] = ("this run", "other run")) -> list[str]:
    """Markdown table lines: the metrics of the experiments that ran (status ok) in both ``records`` and
    ``against``, side by side under each record's calibration mode, with the difference (other − this); empty
    when no experiment ran in both. ``metrics`` keeps only these experiments and metrics, in its order."""
    names = list(metrics) if metrics is not None else sorted(records)
    common = [n for n in names if n in records and n in against and records[n].get("status") == "ok"
              and against[n].get("status") == "ok"]
    if not common:
        return []
    lines = [f"| experiment | metric | {columns[0]} | {columns[1]} | {columns[1].split()[0]} − {columns[0].split()[0]} "
             "| unit |", "| --- | --- | --- | --- | --- | --- |"]
    for name in common:
        a, b = records[name], against[name]
        label_a = f"{calibration_mode(a)}{' quick' if a.get('quick') else ''}"
        label_b = f"{calibration_mode(b)}{' quick' if b.get('quick') else ''}"
        rows = []
        for metric in (metrics[name] if metrics is not None else a.get("metrics", {})):
            ma, mb = a.get("metrics", {}).get(metric), b.get("metrics", {}).get(metric)
            if ma is None or mb is None:
                continue
            va, vb = ma.get("value"), mb.get("value")
            diff = (vb - va) if isinstance(va, (int, float)) and isinstance(vb, (int, float)) else None
            rows.append(f"| {name} | {metric} | {_fmt(va)} | {_fmt(vb)} | {_fmt(diff, 3)} | {ma.get('unit', '')} |")
        if rows or metrics is None:         # a chosen experiment without any chosen metric in both is left out
            lines += [f"| **{name}** | | {label_a} | {label_b} | | |"] + rows
    return lines


def calibration_comparison(records: Mapping[str, Mapping[str, Any]], against: Mapping[str, Mapping[str, Any]],
                           against_name: str) -> list[str]:
    """Markdown lines: every metric of the experiments that both ``records`` and ``against`` hold, side by side
    under each record's calibration mode (e.g. oracle | estimated), with the difference."""
    lines = ["## Side by side: this run and " + _md_escape(against_name), "",
             "Each experiment's metrics in this directory and in the other one, under the calibration mode each "
             "was run with (`--calibration oracle`: the twin's exact sensor; `estimated`: what a user has).", ""]
    table = comparison_table(records, against)
    return lines + (table or ["No experiment ran in both directories."]) + [""]


def render_report(records: Mapping[str, Mapping[str, Any]], out_dir: Path,
                  against: Sequence[tuple[str, Mapping[str, Mapping[str, Any]]]] = ()) -> str:
    """The Markdown text of the report (figure links relative to ``out_dir``); each (name, records) of
    ``against``, another run (e.g. the other calibration mode), adds a side-by-side table."""
    lines: list[str] = ["# StereoTacTip benchmark report", ""]
    if not records:
        lines += ["No experiment records in this directory.", ""]
    recs = dict(sorted(records.items()))
    any_rec = next(iter(recs.values()), None)
    if any_rec is not None:
        quick = {r["quick"] for r in recs.values()}
        commits = sorted({r["commit"] for r in recs.values()})
        seeds = sorted({r["seed"] for r in recs.values()})
        total = sum(float(r.get("wall_time_s") or 0.0) for r in recs.values())
        v = any_rec["versions"]
        lines += [f"- commit: {', '.join(commits)}",
                  f"- variant: {'quick' if quick == {True} else 'full' if quick == {False} else 'mixed quick/full'}",
                  f"- seed(s): {', '.join(map(str, seeds))}",
                  f"- total wall time: {total:.1f} s",
                  "- versions: " + ", ".join(f"{k} {val}" for k, val in v.items()), ""]

    lines += ["## Summary", "",
              "Twin cells failing their physics checks (skin > 0.05 mm inside the indenter, unsettled, MuJoCo "
              "warnings; `twin.validity`) are kept out of the scores against CAD; the column counts them.", "",
              "| experiment | status | wall time (s) | physically invalid twin cells | design(s) |",
              "| --- | --- | --- | --- | --- |"]
    for name, r in recs.items():
        status = r["status"] if r["status"] == "ok" else f"**{r['status']}**"
        lines.append(f"| {name} | {status} | {_fmt(r.get('wall_time_s'), 3)} | {invalid_cells(r)} | "
                     f"{_md_escape(designs_used(r))} |")
    lines.append("")

    lines += ["## Paper figure vs this run", "",
              "| experiment | quantity | paper | this run | unit | where in the paper |",
              "| --- | --- | --- | --- | --- | --- |"]
    for name, r in recs.items():
        for metric, paper, measured, unit, where in paper_figures(r):
            lines.append(f"| {name} | {metric} | {paper} | {measured} | {unit} | {_md_escape(where)} |")
    lines += ["", "Trends and qualitative claims:", "",
              "| experiment | paper's claim | this run | verdict |", "| --- | --- | --- | --- |"]
    for name, r in recs.items():
        for f in r.get("findings", []):
            lines.append(f"| {name} | {_md_escape(f['claim'])} | {_md_escape(f['observed'])} | {_verdict(f['agrees'])} |")
    lines.append("")

    for other_name, other_records in against:
        lines += calibration_comparison(recs, other_records, other_name)

    quick_recs = {n: r for n, r in recs.items() if r.get("quick")}
    if quick_recs:
        lines += ["## Regression gate (benchmarks/thresholds.toml)", ""]
        try:
            violations = check(quick_recs, load_thresholds(), experiments=list(quick_recs))
        except ResultsError as exc:
            lines += [f"thresholds file unreadable: {exc}", ""]
        else:
            lines += [f"- {v}" for v in violations] or ["All guarded quick metrics are within their thresholds."]
            lines.append("")

    for name, r in recs.items():
        lines += [f"## {name}", ""]
        if r.get("description"):
            lines += [r["description"], ""]
        if r.get("error"):
            lines += ["```", str(r["error"]).strip(), "```", ""]
        if r["metrics"]:
            lines += ["| metric | value | unit |", "| --- | --- | --- |"]
            lines += [f"| {k} | {_fmt(m['value'])} | {m['unit']} |" for k, m in r["metrics"].items()]
            lines.append("")
        for note in r.get("notes", []):
            lines.append(f"- {_md_escape(note)}")
        for f in r.get("findings", []):
            lines.append(f"- finding ({_verdict(f['agrees'])}): {_md_escape(f['claim'])} — {_md_escape(f['observed'])}")
        if r.get("notes") or r.get("findings"):
            lines.append("")
        for fig in r.get("figures", []):
            lines += [f"![{name}: {Path(fig).stem}]({fig})", ""]

    for path in sorted(out_dir.glob("sweep_*.json")):
        try:
            sweep = json.loads(path.read_text())
            rows, units = sweep["rows"], sweep["units"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
            continue
        lines += [f"## Sweep: {sweep.get('sweep', path.stem)}", ""]
        metrics = list(units)
        lines.append("| cell | status | " + " | ".join(f"{m} ({units[m]})" for m in metrics) + " |")
        lines.append("| --- | --- | " + " | ".join("---" for _ in metrics) + " |")
        for row in rows:
            lines.append(f"| {row['cell']} | {row['status']} | " + " | ".join(_fmt(row.get(m)) for m in metrics) + " |")
        lines.append("")
        png = path.with_suffix(".png")
        if png.is_file():
            lines += [f"![sweep]({png.name})", ""]
    return "\n".join(lines) + "\n"


def write_report(out_dir: Path, screenshot: bool = True, against: Path | Sequence[Path] | None = None) -> Path:
    """Write ``out_dir/report.md`` and ``out_dir/report.html`` (:mod:`benchmarks.report_html`: the same
    content with the sweeps' trade-off plots) from the records there; returns the Markdown path. Each
    directory of ``against`` adds a side-by-side table of the experiments it shares with ``out_dir``.

    With ``screenshot`` and a Chromium on this machine, ``out_dir/report.png`` is the page as headless
    Chromium paints it; otherwise an older ``report.png`` is removed rather than left to disagree."""
    out_dir = Path(out_dir)
    records = load_records(out_dir)
    has_sweeps = any(out_dir.glob("sweep_*.json"))
    if not records and not has_sweeps:
        raise ResultsError(f"results directory {out_dir}: no experiment JSON records or sweep tables found")
    path = out_dir / "report.md"
    from pipeline.io.atomic import atomic_write_text

    from benchmarks.report_html import render_html

    others = []
    for other_dir in [] if against is None else [against] if isinstance(against, (str, Path)) else against:
        other_records = load_records(Path(other_dir))
        if not other_records:
            raise ResultsError(f"results directory {other_dir}: no experiment JSON records to compare with")
        others.append((str(other_dir), other_records))
    atomic_write_text(path, render_report(records, out_dir, against=others))
    html_path = atomic_write_text(out_dir / "report.html", render_html(records, out_dir))
    png, shot = out_dir / "report.png", None
    if screenshot:
        from benchmarks.browser import write_screenshot

        try:
            shot = write_screenshot(html_path, png)
        except (OSError, RuntimeError, TimeoutError) as exc:      # the report stands without its picture
            print(f"[report] no screenshot of {html_path.name}: {exc}", file=sys.stderr)
    if shot is None:
        png.unlink(missing_ok=True)
    return path
