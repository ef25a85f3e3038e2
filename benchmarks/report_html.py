"""``DIR/report.html``: the benchmark report as one self-contained page, with the sweeps' trade-offs.

The page holds what ``report.md`` holds (provenance, the summary with physics-validity counts, paper
figure vs this run, findings, each experiment's metrics and figures) and, for every sweep table in DIR,
the trade-off plots: each metric against skin thickness (one line per marker separation) and against
marker separation (one line per skin thickness), per pattern. The plots are inline SVG drawn here (no
script, no network): hovering a point shows its cell, value and validity; a hollow point is a cell
whose twin frames failed their physics checks; a cell without a value is named under the plot. Nothing
is fetched: figures are the PNG files beside the page.
How a real browser lays the page out and paints it is :mod:`benchmarks.browser`.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

from benchmarks.report import _fmt   # one way a figure is printed, in report.md and report.html alike

__all__ = ["render_html", "tradeoff_svg", "PLOT_METRICS_MAX"]

#: Metrics per sweep drawn as trade-off plots (the experiment's first declared ones with numbers).
PLOT_METRICS_MAX = 6
_W, _H, _PAD = 320, 210, 42
_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf")


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def tradeoff_svg(rows: Sequence[Mapping[str, Any]], metric: str, unit: str, x_key: str, series_key: str,
                 title: str, ident: Mapping[str, Any] | None = None) -> str:
    """One SVG plot of ``metric`` against ``x_key``, a line per value of ``series_key``.

    Every row with a number for ``metric`` is one ``<circle>`` (hollow when ``physics_valid`` is False)
    with a ``<title>`` tooltip; rows without a number are listed under the plot, not drawn. ``ident``
    becomes ``data-*`` attributes of the ``<figure>`` (which sweep, pattern, metric and axis it shows),
    so a checker can match each drawn plot with the table rows it should show."""
    pts = [(r, _num(r.get(x_key)), _num(r.get(metric))) for r in rows]
    drawn = [(r, x, y) for r, x, y in pts if x is not None and y is not None]
    missing = [r for r, x, y in pts if y is None]
    attrs = "".join(f' data-{_e(k)}="{_e(v)}"' for k, v in (ident or {}).items())
    out = [f'<figure class="plot"{attrs}><svg xmlns="http://www.w3.org/2000/svg" width="{_W}" height="{_H}" '
           f'viewBox="0 0 {_W} {_H}" role="img" aria-label="{_e(title)}">']
    out.append(f'<text x="{_W / 2}" y="14" text-anchor="middle" class="t">{_e(title)}</text>')
    if drawn:
        xs = [x for _, x, _ in drawn]
        ys = [y for _, _, y in drawn]
        x0, x1 = min(xs), max(xs)
        y0, y1 = min(ys + [0.0]), max(ys)
        x0, x1 = (x0 - 0.5, x1 + 0.5) if x0 == x1 else (x0, x1)
        y1 = y1 + 1.0 if y0 == y1 else y1

        def px(x: float) -> float:
            return _PAD + (x - x0) / (x1 - x0) * (_W - _PAD - 12)

        def py(y: float) -> float:
            return _H - _PAD + 10 - (y - y0) / (y1 - y0) * (_H - _PAD - 24)

        out.append(f'<line x1="{_PAD}" y1="{py(y0):.1f}" x2="{_W - 10}" y2="{py(y0):.1f}" class="ax"/>')
        out.append(f'<line x1="{_PAD}" y1="{py(y0):.1f}" x2="{_PAD}" y2="20" class="ax"/>')
        for v in (x0, x1):
            out.append(f'<text x="{px(v):.1f}" y="{py(y0) + 13:.1f}" text-anchor="middle">{_fmt(v, 3)}</text>')
        for v in (y0, y1):
            out.append(f'<text x="{_PAD - 4}" y="{py(v) + 4:.1f}" text-anchor="end">{_fmt(v, 3)}</text>')
        out.append(f'<text x="{_W / 2}" y="{_H - 4}" text-anchor="middle">{_e(x_key)}</text>')
        out.append(f'<text x="10" y="{_H / 2}" transform="rotate(-90 10 {_H / 2})" text-anchor="middle">'
                   f'{_e(metric)} ({_e(unit)})</text>')
        series = sorted({r.get(series_key) for r, _, _ in drawn}, key=lambda v: (v is None, v))
        for k, s in enumerate(series):
            colour = _COLOURS[k % len(_COLOURS)]
            mine = sorted(((x, y, r) for r, x, y in drawn if r.get(series_key) == s), key=lambda t: t[0])
            if len(mine) > 1:
                path = " ".join(f"{px(x):.1f},{py(y):.1f}" for x, y, _ in mine)
                out.append(f'<polyline points="{path}" fill="none" stroke="{colour}" stroke-width="1.2"/>')
            for x, y, r in mine:
                valid = r.get("physics_valid")
                fill = "none" if valid is False else colour
                tip = (f"{r.get('cell')}: {metric} = {_fmt(y)} {unit}; {x_key} {_fmt(x)}; {series_key} {_fmt(s)}; "
                       f"physics {'valid' if valid else 'INVALID' if valid is False else 'not reported'}")
                out.append(f'<circle cx="{px(x):.1f}" cy="{py(y):.1f}" r="3.5" fill="{fill}" stroke="{colour}" '
                           f'class="pt"><title>{_e(tip)}</title></circle>')
            out.append(f'<text x="{_W - 12}" y="{30 + 12 * k}" text-anchor="end" fill="{colour}">'
                       f'{_e(series_key)} {_e(_fmt(s))}</text>')
    else:
        out.append(f'<text x="{_W / 2}" y="{_H / 2}" text-anchor="middle">no cell reported {_e(metric)}</text>')
    out.append("</svg>")
    if missing:
        out.append("<figcaption>not drawn (no value): " + ", ".join(_e(r.get("cell")) for r in missing)
                   + "</figcaption>")
    out.append("</figure>")
    return "".join(out)


def _sweep_section(path: Path) -> list[str]:
    try:
        sweep = json.loads(path.read_text())
        rows, units = sweep["rows"], sweep["units"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        return []
    name = sweep.get("sweep", path.stem)
    out = [f'<section class="sweep"><h2>Sweep: {_e(name)}</h2>']
    links = [p.name for p in (path.with_suffix(".parquet"), path.with_suffix(".csv")) if p.is_file()]
    if links:
        out.append("<p>Results table: " + ", ".join(f'<a href="{_e(n)}">{_e(n)}</a>' for n in links) + "</p>")
    status: dict[str, int] = {}
    for r in rows:
        status[str(r.get("status"))] = status.get(str(r.get("status")), 0) + 1
    valid = [r.get("physics_valid") for r in rows]
    out.append(f"<p>{len(rows)} cells: " + ", ".join(f"{v} {_e(k)}" for k, v in sorted(status.items()))
               + f"; physics valid {sum(v is True for v in valid)}, invalid {sum(v is False for v in valid)}, "
               f"not reported {sum(v is None for v in valid)}. Engine: {_e(sweep.get('engine', '—'))}; "
               f"seed {_e(sweep.get('seed'))}.</p>")
    metrics = [m for m in units if any(_num(r.get(m)) is not None for r in rows)
               and m not in ("invalid_cells", "valid_cells", "failed_cells")][:PLOT_METRICS_MAX]
    for pattern in sorted({str(r.get("pattern")) for r in rows}):
        mine = [r for r in rows if str(r.get("pattern")) == pattern]
        out.append(f"<h3>{_e(pattern)} pattern</h3><div class='plots'>")
        for m in metrics:
            ident = {"sweep": name, "pattern": pattern, "metric": m}
            out.append(tradeoff_svg(mine, m, units[m], "skin_mm", "separation_mm", f"{m} vs skin thickness",
                                    {**ident, "x": "skin_mm"}))
            out.append(tradeoff_svg(mine, m, units[m], "separation_mm", "skin_mm", f"{m} vs marker separation",
                                    {**ident, "x": "separation_mm"}))
        out.append("</div>")
    png = path.with_suffix(".png")
    if png.is_file():
        out.append(f'<img src="{_e(png.name)}" alt="sweep {_e(name)} summary">')
    out.append("</section>")
    return out


_CSS = """body{font-family:serif;max-width:1100px;margin:1em auto;padding:0 1em}table{border-collapse:collapse;
margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;font-size:13px}img{max-width:100%}
.plots{display:flex;flex-wrap:wrap;gap:8px}.plot{margin:0}svg text{font-size:10px;font-family:sans-serif}
svg .t{font-size:11px;font-weight:bold}.ax{stroke:#333;stroke-width:1}.pt:hover{stroke-width:3}
figcaption{font-size:11px;color:#a00;max-width:320px}.bad{color:#a00;font-weight:bold}"""


def render_html(records: Mapping[str, Mapping[str, Any]], out_dir: Path) -> str:
    """The HTML text of the report (figure and table links relative to ``out_dir``)."""
    out_dir = Path(out_dir)
    recs = dict(sorted(records.items()))
    h = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
         "<title>StereoTacTip benchmark report</title>", f"<style>{_CSS}</style></head><body>",
         "<h1>StereoTacTip benchmark report</h1>"]
    if recs:
        any_rec = next(iter(recs.values()))
        commits = sorted({str(r.get("commit")) for r in recs.values()})
        seeds = sorted({str(r.get("seed")) for r in recs.values()})
        total = sum(float(r.get("wall_time_s") or 0.0) for r in recs.values())
        h.append("<h2>Provenance</h2><ul>"
                 f"<li>commit: {_e(', '.join(commits))}</li><li>seed(s): {_e(', '.join(seeds))}</li>"
                 f"<li>total wall time: {total:.1f} s</li><li>versions: "
                 + _e(", ".join(f"{k} {v}" for k, v in (any_rec.get("versions") or {}).items())) + "</li></ul>")
        h.append("<h2>Summary</h2><table><tr><th>experiment</th><th>status</th><th>wall time (s)</th>"
                 "<th>physically invalid twin cells</th></tr>")
        for name, r in recs.items():
            inv = (r["metrics"].get("invalid_cells") or {}).get("value")
            val = (r["metrics"].get("valid_cells") or {}).get("value")
            phys = "—" if inv is None else f"{_fmt(inv)}" + (f" of {_fmt(inv + val)}" if val is not None else "")
            cls = "" if r.get("status") == "ok" else " class='bad'"
            h.append(f"<tr><td>{_e(name)}</td><td{cls}>{_e(r.get('status'))}</td>"
                     f"<td>{_fmt(r.get('wall_time_s'), 3)}</td><td>{_e(phys)}</td></tr>")
        h.append("</table><h2>Paper figure vs this run</h2><table><tr><th>experiment</th><th>quantity</th>"
                 "<th>paper</th><th>this run</th><th>unit</th><th>where in the paper</th></tr>")
        for name, r in recs.items():
            for metric, p in (r.get("paper") or {}).items():
                m = r["metrics"].get(metric)
                h.append(f"<tr><td>{_e(name)}</td><td>{_e(metric)}</td><td>{_fmt(p['value'])}</td>"
                         f"<td>{_fmt(m['value'] if m else None)}</td><td>{_e(p['unit'])}</td><td>{_e(p['text'])}</td></tr>")
        h.append("</table><h2>Findings</h2><table><tr><th>experiment</th><th>claim</th><th>this run</th>"
                 "<th>verdict</th></tr>")
        verdict = {True: "agrees", False: "disagrees", None: "undecided"}
        for name, r in recs.items():
            for f in r.get("findings") or []:
                h.append(f"<tr><td>{_e(name)}</td><td>{_e(f['claim'])}</td><td>{_e(f['observed'])}</td>"
                         f"<td>{verdict.get(f.get('agrees'), '?')}</td></tr>")
        h.append("</table>")
        for name, r in recs.items():
            h.append(f"<section><h2>{_e(name)}</h2><p>{_e(r.get('description', ''))}</p>")
            if r.get("metrics"):
                h.append("<table><tr><th>metric</th><th>value</th><th>unit</th></tr>" + "".join(
                    f"<tr><td>{_e(k)}</td><td>{_fmt(m.get('value'))}</td><td>{_e(m.get('unit'))}</td></tr>"
                    for k, m in r["metrics"].items()) + "</table>")
            for note in r.get("notes") or []:
                h.append(f"<p>{_e(note)}</p>")
            for fig in r.get("figures") or []:
                h.append(f'<img src="{_e(fig)}" alt="{_e(name)}: {_e(Path(fig).stem)}">')
            h.append("</section>")
    else:
        h.append("<p>No experiment records in this directory.</p>")
    for path in sorted(out_dir.glob("sweep_*.json")):
        h += _sweep_section(path)
    h.append("</body></html>")
    return "\n".join(h) + "\n"
