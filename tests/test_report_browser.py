"""``report.html`` opened in a real headless Chromium (Debian's ``chromium``, the ``report`` extra).

The report is built from a real small run of the framework's own test experiments: the toy
experiment's record (paper table, finding, a matplotlib figure), a 4-cell sweep of it (its ``skin_mm``
metric differs per cell, so points and lines are distinct), and a 12-cell ``toy-table`` sweep over two
patterns, two marker separations and three skin thicknesses, in which the thin-skin cells fail their
physics checks and the thick-skin cells raise (its ``mean`` is the same in every cell, so points of
different series coincide and only the last drawn is visible: the checker allows exactly that). The
page is loaded with JavaScript on and the network blocked; once it has run and painted, every trade-off
plot must be present, hold one point per cell of the sweep table that reported the metric (hollow where
the physics failed), a line per series with more than one point, and every point must be painted in
its series colour in the screenshot; no script error, console error, failed load, broken image or
network request is allowed. The same checker must find each fault planted in a broken copy of the page.

Without Chromium the tests skip and say why, except under ``CI=true``: CI installs the extra
(``make setup`` as root with apt), so there a missing browser fails.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

import test_benchmarks as TB
import test_executor as TE
from benchmarks import registry as reg
from benchmarks import results as res
from benchmarks.registry import Context, PaperValue, register
from benchmarks.report import write_report
from benchmarks.browser import Chromium, find_chromium
from benchmarks.sweep import make_cells, run_sweep

ON_CI = os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")

SKINS, SEPARATIONS, PATTERNS = [0.5, 1.0, 1.5], [1.8, 2.54], ["hexagon", "square"]
#: each sweep's plotted metrics ("invalid_cells" is a count: tabulated, not plotted)
PLOTTED = {"toy": ["mean", "skin_mm"], "toy-table": ["mean"]}
AXES = (("skin_mm", "separation_mm"), ("separation_mm", "skin_mm"))   # (x, one line per value of)
#: a painted pixel may differ from its declared colour by this much per channel (anti-aliased edges)
COLOUR_TOL = 48


@pytest.fixture(scope="module")
def browser():
    exe = find_chromium()
    if exe is None:
        why = ("no headless Chromium on this machine (Debian: apt-get install chromium; `make setup` does it "
               "as root; or set STEREOTACTIP_CHROMIUM to the executable)")
        if ON_CI:
            pytest.fail("CI installs the report extra, yet " + why)
        pytest.skip(why)
    with Chromium(exe) as b:
        yield b


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory, browser):
    """A results directory with one experiment record and one sweep, and its report (with report.png)."""
    out = tmp_path_factory.mktemp("report")
    reg.load_all()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(reg, "_REGISTRY", dict(reg._REGISTRY))
        register("toy", tags=("quick",), metrics={"mean": "1", "skin_mm": "mm"},
                 paper={"mean": PaperValue(0.5, "1", "E[U(0,1)]")})(TB._toy_run)
        register("toy-table", tags=("quick",), metrics={"mean": "1", "invalid_cells": "1"})(TE._toy)
        res.execute(reg._REGISTRY["toy"], Context(out_dir=out, quick=True, progress=False))
        run_sweep("toy", make_cells(SKINS[:2], SEPARATIONS, PATTERNS[:1]), out, quick=True, workers=1,
                  progress=False)
        run_sweep("toy-table", make_cells(SKINS, SEPARATIONS, PATTERNS), out, quick=True, workers=1,
                  progress=False)
        write_report(out)
    return out


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def expected_plots(out_dir: Path) -> dict[tuple, dict]:
    """What each trade-off plot must show, from the sweep tables alone (not from the page)."""
    want = {}
    for path in sorted(out_dir.glob("sweep_*.json")):
        sweep = json.loads(path.read_text())
        for pattern in sorted({r["pattern"] for r in sweep["rows"]}):
            rows = [r for r in sweep["rows"] if r["pattern"] == pattern]
            for metric in PLOTTED[sweep["sweep"]]:
                for x, series in AXES:
                    pts = [r for r in rows if _finite(r.get(metric)) and _finite(r.get(x))]
                    per_series = [sum(r[series] == s for r in pts) for s in {r[series] for r in pts}]
                    want[(sweep["sweep"], pattern, metric, x)] = {
                        "cells": sorted(r["cell"] for r in pts),
                        "hollow": sorted(r["cell"] for r in pts if r.get("physics_valid") is False),
                        "lines": sum(n > 1 for n in per_series)}
    return want


def _rgb(colour: str) -> np.ndarray:
    m = re.fullmatch(r"#([0-9a-fA-F]{2})([0-9a-fA-F]{2})([0-9a-fA-F]{2})", colour or "")
    assert m, f"point colour {colour!r} is not #rrggbb"
    return np.array([int(g, 16) for g in m.groups()], dtype=int)


def check_page(browser: Chromium, html: Path, want: dict[tuple, dict]) -> list[str]:
    """Everything wrong with ``html`` as Chromium runs and paints it, given the plots it must show."""
    view = browser.load(html)
    problems = [f"page error: {e}" for e in view.errors]
    problems += [f"network request from the page: {u}" for u in view.external]
    problems += [f"image not shown: {i['src']}" for i in view.images if not i["loaded"]]
    shot = cv2.imdecode(np.frombuffer(view.png, np.uint8), cv2.IMREAD_COLOR)
    if shot is None:
        return problems + ["the screenshot is not a PNG"]
    shot = shot[:, :, ::-1].astype(int)                                      # BGR → RGB
    seen = {}
    for p in view.plots:
        i = p["ident"]
        key = (i.get("sweep"), i.get("pattern"), i.get("metric"), i.get("x"))
        if key in seen:
            problems.append(f"plot {key} drawn twice")
        seen[key] = p
    problems += [f"plot {k} missing" for k in want if k not in seen]
    problems += [f"plot {k} not in the sweep tables" for k in seen if k not in want]
    for key in [k for k in want if k in seen]:
        p, w = seen[key], want[key]
        box = p["svg"]
        if box is None or box["w"] < 50 or box["h"] < 50:
            problems.append(f"plot {key}: no laid-out SVG ({box})")
            continue
        cells = sorted(pt["tip"].split(":")[0] for pt in p["points"])
        if cells != w["cells"]:
            problems.append(f"plot {key}: points for {cells}, the table has {w['cells']}")
        hollow = sorted(pt["tip"].split(":")[0] for pt in p["points"] if not pt["filled"])
        if hollow != w["hollow"]:
            problems.append(f"plot {key}: hollow points {hollow}, physics-invalid cells {w['hollow']}")
        if p["lines"] != w["lines"]:
            problems.append(f"plot {key}: {p['lines']} lines, expected {w['lines']}")
        for k, pt in enumerate(p["points"]):
            name = pt["tip"].split(":")[0]
            cx, cy = pt["x"] + pt["w"] / 2, pt["y"] + pt["h"] / 2
            if not pt["shown"] or pt["w"] <= 0:
                problems.append(f"plot {key}: point {name} hidden")
                continue
            if not (box["x"] <= cx <= box["x"] + box["w"] and box["y"] <= cy <= box["y"] + box["h"]):
                problems.append(f"plot {key}: point {name} outside its plot")
                continue
            if any(abs(q["x"] - pt["x"]) < pt["w"] / 2 and abs(q["y"] - pt["y"]) < pt["h"] / 2
                   for q in p["points"][k + 1:]):
                continue                                     # the same value drawn again on top of it
            colour, r = _rgb(pt["colour"]), int(math.ceil(pt["w"] / 2)) + 1
            ix, iy = int(cx), int(cy)
            patch = shot[max(iy - r, 0):iy + r + 1, max(ix - r, 0):ix + r + 1]
            ring = patch.size and (np.abs(patch - colour).max(axis=2) <= COLOUR_TOL).any()
            centre = iy < shot.shape[0] and ix < shot.shape[1] and np.abs(shot[iy, ix] - colour).max() <= COLOUR_TOL
            if not ring or (pt["filled"] and not centre):
                problems.append(f"plot {key}: point {name} not painted in {pt['colour']} at ({ix}, {iy})")
    return problems


def test_sweep_table_has_what_the_plots_must_show(report_dir):
    """The fixture's own truth: every kind of point the checker looks for is present in the data."""
    want = expected_plots(report_dir)
    assert len(want) == 4 + 4                                # toy-table: 2 patterns × "mean" × 2 axes; toy: 2 metrics × 2 axes
    for (sweep, pattern, _, x), w in want.items():
        assert len(w["cells"]) == 4 and w["lines"] == 2      # skins 0.5, 1.0 × 2 separations; 1.5 mm raised
        if sweep == "toy-table":
            assert len(w["hollow"]) == 2 and all("skin0.50" in c for c in w["hollow"])
        else:
            assert w["hollow"] == []                         # the toy reports no physics validity


def test_report_renders_every_plot_in_chromium(browser, report_dir):
    page = report_dir / "report.html"
    assert check_page(browser, page, expected_plots(report_dir)) == []
    view = browser.load(page)
    assert [i["src"] for i in view.images] == ["toy_hist.png", "sweep_toy-table.png", "sweep_toy.png"]
    assert view.errors == [] and view.external == []


def test_report_png_is_the_page_as_chromium_paints_it(browser, report_dir):
    shot = cv2.imread(str(report_dir / "report.png"), cv2.IMREAD_COLOR)
    assert shot is not None
    view = browser.load(report_dir / "report.html")
    assert shot.shape[:2] == (view.height, view.width)
    # the plot of the first pattern sits where the page lays it out, and is not blank
    box = view.plots[0]["svg"]
    region = shot[int(box["y"]):int(box["y"] + box["h"]), int(box["x"]):int(box["x"] + box["w"])]
    assert (region.min(axis=2) < 128).mean() > 0.005


def test_no_screenshot_leaves_no_stale_png(report_dir, tmp_path):
    import shutil

    copy = tmp_path / "r"
    shutil.copytree(report_dir, copy)
    assert (copy / "report.png").is_file()
    write_report(copy, screenshot=False)
    assert not (copy / "report.png").exists()


def _first_svg_span(page: str) -> tuple[int, int]:
    start = page.index("<svg ")
    return start, page.index("</svg>", start) + len("</svg>")


def _drop_one_point(page: str) -> str:
    a, b = _first_svg_span(page)
    svg = re.sub(r"<circle [^>]*><title>[^<]*</title></circle>", "", page[a:b], count=1)
    return page[:a] + svg + page[b:]


def _drop_first_plot(page: str) -> str:
    a = page.index('<figure class="plot"')
    return page[:a] + page[page.index("</figure>", a) + len("</figure>"):]


BROKEN = {
    "script error": (lambda p: p.replace("</body>", "<script>undefinedPlotter.draw()</script></body>"),
                     "page error: uncaught exception: ReferenceError: undefinedPlotter is not defined"),
    "console error": (lambda p: p.replace("</body>", "<script>console.error('no data for plot')</script></body>"),
                      "page error: console.error: no data for plot"),
    "CDN script": (lambda p: p.replace("</head>", '<script src="https://cdn.example.org/plot.js"></script></head>'),
                   "network request from the page: https://cdn.example.org/plot.js"),
    "a point missing": (_drop_one_point, "points for"),
    "a plot missing": (_drop_first_plot, "', 'mean', 'skin_mm') missing"),
    "points painted over": (lambda p: p.replace("</style>", ".plots svg{filter:opacity(0)}</style>"),
                            "not painted"),
    "points hidden": (lambda p: p.replace("</style>", ".pt{visibility:hidden}</style>"), "hidden"),
    "a figure missing": (lambda p: p.replace('src="toy_hist.png"', 'src="toy_histogram.png"'),
                         "image not shown: toy_histogram.png"),
}


@pytest.mark.parametrize("fault", list(BROKEN))
def test_the_checker_finds_a_broken_page(browser, report_dir, fault):
    """A copy of the real page with one fault planted: the checker that passes the real page fails it."""
    breaks, says = BROKEN[fault]
    page = (report_dir / "report.html").read_text()
    broken = breaks(page)
    assert broken != page
    copy = report_dir / f"broken_{fault.replace(' ', '_')}.html"
    copy.write_text(broken)
    try:
        problems = check_page(browser, copy, expected_plots(report_dir))
    finally:
        copy.unlink()
    assert any(says in p for p in problems), problems
