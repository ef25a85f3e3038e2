"""One registry of the paper's experiments (dm_control suite style).

An experiment is a plain function ``run(ctx: Context) -> Result`` registered with::

    @register("patterns", tags=("quick", "paper"), metrics={"matched_fraction_min": "1"},
              requires=("pipeline.runner", "twin.simulate"))
    def run(ctx: Context) -> Result: ...

``metrics`` declares every metric the experiment reports and its unit (``"1"`` for a
dimensionless ratio); ``requires`` names the modules it needs (an experiment whose upstream
module is missing is reported as *unavailable*, not silently skipped); ``paper`` gives the
paper's value for a metric, for the report's "paper figure vs this run" table.

One test (``tests/test_benchmarks.py``) walks the registry and checks every experiment's
invariants; ``stereotactip bench NAME|all`` runs them.
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from pipeline.errors import UserError

__all__ = [
    "Context",
    "stream_rng",
    "Result",
    "Finding",
    "PaperValue",
    "Experiment",
    "register",
    "get",
    "names",
    "all_experiments",
    "load_all",
    "UnknownExperimentError",
]


class UnknownExperimentError(UserError, KeyError):
    """The experiment name given on the command line is not registered."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


@dataclass(frozen=True)
class PaperValue:
    """A number the paper reports for one metric: ``value`` in ``unit``; ``text`` says where."""

    value: float
    unit: str
    text: str


@dataclass(frozen=True)
class Finding:
    """A qualitative claim of the paper checked against this run.

    ``agrees`` is True / False when the run decides the claim, None when the run cannot (e.g. the
    quick grid lacks the cells needed). ``observed`` states the numbers behind the verdict.
    """

    claim: str
    observed: str
    agrees: bool | None


@dataclass
class Result:
    """What an experiment returns.

    Parameters
    ----------
    metrics : {name: (value, unit)}
        Scalar results. Units are strings (``"mm"``, ``"px"``, ``"ms"``, ``"1"`` for ratios).
    figures : list of Path
        PNG files written under ``ctx.out_dir``.
    tables : {name: list of row dicts}
        Per-cell numbers behind the metrics (JSON-serialisable values).
    notes : list of str
        Anything a reader needs to interpret the numbers (approximations, substitutions).
    findings : list of Finding
        The paper's qualitative claims, as this run sees them.
    designs : list
        ``SensorDesign`` objects the experiment used (the first is "the" design in the JSON).
    setups : list of dict
        Provenance of what the pipeline was given per design (``benchmarks.estimated.SensorSetup.provenance``:
        calibration mode, drawn stack deviations, fitted index); recorded under ``calibration`` in the JSON.
    """

    metrics: dict[str, tuple[float, str]] = field(default_factory=dict)
    figures: list[Path] = field(default_factory=list)
    tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)
    designs: list[Any] = field(default_factory=list)
    setups: list[dict[str, Any]] = field(default_factory=list)

    def metric(self, name: str, value: float, unit: str) -> None:
        self.metrics[name] = (float(value), unit)


def stream_rng(seed: int, stream: str = "") -> np.random.Generator:
    """The generator of a named stream under a root seed (what :meth:`Context.rng` gives).

    Cells run by the executor take ``(seed, stream)`` and build their generator where they run: a
    Generator object handed to a cell is consumed by it, so reusing the same job list (a second
    engine, a retried cell) would continue the stream instead of restarting it."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(stream.encode())])


@dataclass(frozen=True)
class Context:
    """Everything an experiment may depend on besides its code.

    Parameters
    ----------
    out_dir : Path
        Where the experiment writes its figures (the JSON is written by the caller).
    quick : bool
        Run the reduced grid (the CI variant, whose metrics are gated by ``thresholds.toml``).
    seed : int
        Root seed; every random stream derives from it through :meth:`rng`.
    overrides : {dotted key: value}
        Design overrides applied by :meth:`design` (e.g. ``{"skin.thickness_mm": 0.5}``).
    params : {name: value}
        Experiment-specific knob overrides (grid sizes, trial counts), read with :meth:`param`.
    progress : bool
        Show tqdm progress bars.
    base_design : str or None
        Set by a sweep cell: the one design every experiment uses instead of its own choice(s).
    engine : benchmarks.executor.Engine or None
        Where an experiment made of independent cells runs them (:func:`benchmarks.executor.run_cells`);
        None: local processes on all cores, or inline inside a sweep cell.
    calibration : {"oracle", "estimated"}
        What the pipeline is told about the sensor (:mod:`benchmarks.estimated`): the twin's exact cameras,
        index and stack, or a chessboard calibration, a press-fitted index and a drawing the built
        stack deviates from within tolerances.
    error_sources : tuple of str or None
        With ``calibration="estimated"``: the error sources kept (subset of ``benchmarks.estimated.SOURCES``;
        None: all), for an ablation.
    """

    out_dir: Path
    quick: bool = False
    seed: int = 0
    overrides: Mapping[str, Any] = field(default_factory=dict)
    params: Mapping[str, Any] = field(default_factory=dict)
    progress: bool = True
    base_design: str | None = None
    engine: Any = None
    calibration: str = "oracle"
    error_sources: tuple[str, ...] | None = None

    def rng(self, stream: str = "") -> np.random.Generator:
        """An independent generator for a named stream, reproducible from ``seed`` alone."""
        return stream_rng(self.seed, stream)

    def design(self, name: str | None = None):
        """Load a design (``base_design`` if set, else ``name``, else ``hexagon127``) with the overrides."""
        from pipeline.design import DEFAULT_DESIGN, load_design

        design = load_design(self.base_design or name or DEFAULT_DESIGN)
        return design.with_overrides(dict(self.overrides)) if self.overrides else design

    def designs(self, names: Iterable[str]) -> list:
        """The designs an experiment loops over: ``names`` normally, only the sweep cell's design
        when ``base_design`` is set (overrides are applied either way)."""
        if self.base_design is not None:
            return [self.design()]
        return [self.design(n) for n in names]

    def sensor_setup(self, design):
        """The twin's sensor and what the pipeline is given for ``design`` (:func:`benchmarks.estimated.sensor_setup`
        with this context's calibration mode, error sources and seed). The estimated chessboard calibration
        and index fit are cached under ``out_dir/calibration_cache`` per design and seed."""
        from benchmarks.estimated import sensor_setup

        return sensor_setup(design, mode=self.calibration, seed=self.seed, sources=self.error_sources,
                            cache_dir=self.out_dir / "calibration_cache", progress=self.progress)

    def param(self, name: str, full: Any, quick: Any | None = None) -> Any:
        """``params[name]`` if given, else ``quick`` (when ``self.quick`` and given) else ``full``."""
        if name in self.params:
            return self.params[name]
        return quick if (self.quick and quick is not None) else full

    def bar(self, iterable: Iterable | None = None, *, desc: str = "", total: int | None = None):
        """A tqdm progress bar (disabled when ``progress`` is False)."""
        from tqdm import tqdm

        return tqdm(iterable, desc=desc, total=total, disable=not self.progress, leave=False, dynamic_ncols=True)

    def run_cells(self, fn: Callable[..., Any], jobs: Iterable[tuple], *, desc: str = "") -> list:
        """Run the experiment's cells ``fn(*job)`` on :attr:`engine` (see :mod:`benchmarks.executor`);
        the outcomes in job order. A cell that raised is an outcome with its ``error``."""
        from benchmarks.executor import run_cells

        return run_cells(fn, list(jobs), engine=self.engine, desc=desc, progress=self.progress)

    def figure_path(self, name: str) -> Path:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        return self.out_dir / name


@dataclass(frozen=True)
class Experiment:
    name: str
    run: Callable[[Context], Result]
    tags: tuple[str, ...]
    metrics: Mapping[str, str]
    requires: tuple[str, ...]
    paper: Mapping[str, PaperValue]
    description: str

    def missing_requirements(self) -> list[str]:
        """Modules in ``requires`` that cannot be imported in this installation (the experiment is skipped)."""
        missing = []
        for mod in self.requires:
            try:
                if importlib.util.find_spec(mod) is None:
                    missing.append(mod)
            except (ImportError, ValueError):
                missing.append(mod)
        return missing

    def available(self) -> bool:
        return not self.missing_requirements()


_REGISTRY: dict[str, Experiment] = {}


def register(name: str, *, tags: Iterable[str] = (), metrics: Mapping[str, str],
             requires: Iterable[str] = (), paper: Mapping[str, PaperValue] | None = None,
             registry: dict[str, Experiment] | None = None) -> Callable:
    """Decorator adding ``run(ctx) -> Result`` to the registry under ``name``."""
    reg = _REGISTRY if registry is None else registry

    def deco(fn: Callable[[Context], Result]) -> Callable[[Context], Result]:
        if name in reg and reg[name].run is not fn:
            raise ValueError(f"experiment {name!r} registered twice")
        unknown = sorted(set(paper or {}) - set(metrics))
        if unknown:
            raise ValueError(f"experiment {name!r}: paper value for undeclared metric {unknown[0]!r}")
        doc = (fn.__doc__ or "").strip().splitlines()
        reg[name] = Experiment(name=name, run=fn, tags=tuple(tags), metrics=dict(metrics),
                               requires=tuple(requires), paper=dict(paper or {}),
                               description=doc[0] if doc else "")
        return fn

    return deco


def load_all() -> None:
    """Import every module in ``benchmarks.experiments`` (each registers itself)."""
    import benchmarks.experiments as pkg

    for info in pkgutil.iter_modules(pkg.__path__):
        importlib.import_module(f"{pkg.__name__}.{info.name}")


def all_experiments() -> dict[str, Experiment]:
    load_all()
    return dict(sorted(_REGISTRY.items()))


def names(tag: str | None = None) -> list[str]:
    return [n for n, e in all_experiments().items() if tag is None or tag in e.tags]


def get(name: str) -> Experiment:
    exps = all_experiments()
    if name not in exps:
        raise UnknownExperimentError(f"unknown experiment {name!r} (known: {', '.join(exps) or 'none'})")
    return exps[name]
