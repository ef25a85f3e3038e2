"""The CI regression gate: ``benchmarks/thresholds.toml`` read and checked against quick records.

``thresholds.toml`` is the one versioned file of regression thresholds for the quick variants;
:func:`load_thresholds` reads it and :func:`check` compares the records that :mod:`benchmarks.results`
wrote with it.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Iterable, Mapping

from benchmarks.results import ResultsError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["Threshold", "Violation", "load_thresholds", "thresholds_path", "check", "bounds_text"]

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


def bounds_text(lo: float | None, hi: float | None, *, table: bool = False) -> str:
    """A range of which either end may be open: ``>= lo and <= hi`` (messages), or with ``table`` the
    README table's ``lo – hi`` / ``≥ lo`` / ``≤ hi`` / ``—`` at 4 significant digits."""
    if table:
        if lo is None and hi is None:
            return "—"
        if lo is not None and hi is not None:
            return f"{lo:.4g} – {hi:.4g}"
        return f"≥ {lo:.4g}" if lo is not None else f"≤ {hi:.4g}"
    parts = []
    if lo is not None:
        parts.append(f">= {lo:g}")
    if hi is not None:
        parts.append(f"<= {hi:g}")
    return " and ".join(parts)


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

    def describe(self, tier: str | None = None) -> str:
        sanity = bounds_text(self.min, self.max)
        golden = bounds_text(self.golden_min, self.golden_max)
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
