"""The benchmark framework (registry, JSON records, thresholds gate, report, sweep, CLI) and one test
that walks the registry and checks every experiment's invariants (dm_control ``suite_test`` style).

Cheap experiments (tag ``cheap``) run for real with tiny settings; the expensive ones are exercised
by ``stereotactip bench all --quick --check`` in CI (``make test``). Over ~400 lines on purpose: the
framework's pieces (records, gate, report, README blocks, sweep, CLI) share the toy experiment and its
fixtures defined at the top.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from benchmarks import registry as reg
from benchmarks import results as res
from benchmarks import thresholds as gate
from benchmarks.registry import Context, Finding, PaperValue, Result, register
from benchmarks.report import render_report, write_report
from benchmarks.sweep import Cell, make_cells, run_sweep
from stereotactip.cli import main


# ----- a private experiment used to exercise the framework itself ------------------------------

def _toy_run(ctx: Context) -> Result:
    """Toy: mean of uniform samples (known value 0.5) — a test fixture, not a paper experiment."""
    n = int(ctx.param("n", 2000, quick=500))
    x = ctx.rng("toy").uniform(size=n)
    out = Result(designs=[ctx.design()])
    out.metric("mean", x.mean(), "1")
    out.metric("skin_mm", out.designs[0].skin.thickness_mm, "mm")
    out.tables["samples"] = [{"i": i, "x": float(v)} for i, v in enumerate(x[:3])]
    out.findings.append(Finding("the mean is one half", f"mean {x.mean():.3f}", abs(x.mean() - 0.5) < 0.05))
    with res.paper_style() as plt:
        fig, ax = plt.subplots(figsize=(2, 2))
        ax.hist(x, bins=10)
        out.figures.append(res.save_figure(fig, ctx.figure_path("toy_hist")))
    return out


@pytest.fixture
def toy(monkeypatch):
    """Register the toy experiment in the global registry for the duration of a test."""
    monkeypatch.setattr(reg, "_REGISTRY", dict(reg._REGISTRY))
    register("toy", tags=("quick",), metrics={"mean": "1", "skin_mm": "mm"},
             paper={"mean": PaperValue(0.5, "1", "E[U(0,1)]")})(_toy_run)
    return reg._REGISTRY["toy"]


# Mean of n uniform samples has standard deviation sqrt(1/12/n) = 0.013 for n = 500: 5 sigma = 0.065.
TOY_MEAN_TOL = 5 * math.sqrt(1 / 12 / 500)


def test_execute_writes_a_complete_record(toy, tmp_path):
    ctx = Context(out_dir=tmp_path, quick=True, seed=3, progress=False)
    rec = res.execute(toy, ctx)
    on_disk = res.load_record(tmp_path / "toy.json")
    assert on_disk == rec
    assert set(res.REQUIRED_KEYS) <= set(rec)
    assert rec["status"] == "ok" and rec["error"] is None
    assert rec["quick"] is True and rec["seed"] == 3
    assert rec["metrics"]["mean"]["unit"] == "1"
    assert abs(rec["metrics"]["mean"]["value"] - 0.5) < TOY_MEAN_TOL
    assert rec["design"]["name"] == "hexagon127" and rec["design"]["skin"]["thickness_mm"] == 1.0
    assert rec["commit"] == "unknown" or len(rec["commit"]) == 40
    assert {"numpy", "mujoco", "opencv"} <= set(rec["versions"])
    assert rec["figures"] == ["toy_hist.png"] and (tmp_path / "toy_hist.png").stat().st_size > 1000
    assert rec["findings"][0]["agrees"] is True


def test_seed_makes_runs_reproducible_and_streams_independent(toy, tmp_path):
    a = res.execute(toy, Context(out_dir=tmp_path / "a", quick=True, seed=1, progress=False))
    b = res.execute(toy, Context(out_dir=tmp_path / "b", quick=True, seed=1, progress=False))
    c = res.execute(toy, Context(out_dir=tmp_path / "c", quick=True, seed=2, progress=False))
    assert a["metrics"]["mean"] == b["metrics"]["mean"]
    assert a["metrics"]["mean"] != c["metrics"]["mean"]
    ctx = Context(out_dir=tmp_path, seed=1)
    assert not np.array_equal(ctx.rng("x").uniform(size=4), ctx.rng("y").uniform(size=4))


def test_overrides_and_sweep_base_design_reach_the_design(toy, tmp_path):
    ctx = Context(out_dir=tmp_path, quick=True, overrides={"skin.thickness_mm": 0.5}, progress=False)
    rec = res.execute(toy, ctx)
    assert rec["metrics"]["skin_mm"]["value"] == 0.5 and rec["overrides"] == {"skin.thickness_mm": 0.5}
    ctx = Context(out_dir=tmp_path, base_design="square121")
    assert [d.name for d in ctx.designs(["hexagon127", "circular217_dome"])] == ["square121"]
    assert [d.name for d in Context(out_dir=tmp_path).designs(["hexagon127", "square121"])] == ["hexagon127", "square121"]


def test_failures_are_recorded_not_hidden(tmp_path):
    local: dict = {}

    @register("boom", metrics={"x": "mm"}, registry=local)
    def boom(ctx):
        raise RuntimeError("exploded on purpose")

    @register("undeclared", metrics={"x": "mm"}, registry=local)
    def undeclared(ctx):
        r = Result()
        r.metric("y", 1.0, "mm")
        return r

    @register("wrong-unit", metrics={"x": "mm"}, registry=local)
    def wrong_unit(ctx):
        r = Result()
        r.metric("x", 1.0, "px")
        return r

    @register("needs-missing", metrics={"x": "mm"}, requires=("no_such_module_xyz",), registry=local)
    def needs(ctx):  # pragma: no cover — must not run
        raise AssertionError

    ctx = Context(out_dir=tmp_path, progress=False)
    r = res.execute(local["boom"], ctx)
    assert r["status"] == "error" and "exploded on purpose" in r["error"]
    assert res.execute(local["undeclared"], ctx)["status"] == "error"
    assert res.execute(local["wrong-unit"], ctx)["status"] == "error"
    r = res.execute(local["needs-missing"], ctx)
    assert r["status"] == "unavailable" and "no_such_module_xyz" in r["error"]
    with pytest.raises(RuntimeError):
        res.execute(local["boom"], ctx, catch=False)
    with pytest.raises(ValueError, match="registered twice"):
        register("boom", metrics={"x": "mm"}, registry=local)(lambda ctx: Result())
    with pytest.raises(ValueError, match="undeclared metric"):
        register("p", metrics={"x": "mm"}, paper={"y": PaperValue(1, "mm", "")}, registry=local)(boom)


def _thresholds_file(tmp_path, text):
    path = tmp_path / "thresholds.toml"
    path.write_text(text)
    return path


def test_check_flags_out_of_bounds_missing_and_failed(toy, tmp_path):
    rec = res.execute(toy, Context(out_dir=tmp_path, quick=True, progress=False))
    th = gate.load_thresholds(_thresholds_file(tmp_path, """
[toy]
mean = { min = 0.45, max = 0.55, measured = 0.5, why = "5 sigma" }
skin_mm = { max = 0.9, why = "deliberately violated" }
absent = { min = 0, why = "metric the run does not report" }
"""))
    vs = gate.check({"toy": rec}, th)
    assert {(v.metric, v.reason) for v in vs} == {("skin_mm", "out of bounds: sanity tier (collapse)"),
                                                  ("absent", "metric missing")}
    text = str(next(v for v in vs if v.metric == "skin_mm"))
    assert "toy.skin_mm" in text and "<= 0.9" in text and "value 1" in text
    assert [v.reason for v in gate.check({}, th, experiments=["toy"])][0] == "experiment did not run"
    failed = dict(rec, status="error", error="boom")
    assert all("status" in v.reason for v in gate.check({"toy": failed}, th))
    full = dict(rec, quick=False)
    assert all("full run" in v.reason for v in gate.check({"toy": full}, th))


def test_golden_tier_catches_a_regression_the_sanity_tier_lets_through(toy, tmp_path):
    """The toy's mean is about 0.5: inside a loose sanity bound, outside a golden bound set from another value."""
    rec = res.execute(toy, Context(out_dir=tmp_path, quick=True, progress=False))
    assert rec["metrics"]["mean"]["value"] == pytest.approx(0.5, abs=0.05)
    ok = gate.load_thresholds(_thresholds_file(tmp_path, """
[toy]
mean = { min = 0.1, max = 0.9, golden_min = 0.4, golden_max = 0.6, kind = "deterministic", measured = 0.5, why = "x" }
"""))
    assert gate.check({"toy": rec}, ok) == []
    drifted = gate.load_thresholds(_thresholds_file(tmp_path, """
[toy]
mean = { min = 0.1, max = 0.9, golden_min = 0.31, golden_max = 0.4, kind = "deterministic", measured = 0.4, why = "x" }
"""))
    (v,) = gate.check({"toy": rec}, drifted)
    assert "golden tier" in v.reason and "golden >= 0.31 and <= 0.4" in str(v) and "value 0.49" in str(v)
    collapsed = gate.load_thresholds(_thresholds_file(tmp_path, """
[toy]
mean = { max = 0.45, golden_max = 0.45, kind = "exact", measured = 0.45, why = "x" }
"""))
    (v,) = gate.check({"toy": rec}, collapsed)
    assert "sanity tier" in v.reason and "<= 0.45" in str(v)


def test_mode_tables_apply_only_to_records_of_their_calibration_mode(toy, tmp_path):
    rec = res.execute(toy, Context(out_dir=tmp_path, quick=True, progress=False))
    assert rec["calibration"]["mode"] == "oracle"
    th = gate.load_thresholds(_thresholds_file(tmp_path, """
[toy]
mean = { min = 0.4, why = "both modes" }
[toy.estimated]
mean = { min = 0.9, why = "estimated records only" }
[toy.oracle]
skin_mm = { max = 0.9, why = "oracle records only" }
"""))
    assert set(th["toy"]) == {"mean", "estimated.mean", "oracle.skin_mm"}
    (v,) = gate.check({"toy": rec}, th)
    assert v.metric == "skin_mm (oracle)"
    est = dict(rec, calibration=dict(rec["calibration"], mode="estimated"))
    (v,) = gate.check({"toy": est}, th)
    assert v.metric == "mean (estimated)" and ">= 0.9" in v.threshold


@pytest.mark.parametrize("spec, match", [
    ("golden_max = 0.7, kind = 'deterministic', measured = 0.5", "within 25% above the measured 0.5"),
    ("golden_min = 0.3, kind = 'deterministic', measured = 0.5", "within 25% below the measured 0.5"),
    ("golden_max = 0.6, kind = 'exact', measured = 0.5", "within 0% above"),
    ("golden_max = 0.45, kind = 'deterministic', measured = 0.5", "above the measured"),
    ("golden_max = 0.6, kind = 'noisy', measured = 0.5", "needs spread"),
    ("golden_max = 0.7, kind = 'noisy', spread = [0.4, 0.5]", "within 25% above the measured 0.5"),
    ("golden_max = 0.6, kind = 'noisy', spread = [0.5, 0.4]", "spread must be"),
    ("golden_max = 0.6, measured = 0.5", "needs kind"),
    ("kind = 'exact', measured = 0.5", "without golden_min and/or golden_max"),
    ("golden_max = 0.6, kind = 'sloppy', measured = 0.5", "needs kind"),
    ("max = 0.55, golden_max = 0.6, kind = 'deterministic', measured = 0.5", "looser than the sanity max"),
    ("measured = 'half'", "expected a number"),
])
def test_golden_bounds_keep_their_own_rule(tmp_path, spec, match):
    """A golden bound sits at the measured value (exact), within 25 % of it (deterministic) or within 25 %
    beyond the measured spread (noisy), and inside the sanity bound: the file cannot drift loose."""
    text = f"[toy]\nmean = {{ min = 0.0, {spec}, why = 'x' }}\n"
    if "max = 0.55" in spec:
        text = f"[toy]\nmean = {{ {spec}, why = 'x' }}\n"
    with pytest.raises(res.ResultsError, match=match):
        gate.load_thresholds(_thresholds_file(tmp_path, text))


@pytest.mark.parametrize("text, match", [
    ("[toy]\nmean = { min = 0.4 }\n", "why"),
    ("[toy]\nmean = { why = 'x' }\n", "min and/or max"),
    ("[toy]\nmean = { min = 1, why = 'x', typo = 2 }\n", "unknown key 'typo'"),
    ("[toy]\nmean = 3\n", "inline table"),
    ("[toy.estimated]\nmean = 3\n", "table of metric bounds"),
    ("[toy\n", "thresholds file"),
])
def test_malformed_thresholds_are_user_errors(tmp_path, text, match):
    with pytest.raises(res.ResultsError, match=match):
        gate.load_thresholds(_thresholds_file(tmp_path, text))


def test_cli_bench_check_exit_status_and_message(toy, tmp_path, monkeypatch, capsys):
    good = _thresholds_file(tmp_path, "[toy]\nmean = { min = 0.4, max = 0.6, why = 'x' }\n")
    monkeypatch.setattr(gate, "thresholds_path", lambda: good)
    out = tmp_path / "out"
    assert main(["bench", "toy", "--quick", "--check", "--out", str(out), "--no-progress"]) == 0
    bad = tmp_path / "bad"
    bad.mkdir()
    bad_file = _thresholds_file(bad, "[toy]\nmean = { min = 0.9, why = 'regression on purpose' }\n")
    monkeypatch.setattr(gate, "thresholds_path", lambda: bad_file)
    capsys.readouterr()
    assert main(["bench", "toy", "--quick", "--check", "--out", str(out), "--no-progress"]) == 1
    printed = capsys.readouterr().out
    assert "REGRESSION toy.mean" in printed and ">= 0.9" in printed
    # user errors: unknown experiment, malformed option, --check without --quick
    assert main(["bench", "no-such-experiment", "--out", str(out)]) == 2
    assert main(["bench", "toy", "--out", str(out), "--param", "oops"]) == 2
    assert main(["bench", "toy", "--check", "--out", str(out), "--no-progress"]) == 2
    assert main(["bench", "toy", "--out", str(out), "--set", "skin.no_such_key=1"]) == 2


def test_cli_param_and_set_reach_the_experiment(toy, tmp_path):
    out = tmp_path / "o"
    assert main(["bench", "toy", "--out", str(out), "--param", "n=10", "--set", "skin.thickness_mm=1.5",
                 "--no-progress"]) == 0
    rec = json.loads((out / "toy.json").read_text())
    assert rec["params"] == {"n": 10} and rec["metrics"]["skin_mm"]["value"] == 1.5
    assert len(rec["tables"]["samples"]) == 3


def test_report_has_paper_table_findings_gate_and_figures(toy, tmp_path, monkeypatch):
    res.execute(toy, Context(out_dir=tmp_path, quick=True, progress=False))
    th = _thresholds_file(tmp_path / "..", "[toy]\nmean = { min = 0.99, why = 'x' }\n")
    monkeypatch.setattr(gate, "thresholds_path", lambda: th)
    path = write_report(tmp_path)
    text = path.read_text()
    assert "## Paper figure vs this run" in text
    row = next(line for line in text.splitlines() if line.startswith("| toy | mean |"))
    assert "| 0.5 |" in row and "E[U(0,1)]" in row
    assert "the mean is one half" in text and "agrees" in text
    assert "REGRESSION toy.mean" in text
    assert "![toy: toy_hist](toy_hist.png)" in text
    (tmp_path / "empty").mkdir()
    with pytest.raises(res.ResultsError, match="no experiment JSON"):
        write_report(tmp_path / "empty")
    assert main(["report", str(tmp_path / "missing")]) == 2
    assert render_report({}, tmp_path).startswith("# StereoTacTip benchmark report")


def test_sweep_cells_keep_pattern_radius_and_fit_the_gel():
    from pipeline.design import load_design

    cells = make_cells([0.5, 1.5], [1.80, 2.54, 3.54], ["hexagon", "square", "circular"])
    assert len(cells) == 18
    counts = {c.cell_id: c.design().marker_count for c in cells}
    # the built-in hexagons are reproduced exactly
    for sep, name in ((1.80, "hexagon217_sep180"), (2.54, "hexagon127"), (3.54, "hexagon61_sep354")):
        assert counts[Cell("hexagon", sep, 0.5).cell_id] == load_design(name).marker_count
    for c in cells:
        d = c.design()
        assert d.skin.thickness_mm == c.skin_mm and d.pattern.separation_mm == c.separation_mm
        assert d.pattern_radius_mm() + d.pattern.separation_mm / 2 <= d.gel.radius_mm


def test_sweep_is_resumable_and_tabulated(toy, tmp_path, monkeypatch):
    calls = []
    original = toy.run

    def counting(ctx):
        calls.append(ctx.base_design)
        return original(ctx)

    monkeypatch.setitem(reg._REGISTRY, "toy", reg.Experiment(**{**toy.__dict__, "run": counting}))
    cells = make_cells([0.5, 1.0], [2.54], ["hexagon", "square"])
    out = run_sweep("toy", cells, tmp_path, quick=True, workers=1, progress=False)
    assert len(calls) == 4 and all(r["status"] == "ok" for r in out["rows"])
    assert {(r["pattern"], r["skin_mm"]) for r in out["rows"]} == {(p, s) for p in ("hexagon", "square") for s in (0.5, 1.0)}
    by = {r["cell"]: r for r in out["rows"]}
    assert by[Cell("square", 2.54, 0.5).cell_id]["skin_mm"] == 0.5
    assert out["csv"].read_text().count("\n") == 5 and out["figure"].is_file()
    again = run_sweep("toy", cells + make_cells([1.5], [2.54], ["hexagon"]), tmp_path, quick=True, workers=1,
                      progress=False)
    assert len(calls) == 5 and len(again["rows"]) == 5  # only the new cell ran
    assert json.loads(again["json"].read_text())["units"]["skin_mm"] == "mm"


# ----- the registry walk -----------------------------------------------------------------------

EXPERIMENTS = reg.all_experiments()
THRESHOLDS = gate.load_thresholds()


def test_thresholds_file_names_only_registered_experiments_and_declared_metrics():
    assert THRESHOLDS and all(THRESHOLDS.values())        # the gate guards something
    for exp, table in THRESHOLDS.items():
        assert exp in EXPERIMENTS, f"thresholds.toml guards unknown experiment {exp!r}"
        for key, th in table.items():
            metric = th.metric
            assert metric in EXPERIMENTS[exp].metrics, f"thresholds.toml: {exp}.{metric} is not declared"
            if th.measured is not None:
                assert not th.violated_by(th.measured), f"{exp}.{key}: measured value violates its own bound"
            for v in th.spread or ():
                assert not th.violated_by(v), f"{exp}.{key}: a measured run violates its own bound"


def test_every_guarded_metric_has_both_tiers():
    """Every bound in the CI gate has a sanity tier (collapse) and a golden tier (regression), the golden one
    set from measurements under the file's own rule (checked by the loader)."""
    for exp, table in THRESHOLDS.items():
        for key, th in table.items():
            assert th.min is not None or th.max is not None, f"{exp}.{key}: no sanity tier"
            assert th.kind is not None and (th.golden_min is not None or th.golden_max is not None), \
                f"{exp}.{key}: no golden tier"


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_registered_experiment_invariants(name, tmp_path):
    exp = EXPERIMENTS[name]
    assert exp.description, f"{name}: run() needs a docstring (first line = description)"
    assert exp.metrics and all(isinstance(u, str) and u for u in exp.metrics.values()), f"{name}: declare units"
    assert "quick" in exp.tags or "full-only" in exp.tags
    for metric, pv in exp.paper.items():
        assert pv.unit == exp.metrics[metric], f"{name}.{metric}: paper unit differs from the metric's"
    # every upstream module has landed: an unavailable experiment is a broken install, not a skip
    assert exp.available(), f"{name}: required module(s) missing: {exp.missing_requirements()}"
    if "quick" in exp.tags:
        assert THRESHOLDS.get(name), f"{name}: its quick variant has no thresholds in benchmarks/thresholds.toml"
    if "cheap" not in exp.tags:
        return
    ctx = Context(out_dir=tmp_path, quick=True, seed=0, params=TINY_PARAMS.get(name, {}), progress=False)
    rec = res.execute(exp, ctx, catch=False)
    assert rec["status"] == "ok", rec["error"]
    guarded = {th.metric for th in THRESHOLDS.get(name, {}).values()}
    assert guarded <= set(rec["metrics"]), f"a quick run must report every guarded metric: {guarded - set(rec['metrics'])}"
    assert all(m["unit"] == exp.metrics[k] for k, m in rec["metrics"].items())
    for fig in rec["figures"]:
        assert (tmp_path / fig).stat().st_size > 1000


# Tiny settings for the cheap experiments' real runs in this test (kept in one place).
TINY_PARAMS: dict[str, dict] = {
    "latency": {"n_frames": 5},
    "identification": {"n_trials": 2},
}


# ----- resumes keyed by everything that determines a cell ---------------------------------------

def test_sweep_recomputes_a_cell_whenever_an_input_changed(toy, tmp_path, monkeypatch, capsys):
    from benchmarks import sweep as sweep_mod
    from pipeline.design import load_design, to_toml

    calls = []
    original = toy.run

    def counting(ctx):
        calls.append(dict(ctx.params))
        return original(ctx)

    monkeypatch.setitem(reg._REGISTRY, "toy", reg.Experiment(**{**toy.__dict__, "run": counting}))
    design = tmp_path / "base.toml"
    design.write_text(to_toml(load_design("hexagon127")))   # written out: every key in this one file
    monkeypatch.setitem(sweep_mod.BASE_DESIGN, "hexagon", str(design))
    cells = make_cells([0.5, 1.0], [2.54], ["hexagon"])
    out = tmp_path / "out"

    def sweep(**kw):
        return run_sweep("toy", cells, out, workers=1, progress=False, **{"quick": True, **kw})

    sweep(params={"n": 500})
    assert len(calls) == 2
    sweep(params={"n": 500})
    assert len(calls) == 2 and "reusing 2 of 2" in capsys.readouterr().err
    rows = sweep(params={"n": 600})["rows"]                  # a changed --param recomputes ...
    assert len(calls) == 4 and calls[-1] == {"n": 600}
    rec = json.loads((out / "cells" / cells[0].cell_id / "toy.json").read_text())
    assert rec["params"] == {"n": 600} and all(r["status"] == "ok" for r in rows)
    sweep(params={"n": 600}, seed=1)                          # ... so do the seed,
    sweep(params={"n": 600}, seed=1, quick=False)             # the quick flag,
    assert len(calls) == 8
    design.write_text(design.read_text().replace("youngs_modulus_mpa = 0.02", "youngs_modulus_mpa = 0.03"))
    sweep(params={"n": 600}, seed=1, quick=False)             # and the design file's content
    assert len(calls) == 10 and "reusing 0 of 2" in capsys.readouterr().err
    (out / "cells" / cells[1].cell_id / "toy.json").write_bytes(b"\x00{truncated")
    sweep(params={"n": 600}, seed=1, quick=False)             # a corrupt record is recomputed, not fatal
    assert len(calls) == 11 and "reusing 1 of 2" in capsys.readouterr().err
    assert not [p for p in out.rglob(".*.tmp")]


def test_sweep_key_follows_the_base_a_design_extends(toy, tmp_path, monkeypatch):
    """The resume key hashes the merged design: editing the base a sweep design extends changes every
    cell's key although the design file's own bytes are unchanged."""
    from benchmarks import sweep as sweep_mod
    from pipeline.design import design_path

    base = tmp_path / "module.toml"
    base.write_text(design_path("base/stereotactip_module").read_text())
    child = tmp_path / "hexagon.toml"
    child.write_text(design_path("hexagon127").read_text().replace('"base/stereotactip_module"', '"module.toml"'))
    monkeypatch.setitem(sweep_mod.BASE_DESIGN, "hexagon", str(child))
    cells = make_cells([0.5, 1.0], [2.54], ["hexagon"])

    def keys():
        return [sweep_mod.cell_key("toy", c, seed=0, quick=True, params={})[0] for c in cells]

    before, child_bytes = keys(), child.read_bytes()
    assert keys() == before
    base.write_text(base.read_text().replace("gel_n = 1.40", "gel_n = 1.41"))
    after = keys()
    assert child.read_bytes() == child_bytes and all(a != b for a, b in zip(after, before))
    assert cells[0].design().optics.gel_n == 1.41


def test_binary_thresholds_file_is_a_user_error(tmp_path):
    p = tmp_path / "t.toml"
    p.write_bytes(b"\xff\xfe[toy]\x00")
    with pytest.raises(res.ResultsError, match="thresholds file"):
        gate.load_thresholds(p)


def test_readme_gate_figures_are_written_from_the_records(toy, tmp_path, monkeypatch):
    """The README's gate figures are the benchmark's output: the block between the markers is rewritten from
    the quick records, the rest of the file is kept, a rerun changes nothing, a missing block is an error."""
    from benchmarks.readme_blocks import README_BEGIN, README_END, update_readme

    out = tmp_path / "run"
    res.write_record(res.execute(toy, Context(out_dir=out, quick=True, progress=False)), out)
    th = _thresholds_file(tmp_path, """
[toy]
mean = { min = 0.1, max = 0.9, golden_min = 0.4, golden_max = 0.6, kind = "deterministic", measured = 0.5, why = "x" }
skin_mm = { max = 0.5, why = "violated on purpose" }
""")
    monkeypatch.setattr(gate, "thresholds_path", lambda: th)
    readme = tmp_path / "README.md"
    readme.write_text(f"# Title\n\nbefore\n\n{README_BEGIN}\nold figures\n{README_END}\n\nafter\n")
    update_readme(readme, out)
    text = readme.read_text()
    assert text.startswith("# Title\n\nbefore\n\n") and text.endswith("\n\nafter\n") and "old figures" not in text
    rows = {line.split("|")[2].strip(): line for line in text.splitlines() if line.startswith("| toy |")}
    assert set(rows) == {"mean", "skin_mm"}
    assert "0.4 – 0.6" in rows["mean"] and "0.1 – 0.9" in rows["mean"] and "passes" in rows["mean"]
    assert "**fails**" in rows["skin_mm"] and "≤ 0.5" in rows["skin_mm"]
    update_readme(readme, out)
    assert readme.read_text() == text
    readme.write_text("# no block\n")
    with pytest.raises(res.ResultsError, match="gate-figures block"):
        update_readme(readme, out)
    full = tmp_path / "full"
    res.write_record(res.execute(toy, Context(out_dir=full, quick=False, progress=False)), full)
    readme.write_text(f"{README_BEGIN}\n{README_END}\n")
    with pytest.raises(res.ResultsError, match="no quick records"):
        update_readme(readme, full)


def test_readme_shows_every_metric_the_ci_gate_guards():
    """The README's gate-figures block (written by `stereotactip report DIR --readme README.md` from the CI
    run) lists every metric the CI gate (estimated mode) guards: a changed thresholds file needs a rerun."""
    from benchmarks.readme_blocks import README_BEGIN, README_END

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    assert text.count(README_BEGIN) == 1 and text.count(README_END) == 1
    block = text.split(README_BEGIN, 1)[1].split(README_END, 1)[0]
    shown = {tuple(c.strip() for c in line.split("|")[1:3]) for line in block.splitlines() if line.startswith("| ")}
    for exp, table in THRESHOLDS.items():
        for th in table.values():
            if th.mode in (None, "estimated"):
                name = th.metric if th.mode is None else f"{th.metric} ({th.mode})"
                assert (exp, name) in shown, f"README gate figures lack {exp}.{name}: rerun the report with --readme"


def test_readme_headline_blocks_match_the_records_they_were_written_from():
    """The README's headline tables (the quick run's gate figures and experiments, the pipeline's and the
    renderer's accuracy and latency, twin speed, identification coverage, tracking, oracle vs estimated, each error source alone) are generated blocks: each is written again
    from the records it names (kept in docs/records/) and must equal the README's text, so a hand edit of a
    figure, or a record replaced without rerunning `stereotactip report DIR --readme README.md --block NAME`,
    fails here. A block may stand in README.md or in a document under docs/ (the file its marker names), once."""
    from benchmarks.readme_blocks import BLOCKS, load_block_records, readme_blocks, render_block

    root = Path(__file__).resolve().parents[1]
    blocks, where_is = {}, {}
    for doc in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        text = doc.read_text(encoding="utf-8")
        for name, block in readme_blocks(text).items():
            rel = doc.relative_to(root).as_posix()
            assert name not in blocks and text.count(f"<!-- report:{name}:begin") == 1, (
                f"README block {name} stands more than once ({where_is.get(name, rel)}, {rel})")
            assert rel == BLOCKS[name].doc, f"README block {name} stands in {rel}, its marker names {BLOCKS[name].doc}"
            blocks[name], where_is[name] = block, rel
    assert {"gate-figures", "twin-speed", "identification-coverage", "tracking-identity",
            "quick-experiments", "full-suite", "oracle-vs-estimated", "error-sources", "physics-checks",
            "tactip-validation", "pipeline-accuracy", "renderer-accuracy", "identification-summary"} <= set(blocks)
    for name, text in blocks.items():
        if name == "gate-figures":      # the quick run's gate figures, from the same kept records
            source, *other = re.findall(r"figures from `([^`]+)`", text)
        else:
            source, *other = re.findall(r" records? in `([^`]+)`", text)     # a block of two runs names both
        for where in (source, *other):
            assert where.startswith("docs/records/"), f"README block {name}: {where} is not kept in docs/records/"
        assert len(other) == BLOCKS[name].against, f"README block {name} names {1 + len(other)} runs"
        against = [(d, load_block_records(root / d)) for d in other]
        command = source + "".join(f" --against {d}" for d in other)
        assert render_block(name, load_block_records(root / source), source, against) == text, (
            f"README block {name} differs from its records: rerun `stereotactip report {command} "
            f"--readme {where_is[name]} --block {name}`")


def test_readme_block_is_written_from_its_experiment_only(tmp_path):
    """`report DIR --readme README.md --block twin-speed` rewrites that block alone from DIR's `twin` record
    (the other blocks and the prose are kept); a directory without that record, or a README without the
    block, is a clear error."""
    from benchmarks.readme_blocks import begin_marker, end_marker, update_readme

    root = Path(__file__).resolve().parents[1]
    run = tmp_path / "run"
    run.mkdir()
    (run / "twin.json").write_bytes((root / "docs/records/twin-speed/twin.json").read_bytes())
    readme = tmp_path / "README.md"
    other = f"{begin_marker('identification-coverage')}\nkept\n{end_marker('identification-coverage')}"
    readme.write_text(f"# T\n\n{begin_marker('twin-speed')}\nold\n{end_marker('twin-speed')}\n\n{other}\n")
    assert main(["report", str(run), "--readme", str(readme), "--block", "twin-speed"]) == 0
    text = readme.read_text()
    assert "old" not in text and other in text and text.startswith("# T\n\n")
    press_s = json.loads((run / "twin.json").read_text())["metrics"]["press_s_median"]["value"]
    assert "| 5 mm press to equilibrium" in text and f"{press_s:.3g} s median" in text
    with pytest.raises(res.ResultsError, match="no 'identification' record"):
        update_readme(readme, run, ("identification-coverage",))
    with pytest.raises(res.ResultsError, match="needs exactly one gate-figures block"):
        update_readme(readme, run)


def test_full_suite_block_is_written_from_full_records_only(tmp_path):
    """The full-suite block takes a full run's records (quick ones are refused, and a quick run's block leaves
    full records out) and gives each experiment its wall time from its record, and the run's total."""
    from benchmarks.readme_blocks import render_block

    root = Path(__file__).resolve().parents[1]
    quick = res.load_records(root / "docs/records/quick-experiments")
    with pytest.raises(res.ResultsError, match="no full records"):
        render_block("full-suite", quick, "q")
    full = {}
    for k, (name, rec) in enumerate(sorted(quick.items())[:3]):
        full[name] = {**rec, "quick": False, "wall_time_s": 30.0 + 100.0 * k}
    text = render_block("full-suite", full, "f")
    assert "| experiment | designs | wall time | invalid twin cells |" in text
    rows = [line for line in text.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert [r.split(" | ")[0][2:] for r in rows] == sorted(full)
    assert [r.split(" | ")[2] for r in rows] == ["30 s", "2 min 10 s", "3 min 50 s"]
    assert "6 min 30 s of experiment wall time in all" in text
    with pytest.raises(res.ResultsError, match="no quick records"):
        render_block("quick-experiments", full, "f")


def test_readme_block_of_two_runs_needs_the_other_run(tmp_path):
    """The oracle-vs-estimated block compares two directories: written without `--against` it is a clear
    error; a run against itself shows its chosen figures with no difference, under each run's calibration."""
    from benchmarks.readme_blocks import (CALIBRATION_METRICS, begin_marker, end_marker, render_block,
                                          update_readme)

    root = Path(__file__).resolve().parents[1]
    source = "docs/records/quick-experiments"
    records = res.load_records(root / source)
    with pytest.raises(res.ResultsError, match="--against DIR2"):
        render_block("oracle-vs-estimated", records, source)
    text = render_block("oracle-vs-estimated", records, source, [(source, records)])
    rows = [line.split("|")[1:-1] for line in text.splitlines() if line.startswith("| ") and "**" not in line]
    metrics = {(c[0].strip(), c[1].strip()) for c in rows[2:]}
    assert metrics <= {(e, m) for e, ms in CALIBRATION_METRICS.items() for m in ms} and len(metrics) > 10
    assert {c[4].strip() for c in rows[2:]} <= {"0", "—"}
    readme = tmp_path / "README.md"
    readme.write_text(f"{begin_marker('oracle-vs-estimated')}\n{end_marker('oracle-vs-estimated')}\n")
    with pytest.raises(res.ResultsError, match="compares two runs"):
        update_readme(readme, root / source, ("oracle-vs-estimated",))
    run = tmp_path / "run"         # the report pages are written beside the records: a copy keeps docs/ clean
    run.mkdir()
    for name in ("patterns", "refraction"):
        (run / f"{name}.json").write_bytes((root / source / f"{name}.json").read_bytes())
    assert main(["report", str(run), "--against", str(run), "--readme", str(readme),
                 "--block", "oracle-vs-estimated"]) == 0
    assert "| **patterns** | | estimated quick | estimated quick | | |" in readme.read_text()


def test_error_sources_block_is_written_from_three_ablation_runs(tmp_path):
    """The error-sources block takes DIR and two `--against` directories, one column per run in that order,
    labelled by the error source each run kept; a figure changed in one run's record shows in that run's column
    (the README cannot keep a figure its records do not hold); fewer runs, or an oracle run, are clear errors.
    `report` writes one side-by-side table per `--against` directory."""
    from benchmarks.readme_blocks import begin_marker, end_marker, render_block

    root = Path(__file__).resolve().parents[1]
    runs = {}
    for src in ("calibration", "index", "thickness"):
        runs[src] = tmp_path / src          # the report pages are written beside the records: copies keep docs/ clean
        runs[src].mkdir()
        for name in ("patterns", "gaussian"):
            (runs[src] / f"{name}.json").write_bytes(
                (root / f"docs/records/ablation-{src}/{name}.json").read_bytes())
    rec = json.loads((runs["thickness"] / "patterns.json").read_text())
    rec["metrics"]["localisation_rms_mm_hexagon"]["value"] = 9.876
    (runs["thickness"] / "patterns.json").write_text(json.dumps(rec))
    recs = {k: res.load_records(d) for k, d in runs.items()}
    text = render_block("error-sources", recs["index"], "i", [("t", recs["thickness"]), ("c", recs["calibration"])])
    lines = text.splitlines()
    assert "| metric (quick) | index only | thickness only | calibration only |" in lines
    row = next(line for line in lines if line.startswith("| patterns: hexagon127 (mm) |"))
    assert [c.strip() for c in row.split("|")[1:-1]][2] == "9.876"
    assert sum(line.startswith("| gaussian: hexagon127_skin") for line in lines) == 2
    with pytest.raises(res.ResultsError, match="compares three runs"):
        render_block("error-sources", recs["index"], "i", [("t", recs["thickness"])])
    oracle = res.load_records(root / "docs/records/oracle-vs-estimated")
    with pytest.raises(res.ResultsError, match="calibration oracle"):
        render_block("error-sources", oracle, "o", [("t", recs["thickness"]), ("c", recs["calibration"])])
    readme = tmp_path / "README.md"
    readme.write_text(f"{begin_marker('error-sources')}\n{end_marker('error-sources')}\n")
    assert main(["report", str(runs["calibration"]), "--against", str(runs["index"]), "--against",
                 str(runs["thickness"]), "--readme", str(readme), "--block", "error-sources"]) == 0
    assert "| metric (quick) | calibration only | index only | thickness only |" in readme.read_text()
    assert (runs["calibration"] / "report.md").read_text().count("## Side by side") == 2


def _physics_record(conv_diffs: tuple[float, ...], shallow_centre_mm: float) -> dict:
    """A small synthetic ``bench physics`` record: two depths, uniform gel on two meshes (one with a second ν),
    the design on two meshes, and the convergence resolutions (coarsest first) with ``conv_diffs`` vs the finest."""
    mesh = {"fine_mm": 1.5, "core_mm": None, "core_half_mm": 3.0, "gel_levels_mm": [1.5, 4.0],
            "mirrored_split": False, "face_contact": False, "volumetric": "element"}
    nodal, axis = {**mesh, "volumetric": "nodal"}, {**mesh, "core_mm": 0.5, "mirrored_split": True,
                                                    "face_contact": True}
    cases = [("uniform", 0.49, True, mesh, (1.04, 1.10)), ("uniform045", 0.45, True, mesh, (1.3, 1.4)),
             ("uniform_nodal", 0.49, True, nodal, (1.1, 1.2)),
             ("design", None, False, axis, (4.0, 5.0)), ("design_default", None, False, mesh, (4.0, 5.0))]
    rows = []
    for tag, nu, _, _, ratios in cases:
        for depth, ratio in zip((1.0, 3.0), ratios):
            centre = shallow_centre_mm if tag == "design_default" and depth == 1.0 else 0.001
            rows.append({"case": tag, "nu": nu or 0.49, "depth_mm": depth, "force_n": ratio * depth, "theory_n": depth,
                         "ratio": ratio, "chi": 0.1 * depth, "contact_radius_mm": math.sqrt(10 * depth),
                         "hertz_radius_mm": math.sqrt(10 * depth), "penetration_max_mm": 0.01, "valid": True,
                         "centre_lateral_mm": centre, "mirror_disagreement_mm": 0.004})
    fines = (2.0, 1.5, 1.0)[2 - len(conv_diffs):]          # the production mesh (1.5 mm) and the finest among them
    conv = [{"fine_mm": f, "gel_levels_mm": [1.5, 4.0], "depth_mm": 2.0, "force_n": 2.0 + d,
             "penetration_max_mm": 0.05, "marker_diff_vs_finest_mm": d} for f, d in zip(fines, (*conv_diffs, 0.0))]
    return {"experiment": "physics", "commit": "abc", "quick": False, "seed": 0, "metrics": {},
            "design": {"name": "d", "skin": {"thickness_mm": 1.0, "youngs_modulus_mpa": 1.14, "material": "A"},
                       "optics": {"gel_thickness_mm": 10.0},
                       "gel": {"youngs_modulus_mpa": 0.02, "poisson_ratio": 0.49}},
            "tables": {"force_depth": rows, "convergence": conv,
                       "cases": [{"case": t, "nu": nu or 0.49, "uniform": u, **m} for t, nu, u, m, _ in cases]}}


def test_physics_checks_block_decides_each_verdict_from_the_record():
    """The physics-checks block has one row per mesh of the uniform gel (the other ν beside it) and of the design,
    each verdict decided at every depth of the record; convergence is met when the differences shrink and the
    production mesh is within the tolerance of the finest; a record without its tables is a clear error."""
    from benchmarks.readme_blocks import render_block

    def verdicts(rec) -> dict[str, str]:
        text = render_block("physics-checks", {"physics": rec}, "docs/records/x")
        rows = [[c.strip() for c in line.split("|")[1:-1]] for line in text.splitlines()[4:-2]]
        return {r[0].split(":")[0].split(" (")[0]: (r[2], r[3]) for r in rows}

    v = verdicts(_physics_record((0.05, 0.02), shallow_centre_mm=0.03))
    uniform = next(k for k in v if k.startswith("uniform gel"))
    assert v[uniform] == ("FE / theory 1.04–1.10 (median 1.07) at ν = 0.49; 1.30–1.40 at ν = 0.45", "met")
    assert v["the same on the 1.5 mm mesh, one split direction, nodal volumetric stiffness, gel levels 1.5, 4 mm"][1] \
        == "**not met**"                                    # 1.2 at 3 mm is beyond 15 %
    sym = [k for k in v if k.startswith("symmetric press") or k.startswith("the same on the 1.5 mm mesh, one split "
                                                                           "direction, gel levels")]
    assert [v[k][1] for k in sym] == ["met", "**not met**"]   # the default mesh's centre marker at 1 mm only
    assert v["mesh convergence, the design at 2 mm"] == (
        "markers 0.05 / 0.02 mm, force +2 % / +1 %, face-level penetration 0.05 / 0.05 / 0.05 mm",
        "shrinking, converged")
    assert verdicts(_physics_record((0.02, 0.05), 0.0))["mesh convergence, the design at 2 mm"][1] == \
        "**not shrinking**, **not converged**"
    split = _physics_record((0.05, 0.02), 0.0)                # a record that splits markers into pin bases and tilt
    for c, base, tilt in zip(split["tables"]["convergence"], (0.045, 0.018, 0.0), (0.02, 0.011, 0.0)):
        c.update(pin_base_diff_vs_finest_mm=base, pin_tilt_diff_vs_finest_mm=tilt)
    assert verdicts(split)["mesh convergence, the design at 2 mm"][0] == (
        "markers 0.05 / 0.02 mm (pin bases 0.045 / 0.018 mm, pin tilt × height 0.02 / 0.011 mm), force +2 % / +1 %, "
        "face-level penetration 0.05 / 0.05 / 0.05 mm")
    assert verdicts(_physics_record((0.05,), 0.0))["mesh convergence, the design at 2 mm"][1] == \
        "**not converged**"                                # production only, vs the finest: nothing to shrink
    ref = _physics_record((0.05, 0.02), 0.0)                  # with the locking-free reference family
    for c, d in zip(ref["tables"]["convergence"], (0.14, 0.12, 0.11)):
        c["marker_diff_vs_reference_mm"] = d
    ref["tables"]["reference_family"] = [
        {"cells_mm": cm, "skin_layers": 2, "gel_levels_mm": [0.75, 1.5], "dofs": n, "force_n": f, "seconds": t,
         "marker_diff_vs_finest_mm": d}
        for cm, n, f, t, d in ((1.5, 10680, 1.39, 26.0, 0.1), (1.0, 25752, 1.32, 70.0, 0.04),
                               (0.75, 50895, 1.33, 209.0, 0.0))]
    row = verdicts(ref)["the same against a locking-free refinement"]
    assert row == ("production 0.12 mm, the element-wise finest (1 mm) 0.11 mm; force 2.02 N against 1.33 N; the "
                   "family 0.1 / 0.04 mm from its finest (50,895 DOFs, 209 s a press)", "**not met**")
    assert "the same against a locking-free refinement" not in verdicts(_physics_record((0.05, 0.02), 0.0))
    ref["tables"]["reference_meshes"] = [      # the contact meshes the experiments press, against the same finest
        {"mesh": m, "dofs": n, "marker_diff_vs_reference_mm": d, "marker_rms_vs_reference_mm": r}
        for m, n, d, r in (("default", 3324, 0.14, 0.094), ("axis", 7356, 0.083, 0.044), ("sine", 5340, 0.145, 0.09))]
    assert verdicts(ref)["the same against a locking-free refinement"][0].endswith(
        "a press); the contact meshes axis 0.083 mm (RMS 0.044 mm, 7,356 DOFs), sine 0.145 mm (RMS 0.09 mm, 5,340 DOFs)")
    rec = _physics_record((0.05, 0.02), 0.0)
    del rec["tables"]["cases"]
    with pytest.raises(res.ResultsError, match="no force_depth and cases tables"):
        render_block("physics-checks", {"physics": rec}, "docs/records/x")


def _validate_summary(twin: float = 2.17, stat: float = 4.91, ridge: float = 1.13, contrast: float = 116.0) -> dict:
    """A small synthetic ``stereotactip validate`` summary (the keys the tactip-validation block reads), its goals
    decided by validate's own rule."""
    from benchmarks.tactip_validate import _goals

    def stat_row(real, tw):
        return {"real": real, "twin": tw, "relative_difference": abs(tw - real) / real}

    summary = {"design": "tactip331_fitted", "commit": "0123456789abcdef", "frames": 40, "train": 30, "held_out": 10,
            "held_out_frames": [f"tactip331_tap_{k}.png" for k in range(4, 44, 4)], "reference": "tactip331_tap_5.png",
            "held_out_rms_px": {"twin": 2.3, "twin_truth": 2.25, "static": 5.0, "ridge": 1.2, "displacement_twin": 1.98},
            "held_out_rms_px_common_markers": {"twin": twin, "twin_truth": 2.18, "static": stat, "ridge": ridge},
            "fitted_position_parameters": {"twin": 17, "static": 662, "ridge": 6620},
            "fitted_position_parameter_groups": {"pin spacing": 1, "camera": 10, "tap/skin": 4, "pin rotation": 1,
                                                 "tilt pivot": 1},
            "image_stats_median": {"count": stat_row(330, 331), "radius_px": stat_row(4.87, 4.93),
                                   "contrast": stat_row(contrast, 117.0), "spacing_px": stat_row(16.1, 16.3),
                                   "background": stat_row(24.0, 24.0), "noise": stat_row(1.26, 1.28)},
            "per_frame": [], "seconds": 60.0}
    summary["goals"] = _goals(summary["held_out_rms_px_common_markers"], summary["image_stats_median"])
    return summary


def test_pipeline_and_renderer_blocks_decide_each_verdict_from_the_record():
    """The Pipeline and renderer tables read each figure of the kept accuracy record against the tolerance the
    accuracy benchmark derives: a figure beyond it turns that row's verdict to "not met" and leaves the others; a
    record without real frames says so; the Pipeline table needs the latency record beside it."""
    import copy

    from benchmarks.experiments.accuracy import E2E_TOL_MM, TRACE_CENTROID_TOL_PX
    from benchmarks.readme_blocks import load_block_records, render_block

    kept = load_block_records(Path(__file__).resolve().parents[1] / "docs" / "records" / "pipeline-accuracy")

    def rows(name, records) -> dict[str, str]:
        text = render_block(name, records, "docs/records/x")
        cells = [[c.strip() for c in line.split("|")[1:-1]] for line in text.splitlines()
                 if line.startswith("| ") and not line.startswith("| ---")]
        return {r[0].split(",")[0].split(" (")[0]: r[2] for r in cells[1:]}

    ok = rows("pipeline-accuracy", kept)
    assert all(v.endswith("**met**") for k, v in ok.items() if not k.startswith("latency"))
    worse = copy.deepcopy(kept)
    worse["accuracy"]["metrics"]["e2e_max_mm"]["value"] = 1.5 * E2E_TOL_MM
    worse["accuracy"]["metrics"]["render_trace_offset_max_px"]["value"] = 1.5 * TRACE_CENTROID_TOL_PX
    bad = rows("pipeline-accuracy", worse)
    assert [k for k in bad if bad[k] != ok[k]] == ["end-to-end 3-D error"] and bad["end-to-end 3-D error"].endswith("**not met**")
    assert rows("renderer-accuracy", worse)["per-vertex refraction vs a per-pixel ray-traced reference"].endswith("**not met**")
    for m in ("real_frames", "real_found_min", "real_found_max", "real_in_glare"):
        del worse["accuracy"]["metrics"][m]
    assert "not measured" in render_block("pipeline-accuracy", worse, "docs/records/x")
    with pytest.raises(res.ResultsError, match="latency"):
        render_block("pipeline-accuracy", {"accuracy": kept["accuracy"]}, "docs/records/x")


def test_identification_summary_names_the_worst_pattern_and_each_goal_verdict():
    """The certainty rule's headline counts wrong ids over every trial and gives each condition's worst pattern;
    one pattern under a coverage goal, or one wrong id anywhere, turns that verdict to "not met"."""
    import copy

    from benchmarks.readme_blocks import load_block_records, render_block

    kept = load_block_records(Path(__file__).resolve().parents[1] / "docs" / "records" / "identification-coverage")
    text = render_block("identification-summary", kept, "docs/records/x")
    trials = sum(r["trials"] for r in kept["identification"]["tables"]["conditions"])   # every condition's trials
    assert trials >= 55_000
    assert f"**0 wrong ids** in {trials:,} seeded trials (goal: zero — **met**)" in text
    assert "(goal ≥ 95 %: **met**)" in text and "(goal ≥ 99 %: **met**)" in text
    worse = copy.deepcopy(kept)
    rows = worse["identification"]["tables"]["conditions"]
    cell = next(r for r in rows if r["condition"] == "defects_10" and r["design"] == "hexagon127")
    cell["coverage_mean"] = 0.94
    next(r for r in rows if r["condition"] == "rotation_30")["wrong_ids"] = 1
    text = render_block("identification-summary", worse, "docs/records/x")
    assert f"**1 wrong ids** in {trials:,} seeded trials (goal: zero — **not met**)" in text
    assert "10 % + 10 % 94.00 % (hex 127) (goal ≥ 95 %: **not met**)" in text
    assert "these test that no id is wrong: 1)" in text


def test_tactip_validation_block_is_written_from_a_validate_summary(tmp_path):
    """The tactip-validation block reads validate's summary.json as it stands: the held-out RMS table with the
    fitted parameter counts, each goal's verdict as validate decided it (twin ≤ 0.5× static, ≤ 1.5× ridge, the
    image statistics within 10 %); `report DIR --readme README.md --block tactip-validation` writes it from a folder that
    holds only the summary (no report pages there); a folder without one is a clear error."""
    from benchmarks.readme_blocks import begin_marker, end_marker, render_block

    text = render_block("tactip-validation", {"summary.json": _validate_summary()}, "docs/records/x")
    lines = text.splitlines()
    assert lines[2].startswith("TacTip twin vs real frames from the `validate` summary record in `docs/records/x` "
                               "(commit 0123456789, design tactip331_fitted, 40 labelled frames: 30 train / 10 held "
                               "out (tactip331_tap_4, tactip331_tap_8, …, tactip331_tap_40); reference tactip331_tap_5)")
    rows = {r[0]: r[1:] for r in ([c.strip() for c in line.split("|")[1:-1]] for line in lines if line.startswith("| "))}
    assert rows["twin, projected pin tips"] == ["17 (pin spacing, 10 camera, 4 tap/skin, pin rotation, tilt pivot)",
                                                "2.18", "2.25"]
    assert rows["twin, rendered → detected → identified"] == ["same", "2.17", "2.30"]
    assert rows["(a) static: training mean per marker"] == ["662", "4.91", "5.00"]
    assert rows["(b) ridge on [d, tx, ty, products, squares]"] == ["6620", "1.13", "1.20"]
    assert ("Goal ≤ 0.5× static **met**, ≤ 1.5× ridge **not met**: through render → detect → identify the twin is "
            "0.44× the static baseline and 1.92× the ridge") in text
    assert "displacement error (against the reference tap) is 1.98 px." in text
    assert ("count 331 / 330, radius 4.93 / 4.87 px, contrast 117 / 116, spacing 16.3 / 16.1 px, background 24 / 24, "
            "noise 1.28 / 1.26 (all within 1.6 %); goal count, radius, contrast, spacing within 10 % **met**.") in text
    other = render_block("tactip-validation", {"summary.json": _validate_summary(twin=1.6, contrast=140.0)}, "x")
    assert "Goal ≤ 0.5× static **met**, ≤ 1.5× ridge **met**" in other and "within 10 % **not met**" in other
    assert "Goal ≤ 0.5× static **not met**" in render_block(
        "tactip-validation", {"summary.json": _validate_summary(stat=4.0)}, "x")
    run = tmp_path / "val"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps(_validate_summary()))
    readme = tmp_path / "README.md"
    readme.write_text(f"# T\n\n{begin_marker('tactip-validation')}\nold\n{end_marker('tactip-validation')}\n")
    assert main(["report", str(run), "--readme", str(readme), "--block", "tactip-validation"]) == 0
    assert "old" not in readme.read_text() and "| (a) static: training mean per marker | 662 | 4.91 |" in readme.read_text()
    assert sorted(p.name for p in run.iterdir()) == ["summary.json"]
    (run / "summary.json").unlink()
    assert main(["report", str(run), "--readme", str(readme), "--block", "tactip-validation"]) == 2
    with pytest.raises(res.ResultsError, match="no summary.json"):
        render_block("tactip-validation", {}, "x")
    with pytest.raises(res.ResultsError, match="not a `stereotactip validate` summary"):
        render_block("tactip-validation", {"summary.json": {"frames": 2}}, "x")


def test_report_against_another_run_puts_the_calibration_modes_side_by_side(toy, tmp_path, monkeypatch):
    """`report DIR --against DIR2`: the experiments both directories hold, metric by metric under each run's
    calibration mode, with the difference; a directory without records is a clear error."""
    oracle, estimated = tmp_path / "oracle", tmp_path / "estimated"
    res.write_record(res.execute(toy, Context(out_dir=oracle, quick=True, progress=False)), oracle)
    rec = res.execute(toy, Context(out_dir=estimated, quick=True, progress=False, calibration="estimated",
                                   overrides={"skin.thickness_mm": 1.5}))
    res.write_record(rec, estimated)
    th = _thresholds_file(tmp_path, "[toy]\nmean = { min = 0.0, why = 'x' }\n")
    monkeypatch.setattr(gate, "thresholds_path", lambda: th)
    assert main(["report", str(oracle), "--against", str(estimated)]) == 0
    text = (oracle / "report.md").read_text()
    assert "## Side by side" in text and "| **toy** | | oracle quick | estimated quick |" in text
    row = next(line for line in text.splitlines() if line.startswith("| toy | skin_mm |"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[2:6] == ["1", "1.5", "0.5", "mm"]
    (tmp_path / "empty").mkdir()
    assert main(["report", str(oracle), "--against", str(tmp_path / "empty")]) == 2


def test_offered_meshes_are_measured_against_the_reference_markers():
    """Each named mesh the twin offers is pressed once (the default reuses the convergence study's production
    press) and its markers' largest and RMS distance from the reference family's finest are recorded."""
    from types import SimpleNamespace

    from benchmarks.experiments.physics_reference import offered_meshes
    from twin.physics import AXIS_CONTACT_MESH, NAMED_MESHES, SINE_CONTACT_MESH, MeshSpec

    assert (NAMED_MESHES["default"], NAMED_MESHES["axis"], NAMED_MESHES["sine"]) == (MeshSpec(), AXIS_CONTACT_MESH,
                                                                                     SINE_CONTACT_MESH)
    finest = {"markers": np.zeros((4, 3))}
    shift = {AXIS_CONTACT_MESH: 0.1, SINE_CONTACT_MESH: 0.3}
    pressed = []

    def press(design, depths, spec):
        pressed.append(spec)
        markers = np.zeros((4, 3))
        markers[0, 0] = shift[spec]                       # one marker of four off by the shift
        truth = SimpleNamespace(marker_xyz_mm=markers, validity={"penetration_max_mm": 0.01})
        return [(depths[0], 1.5, truth, None, None)], 2.0, SimpleNamespace(model=SimpleNamespace(nv=99))

    prod = {"dofs": 10, "force_n": 2.0, "markers": np.full((4, 3), 0.2) * [1, 0, 0], "seconds": 1.0,
            "penetration_max_mm": 0.0}
    bar = SimpleNamespace(update=lambda: None)
    rows = offered_meshes(None, ("axis", "sine"), 2.0, press, bar, prod, finest)
    assert pressed == [AXIS_CONTACT_MESH, SINE_CONTACT_MESH]
    assert [r["mesh"] for r in rows] == ["default", "axis", "sine"]
    assert [r["marker_diff_vs_reference_mm"] for r in rows] == pytest.approx([0.2, 0.1, 0.3])
    assert [r["marker_rms_vs_reference_mm"] for r in rows] == pytest.approx([0.2, 0.05, 0.15])
    assert "markers" in prod and all("markers" not in r for r in rows)


def test_the_physics_reference_job_presses_an_elastic_flex():
    """The reference a press is timed against is the kind of job a press is: one 3-D elastic flex, its base
    pinned, pressed by a sphere through contacts, on the discrete integrator and the CG solver, and it
    moves the flex (the sphere's 1.5 mm step reaches into the grid's top vertices)."""
    import mujoco as mj

    from benchmarks import twin_bench

    ms = twin_bench.physics_reference_ms(repeats=2)
    assert 0 < ms < 60_000
    model, data = twin_bench._PHYSICS_REFERENCE
    assert model.nflex == 1 and model.flex_dim[0] == 3
    assert model.opt.integrator == mj.mjtIntegrator.mjINT_DISCRETE and model.opt.solver == mj.mjtSolver.mjSOL_CG
    assert data.ncon > 0
    x, y, z = data.flexvert_xpos.T
    under = np.flatnonzero(np.hypot(x, y) < 1e-6)
    assert z[under].max() < 0.007        # the top face's centre (rest z 7.5 mm) pressed in by ~1.5 mm
