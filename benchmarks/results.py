"""Running one experiment, its JSON record and the paper's figure style.

Every experiment run writes ``OUT/<name>.json`` with the keys in :data:`REQUIRED_KEYS`: metrics with
units, the design (``pipeline.design.to_dict``), seed, git commit, quick flag, wall time and the
versions of numpy / mujoco / opencv, plus tables, notes, findings and figure paths (relative to OUT).
The CI gate that compares records with ``benchmarks/thresholds.toml`` is :mod:`benchmarks.thresholds`.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import platform
import subprocess
import time
import traceback
from importlib import metadata
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from benchmarks.registry import Context, Experiment, Result
from pipeline.io.atomic import atomic_write_json, savefig_atomic
from pipeline.errors import UserError

__all__ = [
    "REQUIRED_KEYS",
    "SCHEMA_VERSION",
    "execute",
    "write_record",
    "load_record",
    "read_json_object",
    "load_records",
    "git_commit",
    "versions",
    "paper_style",
    "save_figure",
    "ResultsError",
]

SCHEMA_VERSION = 1
REQUIRED_KEYS = ("schema", "experiment", "status", "metrics", "design", "seed", "commit", "quick",
                 "wall_time_s", "versions", "figures", "tables", "notes", "findings", "paper", "params",
                 "overrides", "error")
STATUSES = ("ok", "error", "unavailable")

# Paper figure widths (IEEE two-column): one column 3.5 in, full width 7.16 in.
COLUMN_IN = 3.5
PAGE_IN = 7.16


class ResultsError(UserError):
    """A results directory, record or thresholds file is missing or malformed."""


# ----- provenance -------------------------------------------------------------------------------

def git_commit(repo: Path | None = None) -> str:
    """``git rev-parse HEAD`` of the source tree (``"unknown"`` outside a git checkout)."""
    repo = repo or Path(__file__).resolve().parents[1]
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    sha = out.stdout.strip()
    return sha if out.returncode == 0 and len(sha) == 40 else "unknown"


def versions() -> dict[str, str]:
    """Versions of the numerical stack that can change the numbers."""
    out = {"python": platform.python_version()}
    for key, dist in (("numpy", "numpy"), ("scipy", "scipy"), ("mujoco", "mujoco"),
                      ("opencv", "opencv-python-headless"), ("pyrender", "pyrender"), ("trimesh", "trimesh")):
        try:
            out[key] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[key] = "not installed"
    return out


# ----- JSON -------------------------------------------------------------------------------------

def _jsonable(value: Any) -> Any:
    """Plain JSON values: numpy scalars/arrays to Python, NaN/inf to None, Paths to strings."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, Path):
        return str(value)
    return value


def _design_dict(design: Any) -> dict[str, Any]:
    from pipeline.design import to_dict

    return to_dict(design)


def build_record(exp: Experiment, ctx: Context, result: Result | None, *, status: str, wall_s: float,
                 error: str | None = None) -> dict[str, Any]:
    """The JSON record of one run (see :data:`REQUIRED_KEYS`)."""
    designs = list(result.designs) if result is not None else []
    if not designs:
        designs = [ctx.design()]
    figures = []
    for p in (result.figures if result is not None else []):
        p = Path(p)
        try:
            figures.append(str(p.resolve().relative_to(ctx.out_dir.resolve())))
        except ValueError:
            figures.append(str(p))
    metrics = {}
    if result is not None:
        for name, (value, unit) in result.metrics.items():
            metrics[name] = {"value": value, "unit": unit}
    record = {
        "schema": SCHEMA_VERSION,
        "experiment": exp.name,
        "description": exp.description,
        "status": status,
        "metrics": metrics,
        "design": _design_dict(designs[0]),
        "designs_used": [d.name for d in designs],
        "seed": int(ctx.seed),
        "commit": git_commit(),
        "quick": bool(ctx.quick),
        "wall_time_s": float(wall_s),
        "versions": versions(),
        "figures": figures,
        "tables": result.tables if result is not None else {},
        "notes": result.notes if result is not None else [],
        "findings": [{"claim": f.claim, "observed": f.observed, "agrees": f.agrees}
                     for f in (result.findings if result is not None else [])],
        "paper": {k: {"value": v.value, "unit": v.unit, "text": v.text} for k, v in exp.paper.items()},
        "params": dict(ctx.params),
        "overrides": dict(ctx.overrides),
        "calibration": {"mode": ctx.calibration,
                        "error_sources": list(ctx.error_sources) if ctx.error_sources is not None else None,
                        "setups": list(result.setups) if result is not None else []},
        "error": error,
    }
    return _jsonable(record)


def write_record(record: Mapping[str, Any], out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{record['experiment']}.json"
    atomic_write_json(path, record, allow_nan=False)  # a half-written record never looks finished
    return path


def read_json_object(path: Path) -> dict[str, Any]:
    """The JSON object in ``path``; a :class:`ResultsError` naming the file when it is unreadable or not an object."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ResultsError(f"result file {path}: not readable JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ResultsError(f"result file {path}: expected a JSON object")
    return data


def load_record(path: Path) -> dict[str, Any]:
    record = read_json_object(path)
    missing = [k for k in REQUIRED_KEYS if k not in record]
    if missing:
        raise ResultsError(f"result file {path}: missing key {missing[0]!r}")
    return record


def load_records(out_dir: Path) -> dict[str, dict[str, Any]]:
    """All experiment records in ``out_dir`` (files with the required keys), by experiment name."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise ResultsError(f"results directory {out_dir} does not exist")
    records = {}
    for path in sorted(out_dir.glob("*.json")):
        try:
            rec = load_record(path)
        except ResultsError:
            continue  # sweep tables and other JSON live here too
        records[rec["experiment"]] = rec
    return records


def execute(exp: Experiment, ctx: Context, *, catch: bool = True) -> dict[str, Any]:
    """Run one experiment, time it, write ``ctx.out_dir/<name>.json`` and return the record.

    An experiment whose required modules are missing is recorded as ``unavailable``; one that
    raises is recorded as ``error`` with the traceback (re-raised when ``catch`` is False).
    """
    ctx.out_dir.mkdir(parents=True, exist_ok=True)
    missing = exp.missing_requirements()
    if missing:
        record = build_record(exp, ctx, None, status="unavailable", wall_s=0.0,
                              error=f"required module(s) not available: {', '.join(missing)}")
        write_record(record, ctx.out_dir)
        return record
    t0 = time.perf_counter()
    try:
        result = exp.run(ctx)
    except Exception as exc:  # noqa: BLE001 — recorded, and the suite continues
        if not catch:
            raise
        record = build_record(exp, ctx, None, status="error", wall_s=time.perf_counter() - t0,
                              error=f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=8)}")
        write_record(record, ctx.out_dir)
        return record
    wall = time.perf_counter() - t0
    gc.collect()  # release the experiment's headless GL contexts before the next one creates its own
    undeclared = sorted(set(result.metrics) - set(exp.metrics))
    wrong_unit = sorted(k for k, (_, u) in result.metrics.items() if k in exp.metrics and exp.metrics[k] != u)
    problem = None
    if undeclared:
        problem = f"metric(s) not declared in register(): {', '.join(undeclared)}"
    elif wrong_unit:
        problem = f"metric(s) with a unit differing from the declaration: {', '.join(wrong_unit)}"
    record = build_record(exp, ctx, result, status="error" if problem else "ok", wall_s=wall, error=problem)
    write_record(record, ctx.out_dir)
    return record


# ----- figures ----------------------------------------------------------------------------------

@contextlib.contextmanager
def paper_style():
    """Matplotlib (Agg) settings resembling the paper's figures: serif, 8 pt, thin lines."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    rc = {"font.family": "serif", "font.size": 8, "axes.titlesize": 8, "axes.labelsize": 8,
          "legend.fontsize": 7, "xtick.labelsize": 7, "ytick.labelsize": 7, "lines.linewidth": 1.0,
          "axes.linewidth": 0.6, "grid.linewidth": 0.4, "grid.alpha": 0.4, "savefig.dpi": 200,
          "savefig.bbox": "tight", "figure.dpi": 100}
    with plt.rc_context(rc):
        yield plt


def save_figure(fig, path: Path) -> Path:
    """Save a matplotlib figure as PNG and close it."""
    import matplotlib.pyplot as plt

    path = Path(path).with_suffix(".png")
    try:
        savefig_atomic(fig, path)
    finally:
        plt.close(fig)
    return path
