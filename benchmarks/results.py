"""Running one experiment, its JSON record, the paper's figure style and the CI threshold gate.

Every experiment run writes ``OUT/<name>.json`` with the keys in :data:`REQUIRED_KEYS`: metrics with
units, the design (``pipeline.design.to_dict``), seed, git commit, quick flag, wall time and the
versions of numpy / mujoco / opencv, plus tables, notes, findings and figure paths (relative to OUT).

``benchmarks/thresholds.toml`` is the one versioned file of regression thresholds for the quick
variants; :func:`check` compares records with it.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import platform
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from importlib import metadata, resources
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from benchmarks.registry import Context, Experiment, Result
from pipeline.io.atomic import atomic_write_json, savefig_atomic
from pipeline.errors import UserError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "REQUIRED_KEYS",
    "SCHEMA_VERSION",
    "execute",
    "write_record",
    "load_record",
    "load_records",
    "git_commit",
    "versions",
    "paper_style",
    "save_figure",
    "Threshold",
    "Violation",
    "load_thresholds",
    "check",
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


def load_record(path: Path) -> dict[str, Any]:
    path = Path(path)
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ResultsError(f"result file {path}: not readable JSON ({exc})") from None
    if not isinstance(record, dict):
        raise ResultsError(f"result file {path}: expected a JSON object")
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


# ----- thresholds (CI regression gate) --------------------------------------------------------
#
# Two tiers per guarded metric:
#   * the *sanity* bound (``min`` / ``max``) catches a collapse: the metric left the range in which the
#     experiment still means what it says;
#   * the *golden* bound (``golden_min`` / ``golden_max``) catches a regression: it sits at the measured
#     value for an ``exact`` metric (bit-for-bit reproducible: counts, seeded integer outcomes), within 25 %
#     of it for a ``deterministic`` one (seeded, reproducible up to floating-point summation order), and
#     within 25 % beyond the measured run-to-run ``spread`` for a ``noisy`` one (times, ratios of times).
# A deterministic metric that moves by more than 25 % in either direction, better or worse, fails the
# golden tier: the change must be looked at and the bound re-measured in the same commit.
# Metrics whose value depends on what the pipeline is told about the sensor sit in a sub-table named after
# the calibration mode (``[gaussian.estimated]``, ``[gaussian.oracle]``) and are checked only against
# records of that mode; the rest apply to every mode.

KINDS = ("exact", "deterministic", "noisy")
MODES = ("oracle", "estimated")
GOLDEN_MARGIN = 0.25
_SPEC_KEYS = {"min", "max", "golden_min", "golden_max", "kind", "measured", "spread", "why"}


@dataclass(frozen=True)
class Threshold:
    """Bounds on one quick metric: the sanity tier ``min <= value <= max`` and the golden tier
    ``golden_min <= value <= golden_max`` (any of the four may be absent). ``mode``: the calibration mode
    whose records the bound applies to (None: every mode)."""

    experiment: str
    metric: str
    min: float | None
    max: float | None
    measured: float | None
    why: str
    golden_min: float | None = None
    golden_max: float | None = None
    kind: str | None = None
    spread: tuple[float, float] | None = None
    mode: str | None = None

    @staticmethod
    def _outside(value: float, lo: float | None, hi: float | None) -> bool:
        return (lo is not None and value < lo) or (hi is not None and value > hi)

    def tier_violated(self, value: float | None) -> str | None:
        """``"sanity"`` or ``"golden"`` (the first tier the value breaks), or None when within both."""
        if value is None or not math.isfinite(value):
            return "sanity"
        if self._outside(value, self.min, self.max):
            return "sanity"
        if self._outside(value, self.golden_min, self.golden_max):
            return "golden"
        return None

    def violated_by(self, value: float | None) -> bool:
        return self.tier_violated(value) is not None

    @staticmethod
    def _describe(lo: float | None, hi: float | None) -> str:
        parts = []
        if lo is not None:
            parts.append(f">= {lo:g}")
        if hi is not None:
            parts.append(f"<= {hi:g}")
        return " and ".join(parts)

    def describe(self, tier: str | None = None) -> str:
        sanity = self._describe(self.min, self.max)
        golden = self._describe(self.golden_min, self.golden_max)
        if tier == "sanity" or not golden:
            return sanity
        if tier == "golden":
            return f"golden {golden}"
        return f"{sanity}; golden {golden}"


@dataclass(frozen=True)
class Violation:
    experiment: str
    metric: str
    threshold: str
    value: float | None
    reason: str

    def __str__(self) -> str:
        v = "missing" if self.value is None else f"{self.value:g}"
        return f"REGRESSION {self.experiment}.{self.metric}: value {v}, threshold {self.threshold} ({self.reason})"


def thresholds_path() -> Path:
    return Path(str(resources.files("benchmarks").joinpath("thresholds.toml")))


def _threshold(path: Path, exp: str, metric: str, spec: Any, mode: str | None) -> Threshold:
    where = f"thresholds file {path}: {exp}.{mode + '.' if mode else ''}{metric}"
    if not isinstance(spec, dict):
        raise ResultsError(f"{where} must be an inline table")
    unknown = sorted(set(spec) - _SPEC_KEYS)
    if unknown:
        raise ResultsError(f"{where}: unknown key {unknown[0]!r}")
    if "min" not in spec and "max" not in spec:
        raise ResultsError(f"{where}: needs min and/or max (the sanity tier)")
    if not str(spec.get("why", "")).strip():
        raise ResultsError(f"{where}: needs a 'why' (margin derivation)")
    try:
        lo, hi, glo, ghi, measured = (_num(spec.get(k)) for k in ("min", "max", "golden_min", "golden_max", "measured"))
        spread = spec.get("spread")
        if spread is not None:
            if not (isinstance(spread, list) and len(spread) == 2):
                raise ValueError("spread must be [lowest, highest] of the measured runs")
            spread = (float(spread[0]), float(spread[1]))
            if not spread[0] <= spread[1]:
                raise ValueError("spread must be [lowest, highest] of the measured runs")
    except (TypeError, ValueError) as exc:
        raise ResultsError(f"{where}: {exc}") from None
    kind = spec.get("kind")
    if glo is not None or ghi is not None or kind is not None:
        if kind not in KINDS:
            raise ResultsError(f"{where}: a golden bound needs kind = one of {', '.join(KINDS)} (got {kind!r})")
        if glo is None and ghi is None:
            raise ResultsError(f"{where}: kind {kind!r} without golden_min and/or golden_max")
        _check_golden(where, kind, glo, ghi, measured, spread)
        for g, s, side in ((glo, lo, "min"), (ghi, hi, "max")):
            if g is not None and s is not None and (g < s if side == "min" else g > s):
                raise ResultsError(f"{where}: golden_{side} {g:g} is looser than the sanity {side} {s:g}")
    return Threshold(exp, metric, lo, hi, measured, str(spec["why"]), glo, ghi, kind, spread, mode)


def _check_golden(where: str, kind: str, glo: float | None, ghi: float | None, measured: float | None,
                  spread: tuple[float, float] | None) -> None:
    """The golden tier's own rule: at the measured value (exact), within 25 % of it (deterministic), within
    25 % beyond the measured spread (noisy); and the measurement itself inside."""
    if kind == "noisy":
        if spread is None:
            raise ResultsError(f"{where}: a noisy metric needs spread = [lowest, highest] of the measured runs")
        lo_m, hi_m = spread
    else:
        if measured is None:
            raise ResultsError(f"{where}: a golden bound needs the measured value it was set from")
        lo_m = hi_m = measured
    margin = 0.0 if kind == "exact" else GOLDEN_MARGIN
    tol = 1e-9 * max(1.0, abs(lo_m), abs(hi_m))
    if glo is not None and not (lo_m - margin * abs(lo_m) - tol <= glo <= lo_m + tol):
        raise ResultsError(f"{where}: golden_min {glo:g} must lie within {margin:.0%} below the measured {lo_m:g} ({kind})")
    if ghi is not None and not (hi_m - tol <= ghi <= hi_m + margin * abs(hi_m) + tol):
        raise ResultsError(f"{where}: golden_max {ghi:g} must lie within {margin:.0%} above the measured {hi_m:g} ({kind})")


def load_thresholds(path: Path | None = None) -> dict[str, dict[str, Threshold]]:
    """``{experiment: {key: Threshold}}`` from ``thresholds.toml``; ``key`` is the metric name, or
    ``"<mode>.<metric>"`` for a bound that applies to one calibration mode only.

    Format: one table per experiment, one inline table per metric with ``min`` and/or ``max`` (sanity),
    ``golden_min`` and/or ``golden_max`` with ``kind`` (golden), ``measured`` / ``spread`` (what the bounds were set
    from) and ``why`` (the margins' derivation); sub-tables ``[exp.oracle]`` / ``[exp.estimated]`` for the
    metrics that depend on the calibration mode.
    """
    path = Path(path) if path is not None else thresholds_path()
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ResultsError(f"thresholds file {path}: {exc}") from None
    out: dict[str, dict[str, Threshold]] = {}
    for exp, table in raw.items():
        if not isinstance(table, dict):
            raise ResultsError(f"thresholds file {path}: [{exp}] must be a table")
        out[exp] = {}
        for metric, spec in table.items():
            if metric in MODES:
                if not isinstance(spec, dict) or not all(isinstance(v, dict) for v in spec.values()):
                    raise ResultsError(f"thresholds file {path}: [{exp}.{metric}] must be a table of metric bounds")
                for m, s in spec.items():
                    out[exp][f"{metric}.{m}"] = _threshold(path, exp, m, s, metric)
            else:
                out[exp][metric] = _threshold(path, exp, metric, spec, None)
    return out


def _num(v: Any) -> float | None:
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"expected a number, got {v!r}")
    return float(v)


def check(records: Mapping[str, Mapping[str, Any]], thresholds: Mapping[str, Mapping[str, Threshold]],
          *, experiments: Iterable[str] | None = None) -> list[Violation]:
    """Compare quick records with the thresholds; every guarded metric must be present and within both tiers.

    ``experiments`` restricts the gate to the ones that were run (default: all with thresholds). A bound of one
    calibration mode applies only to records of that mode.
    """
    wanted = list(thresholds) if experiments is None else [e for e in experiments if e in thresholds]
    violations = []
    for exp in wanted:
        rec = records.get(exp)
        mode = ((rec or {}).get("calibration") or {}).get("mode", "oracle")
        for th in thresholds[exp].values():
            if th.mode is not None and rec is not None and th.mode != mode:
                continue
            metric = th.metric if th.mode is None else f"{th.metric} ({th.mode})"
            if rec is None:
                violations.append(Violation(exp, metric, th.describe(), None, "experiment did not run"))
                continue
            if rec.get("status") != "ok":
                violations.append(Violation(exp, metric, th.describe(), None,
                                            f"experiment status {rec.get('status')!r}: "
                                            f"{(rec.get('error') or '').splitlines()[0] if rec.get('error') else ''}"))
                continue
            if not rec.get("quick"):
                violations.append(Violation(exp, metric, th.describe(), None,
                                            "thresholds guard the --quick variant; this record is a full run"))
                continue
            m = rec["metrics"].get(metric if th.mode is None else th.metric)
            value = None if m is None else m.get("value")
            tier = th.tier_violated(value)
            if tier is not None:
                if m is None:
                    reason = "metric missing"
                elif tier == "sanity":
                    reason = "out of bounds: sanity tier (collapse)"
                else:
                    reason = (f"out of bounds: golden tier ({th.kind}; measured "
                              f"{th.measured if th.spread is None else list(th.spread)}): re-measure if intended")
                violations.append(Violation(exp, metric, th.describe(tier), value, reason))
    return violations
