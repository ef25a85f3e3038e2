"""Benchmarks subcommands of the ``stereotactip`` CLI: ``bench``, ``sweep``, ``report``.

::

    stereotactip bench NAME[,NAME...]|all|list [--quick] [--check] [--seed S] --out DIR [--param k=v] [--set key=v]
                       [--calibration oracle|estimated] [--error-sources calibration,index,thickness]
    stereotactip sweep --experiment NAME --skin 0.5,1.0,1.5 --separation 1.80,2.54,3.54
                       --pattern hexagon,square,circular [--quick] --out DIR [--workers N | --cluster ADDRESS]
    stereotactip report DIR [--against DIR2]... [--readme README.md [--block NAME]...]

Exit status of ``bench``: 0 when every experiment ran (and, with ``--check``, every guarded
quick metric is within ``benchmarks/thresholds.toml``), 1 on an experiment error or a regression.
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path
from typing import Any

from pipeline.errors import UserError


class OptionError(UserError, ValueError):
    """A command-line option value is malformed."""


def _key_values(items: list[str] | None, option: str) -> dict[str, Any]:
    """``["a=1", "b=x"]`` → ``{"a": 1, "b": "x"}`` (values parsed as Python literals when possible)."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise OptionError(f"{option} {item!r}: expected KEY=VALUE")
        try:
            out[key.strip()] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            out[key.strip()] = value
    return out


def _bench(args: argparse.Namespace) -> int:
    from benchmarks.registry import Context, all_experiments, get
    from benchmarks.results import execute
    from benchmarks.thresholds import check, load_thresholds

    exps = all_experiments()
    if args.name == "list":
        for name, e in exps.items():
            missing = e.missing_requirements()
            state = "ready" if not missing else "unavailable (needs " + ", ".join(missing) + ")"
            print(f"{name:20s} [{', '.join(e.tags)}] {state} — {e.description}")
        return 0
    if args.out is None:
        raise OptionError("bench: --out DIR is required")
    # `all --quick` is the CI set: experiments without a quick variant (tag full-only) run in full runs only
    names = [n for n, e in exps.items() if not (args.quick and "full-only" in e.tags)] if args.name == "all" \
        else list(dict.fromkeys(get(n.strip()).name for n in args.name.split(",") if n.strip()))
    if not names:
        raise OptionError(f"bench {args.name!r}: no experiment named")
    overrides = _key_values(args.set, "--set")
    if overrides:  # validate once, before any long run
        from pipeline.design import DEFAULT_DESIGN, load_design

        load_design(DEFAULT_DESIGN).with_overrides(overrides)
    params = _key_values(args.param, "--param")
    sources = None
    if args.error_sources is not None:
        from benchmarks.estimated import parse_sources

        if args.calibration != "estimated":
            raise OptionError("bench --error-sources: only with --calibration estimated")
        sources = parse_sources(args.error_sources)
    out = Path(args.out)
    records = {}
    t0 = time.perf_counter()
    engine = _engine(args)
    for name in names:
        ctx = Context(out_dir=out, quick=args.quick, seed=args.seed, overrides=overrides, params=params,
                      progress=not args.no_progress, engine=engine, calibration=args.calibration,
                      error_sources=sources)
        print(f"[bench] {name} ({args.calibration} calibration) ...", file=sys.stderr, flush=True)
        rec = execute(exps[name], ctx)
        records[name] = rec
        line = f"[bench] {name}: {rec['status']} in {rec['wall_time_s']:.1f} s"
        if rec["status"] != "ok":
            line += f" — {(rec.get('error') or '').strip().splitlines()[0] if rec.get('error') else ''}"
        print(line, file=sys.stderr, flush=True)
        for metric, m in rec["metrics"].items():
            print(f"    {metric:34s} {m['value'] if m['value'] is not None else 'nan':>12} {m['unit']}")
    if engine is not None:
        engine.close()
    print(f"[bench] {len(names)} experiment(s) in {time.perf_counter() - t0:.1f} s → {out}", file=sys.stderr)
    status = 0
    errors = [n for n, r in records.items() if r["status"] == "error"]
    if errors:
        print(f"[bench] error in: {', '.join(errors)}", file=sys.stderr)
        status = 1
    if args.check:
        if not args.quick:
            raise OptionError("bench --check: thresholds guard the --quick variant; add --quick")
        thresholds = load_thresholds()
        violations = check(records, thresholds, experiments=names)
        for v in violations:
            print(str(v))
        other_mode = sorted({f"{exp}.{th.mode}" for exp in names if exp in records for th in thresholds.get(exp, {}).values()
                             if th.mode is not None and th.mode != args.calibration})
        if other_mode:
            print(f"[bench] check: the bounds of {', '.join(other_mode)} apply to --calibration "
                  f"{'/'.join(sorted({m.split('.')[-1] for m in other_mode}))} runs only and were not applied to this "
                  f"{args.calibration} run", file=sys.stderr)
        if violations:
            status = 1
        else:
            print("[bench] check: all guarded metrics within benchmarks/thresholds.toml", file=sys.stderr)
    return status


def _engine(args: argparse.Namespace):
    """The executor engine of ``--cluster`` / ``--workers`` (None: each job's default, all local cores)."""
    from benchmarks.executor import make_engine

    if getattr(args, "cluster", None):
        return make_engine(cluster=args.cluster)
    if getattr(args, "workers", None) is not None:
        return make_engine(workers=args.workers)
    return None


def add_engine_options(p: argparse.ArgumentParser) -> None:
    """``--workers N`` and ``--cluster ADDRESS`` for a command whose cells go through the executor."""
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")
    p.add_argument("--cluster", metavar="ADDRESS", default=None,
                   help="run the cells on an existing Dask cluster, e.g. tcp://10.0.0.5:8786 "
                        "(needs pip install 'stereotactip[cluster]')")


def _sweep(args: argparse.Namespace) -> int:
    from benchmarks.sweep import make_cells, parse_floats, parse_patterns, run_sweep

    cells = make_cells(parse_floats(args.skin, "skin"), parse_floats(args.separation, "separation"),
                       parse_patterns(args.pattern))
    engine = _engine(args)
    try:
        res = run_sweep(args.experiment, cells, Path(args.out), seed=args.seed, quick=args.quick,
                        params=_key_values(args.param, "--param"), progress=not args.no_progress, engine=engine)
    finally:
        if engine is not None:
            engine.close()
    bad = [r for r in res["rows"] if r["status"] not in ("ok", "invalid")]
    print(f"[sweep] {len(res['rows'])} cells → {res['parquet'] or '(no pyarrow: no Parquet)'}, {res['csv']}, "
          f"{res['json']}" + (f", {res['figure']}" if res["figure"] else ""), file=sys.stderr)
    for r in res["rows"]:
        if r["status"] != "ok":
            print(f"[sweep] {r['cell']}: {r['status']} {r['error']}", file=sys.stderr)
    return 1 if bad else 0


def _report(args: argparse.Namespace) -> int:
    from benchmarks.report import write_report

    from benchmarks.readme_blocks import BLOCKS, update_readme

    against = [Path(d) for d in args.against or ()]
    blocks = tuple(args.block or ("gate-figures",))
    # a block written from a command's own summary (validate's summary.json) has no benchmark records to report on
    pages = not (args.readme and all(b in BLOCKS and BLOCKS[b].reads_file for b in blocks))
    path = write_report(Path(args.dir), against=against) if pages else None
    if path is not None:
        print(path)
    if args.readme:
        print(update_readme(Path(args.readme), Path(args.dir), blocks, against_dir=against))
    if path is not None:
        print(path.with_name("report.html"))
        if path.with_name("report.png").is_file():
            print(path.with_name("report.png"))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's subcommands to the top-level parser."""
    p = sub.add_parser("bench", help="run the paper's experiments (twin frames through the pipeline)")
    p.add_argument("name", help="experiment name, comma-separated names (patterns,gaussian), 'all', or 'list'")
    p.add_argument("--quick", action="store_true", help="reduced grid (the CI variant)")
    p.add_argument("--check", action="store_true", help="compare quick metrics with benchmarks/thresholds.toml")
    p.add_argument("--seed", type=int, default=0, help="root random seed (default 0)")
    p.add_argument("--out", metavar="DIR", help="output directory for JSON and PNG")
    p.add_argument("--param", action="append", metavar="KEY=VALUE", help="experiment knob override")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="design override, e.g. skin.thickness_mm=0.5")
    p.add_argument("--calibration", choices=("oracle", "estimated"), default="oracle",
                   help="what the pipeline is given: the twin's exact cameras, index and stack (oracle, default), "
                        "or a chessboard calibration, a press-fitted index and a stack drawn within manufacturing "
                        "tolerances (estimated; cached in OUT/calibration_cache)")
    p.add_argument("--error-sources", metavar="LIST", default=None,
                   help="with --calibration estimated: keep only these error sources, comma-separated subset of "
                        "calibration,index,thickness (an ablation; default all)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_engine_options(p)
    p.set_defaults(func=_bench)

    s = sub.add_parser("sweep", help="run one experiment over skin × separation × pattern cells")
    s.add_argument("--experiment", required=True)
    s.add_argument("--skin", default="1.0", help="skin thicknesses, mm, comma-separated")
    s.add_argument("--separation", default="2.54", help="marker separations, mm, comma-separated")
    s.add_argument("--pattern", default="hexagon", help="subset of hexagon,square,circular")
    s.add_argument("--quick", action="store_true")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", metavar="DIR", required=True)
    s.add_argument("--param", action="append", metavar="KEY=VALUE")
    add_engine_options(s)
    s.add_argument("--no-progress", action="store_true")
    s.set_defaults(func=_sweep)

    r = sub.add_parser("report", help="write DIR/report.md and DIR/report.html from the benchmark results in DIR")
    r.add_argument("dir", metavar="DIR")
    r.add_argument("--against", metavar="DIR2", action="append",
                   help="add a side-by-side table of the experiments DIR2 also holds (e.g. an oracle and an "
                        "estimated run); repeatable: one table per directory")
    r.add_argument("--readme", metavar="README.md",
                   help="also rewrite generated blocks of this README from the records in DIR (default: the "
                        "gate-figures block, from the quick records)")
    r.add_argument("--block", action="append", metavar="NAME",
                   help="with --readme: the block to rewrite, e.g. twin-speed from a `bench twin` results "
                        "directory, identification-coverage from a `bench identification` one (repeatable; names "
                        "in benchmarks/readme_blocks.py); oracle-vs-estimated takes DIR2 from --against, error-sources the "
                        "index-only and thickness-only runs from two --against (DIR the calibration-only run)")
    r.set_defaults(func=_report)

    from benchmarks import cli_terrain

    cli_terrain.register(sub)                      # stereotactip terrain
    from benchmarks import tactip_fit_cli, tactip_validate

    tactip_fit_cli.register(sub)                   # stereotactip fit-twin
    tactip_validate.register(sub)                  # stereotactip validate
