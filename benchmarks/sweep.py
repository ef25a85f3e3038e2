"""Design sweeps: one experiment over a grid of skin thickness × marker separation × pattern.

Each cell is one design (the built-in design of that pattern kind with the cell's overrides) and
one run of the experiment in its own directory ``OUT/cells/<cell id>/``; its JSON record is what
makes a sweep resumable. A finished cell is reused only if its record says ``ok`` and carries the
same resume key: a digest of everything that determines the cell (:func:`cell_key`: experiment,
cell, the cell's full design content, ``--param`` values, seed, quick flag and the experiment's
source code). Any change recomputes the cell; an unreadable record is recomputed too. The run says
how many cells it reused. Cells run in parallel in spawned worker processes (:mod:`benchmarks.pool`:
Ctrl-C / SIGTERM stop within seconds, queued cells are cancelled, workers of a killed driver exit on
their own; ``--cluster`` runs the same cells on a Dask cluster, :mod:`benchmarks.executor`). Each
finished cell's record is stored by the driver as it arrives. The results table is tidy, one row per
cell (design parameters, ``--param`` values, status, every metric, ``physics_valid``, provenance):
``OUT/sweep_<experiment>.parquet`` and ``.csv`` (:mod:`benchmarks.table`), with
``sweep_<experiment>_presses.*`` (the experiment's per-press rows, where it reports them), a JSON copy
and a summary figure ``OUT/sweep_<experiment>.png``, all atomically.

Changing the separation keeps the pattern's radius: ``layers = round(R_base / separation) + 1``
where ``R_base = (layers - 1) · separation`` of the built-in design (the outer ring's distance along
+x), one ring fewer if that does not fit the gel; this reproduces the built-in 61 / 127 /
217-marker hexagons at 3.54 / 2.54 / 1.80 mm.
"""

from __future__ import annotations

import hashlib
import inspect
import itertools
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from pipeline.io.atomic import atomic_write_json
from pipeline.errors import UserError

__all__ = ["Cell", "make_cells", "run_sweep", "cell_key", "BASE_DESIGN", "SweepError"]

BASE_DESIGN = {"hexagon": "hexagon127", "square": "square121", "circular": "circular217_dome"}


class SweepError(UserError, ValueError):
    """A sweep axis value is malformed or names an unknown pattern."""


@dataclass(frozen=True)
class Cell:
    pattern: str
    separation_mm: float
    skin_mm: float

    @property
    def cell_id(self) -> str:
        return f"{self.pattern}_sep{self.separation_mm:.2f}_skin{self.skin_mm:.2f}"

    def overrides(self) -> dict[str, Any]:
        """Design overrides on ``BASE_DESIGN[pattern]`` (layers chosen to keep the pattern radius)."""
        from pipeline.design import load_design

        from pipeline.design import DesignError

        base = load_design(BASE_DESIGN[self.pattern])
        axis_radius_mm = (base.pattern.layers - 1) * base.pattern.separation_mm  # outer ring on the +x axis
        layers = max(int(round(axis_radius_mm / self.separation_mm)) + 1, 2)
        while True:
            ov = {"skin.thickness_mm": self.skin_mm, "pattern.separation_mm": self.separation_mm,
                  "pattern.layers": layers}
            try:
                base.with_overrides(ov)
                return ov
            except DesignError:
                if layers <= 2:
                    raise
                layers -= 1  # the rounded ring count overflows the gel: drop the outer ring

    def design(self):
        from pipeline.design import load_design

        return load_design(BASE_DESIGN[self.pattern]).with_overrides(self.overrides(), name=self.cell_id)


def parse_floats(text: str, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise SweepError(f"--{what} {text!r}: expected comma-separated numbers, e.g. 0.5,1.0,1.5") from None
    if not values or any(not math.isfinite(v) or v <= 0 for v in values):
        raise SweepError(f"--{what} {text!r}: values must be positive numbers")
    return values


def parse_patterns(text: str) -> list[str]:
    values = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in values if v not in BASE_DESIGN]
    if not values or bad:
        raise SweepError(f"--pattern {text!r}: expected a comma-separated subset of {', '.join(BASE_DESIGN)}")
    return values


def make_cells(skins: Sequence[float], separations: Sequence[float], patterns: Sequence[str]) -> list[Cell]:
    return [Cell(p, s, t) for p, s, t in itertools.product(patterns, separations, skins)]


def _cell_record_path(out_dir: Path, experiment: str, cell: Cell) -> Path:
    return out_dir / "cells" / cell.cell_id / f"{experiment}.json"


def _code_digest(exp) -> str:
    """sha256 of the source file of the experiment's run function (its code version)."""
    try:
        src = inspect.getsourcefile(exp.run)
        data = Path(src).read_bytes() if src else b""
    except (OSError, TypeError):
        data = b""
    return hashlib.sha256(data).hexdigest()[:16]


def cell_key(experiment: str, cell: Cell, *, seed: int, quick: bool, params: dict[str, Any]) -> tuple[str, dict]:
    """The resume key of one cell: a digest of everything that determines its result, and the inputs
    it was computed from (stored in the record, so a reader can see why a cell was recomputed).

    The design enters as its full content (the built-in base design with the cell's overrides), so an
    edited design file changes the key as much as a changed cell does."""
    from benchmarks.registry import get
    from pipeline.design import DesignError, to_dict

    try:
        design = to_dict(cell.design())
    except DesignError as exc:
        design = {"invalid": str(exc)}
    inputs = {"experiment": experiment, "cell": cell.cell_id, "pattern": cell.pattern,
              "separation_mm": cell.separation_mm, "skin_mm": cell.skin_mm, "design": design,
              "params": {str(k): repr(v) for k, v in sorted(params.items())}, "seed": int(seed),
              "quick": bool(quick), "experiment_code": _code_digest(get(experiment))}
    blob = json.dumps(inputs, sort_keys=True, default=repr).encode()
    return hashlib.sha256(blob).hexdigest(), inputs


def _is_done(path: Path, *, key: str) -> dict[str, Any] | None:
    """The finished record at ``path`` if it says ``ok`` and carries ``key``; None otherwise (missing,
    unreadable, failed or computed from other inputs)."""
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(rec, dict) or rec.get("status") != "ok" or rec.get("resume_key") != key:
        return None
    return rec


def _run_cell(experiment: str, cell: Cell, out_dir: str, seed: int, quick: bool,
              params: dict[str, Any], key: str = "", inputs: dict | None = None) -> dict[str, Any]:
    """Worker: run one cell (module-level so any engine can ship it). Returns the cell's record with its
    resume key; the driver stores it (:func:`_store`) as the cell finishes."""
    from benchmarks.registry import Context, get
    from benchmarks.results import execute
    from pipeline.design import DesignError

    cell_dir = Path(out_dir) / "cells" / cell.cell_id
    exp = get(experiment)
    try:
        overrides = cell.overrides()
        cell.design()  # validate before running (a 3.54 mm square may not fit the gel, etc.)
    except DesignError as exc:
        return {"experiment": experiment, "status": "invalid", "error": str(exc), "metrics": {}}
    ctx = Context(out_dir=cell_dir, quick=quick, seed=seed, overrides=overrides, params=params,
                  progress=False, base_design=BASE_DESIGN[cell.pattern])
    record = execute(exp, ctx)
    return {**record, "resume_key": key, "resume_inputs": inputs or {}}


def _store(out_dir: Path, experiment: str, cell: Cell, record: dict[str, Any]) -> None:
    """Write a cell's record where a resumed sweep looks for it (atomically: complete or absent)."""
    from benchmarks.results import write_record

    write_record({**record, "experiment": experiment}, out_dir / "cells" / cell.cell_id)


#: Provenance columns of the results table (besides the cell, its parameters and its metrics).
PROVENANCE = ("experiment", "seed", "quick", "commit", "wall_time_s", "engine", "resume_key")


def table_row(experiment: str, cell: Cell, rec: Mapping[str, Any], metric_names: Sequence[str], *,
              params: Mapping[str, Any], seed: int, quick: bool, engine: str) -> dict[str, Any]:
    """One tidy row: the cell's design parameters, ``--param`` values, status, every declared metric,
    the physics-validity flags and the provenance."""
    try:
        design = cell.design()
        layers, markers = design.pattern.layers, design.marker_count
    except Exception:  # noqa: BLE001 - a design that does not fit the gel is a row with status "invalid"
        layers = markers = None
    metrics = rec.get("metrics", {}) or {}
    row: dict[str, Any] = {"cell": cell.cell_id, "pattern": cell.pattern, "separation_mm": cell.separation_mm,
                           "skin_mm": cell.skin_mm, "layers": layers, "marker_count": markers}
    row.update({f"param_{k}": v for k, v in sorted(params.items())})
    row["status"] = rec.get("status")
    row["error"] = (rec.get("error") or "").splitlines()[0] if rec.get("error") else ""
    for m in metric_names:
        v = metrics.get(m)
        row[m] = None if v is None else v.get("value")
    invalid = (metrics.get("invalid_cells") or {}).get("value")
    # the experiment's own physics verdict: True when none of its twin frames failed the checks
    row["physics_valid"] = None if invalid is None else bool(invalid == 0)
    row.update({"experiment": experiment, "seed": int(seed), "quick": bool(quick), "commit": rec.get("commit"),
                "wall_time_s": rec.get("wall_time_s"), "engine": engine, "resume_key": rec.get("resume_key")})
    for pkg, ver in sorted((rec.get("versions") or {}).items()):
        row[f"version_{pkg}"] = ver
    return row


def run_sweep(experiment: str, cells: Iterable[Cell], out_dir: Path, *, seed: int = 0, quick: bool = False,
              workers: int | None = None, params: dict[str, Any] | None = None, progress: bool = True,
              engine=None) -> dict[str, Any]:
    """Run (or resume) a sweep on ``engine`` (default: local processes, ``workers`` of them, all cores
    if None); returns ``{"rows", "csv", "parquet", "json", "figure", "cells_table"}``."""
    from benchmarks.executor import make_engine, run_cells
    from benchmarks.registry import get

    exp = get(experiment)  # fail early on an unknown name
    missing = exp.missing_requirements()
    if missing:
        raise SweepError(f"experiment {experiment!r} is unavailable: missing {', '.join(missing)}")
    if workers is not None and workers < 1:
        raise SweepError(f"--workers {workers}: must be >= 1")
    engine = engine or make_engine(workers=workers)
    cells = list(cells)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    params = dict(params or {})
    records: dict[str, dict[str, Any]] = {}
    todo = []
    keys = {}
    for cell in cells:
        key, inputs = cell_key(experiment, cell, seed=seed, quick=quick, params=params)
        keys[cell.cell_id] = (key, inputs)
        rec = _is_done(_cell_record_path(out_dir, experiment, cell), key=key)
        if rec is not None:
            records[cell.cell_id] = rec
        else:
            todo.append(cell)
    reused = len(cells) - len(todo)
    print(f"[sweep] {experiment}: reusing {reused} of {len(cells)} finished cell(s) (same experiment, design, "
          f"parameters, seed, quick flag and experiment code); computing {len(todo)} on {engine.describe()}",
          file=sys.stderr, flush=True)

    def done(o) -> None:
        cell = todo[o.index]
        if o.ok:
            rec = o.result
        else:  # the cell raised outside the experiment, or its worker was lost too often
            rec = {"experiment": experiment, "status": "error", "error": o.error, "metrics": {},
                   "resume_key": keys[cell.cell_id][0], "wall_time_s": o.wall_s}
        records[cell.cell_id] = rec
        _store(out_dir, experiment, cell, rec)   # the resume point: stored as soon as the cell is done

    run_cells(_run_cell, [(experiment, c, str(out_dir), seed, quick, params, *keys[c.cell_id]) for c in todo],
              engine=engine, on_done=done, desc=f"sweep {experiment}", progress=progress, already_done=reused)

    metric_names = list(exp.metrics)
    rows = [table_row(experiment, cell, records[cell.cell_id], metric_names, params=params, seed=seed,
                      quick=quick, engine=engine.name) for cell in cells]
    units = {m: u for m, u in exp.metrics.items()}
    from benchmarks.table import write_table

    paths = write_table(rows, out_dir / f"sweep_{experiment}")
    # the experiments' own per-press tables (indenter parameters, validity per frame), one row per press
    presses = [{"cell": cell.cell_id, "pattern": cell.pattern, "cell_separation_mm": cell.separation_mm,
                "cell_skin_mm": cell.skin_mm, **r}
               for cell in cells for r in ((records[cell.cell_id].get("tables") or {}).get("cells") or [])
               if isinstance(r, dict)]
    cells_table = write_table(presses, out_dir / f"sweep_{experiment}_presses") if presses else None
    json_path = out_dir / f"sweep_{experiment}.json"
    atomic_write_json(json_path, {"sweep": experiment, "seed": seed, "quick": quick, "units": units,
                                  "engine": engine.describe(), "cells_reused": reused, "rows": rows},
                      allow_nan=False)
    fig_path = _summary_figure(experiment, rows, units, out_dir / f"sweep_{experiment}.png")
    return {"rows": rows, "csv": paths["csv"], "parquet": paths["parquet"], "json": json_path, "figure": fig_path,
            "cells_table": cells_table}


def _summary_figure(experiment: str, rows: list[dict[str, Any]], units: dict[str, str], path: Path) -> Path | None:
    """Each metric (up to 4) vs separation, one line per skin thickness, one marker style per pattern."""
    from benchmarks.results import COLUMN_IN, paper_style, save_figure

    metrics = [m for m in units if any(isinstance(r.get(m), (int, float)) for r in rows)][:4]
    if not metrics:
        return None
    with paper_style() as plt:
        fig, axes = plt.subplots(1, len(metrics), figsize=(COLUMN_IN * len(metrics) * 0.75, 2.4), squeeze=False)
        markers = {"hexagon": "o", "square": "s", "circular": "^"}
        skins = sorted({r["skin_mm"] for r in rows})
        colours = plt.cm.viridis([i / max(len(skins) - 1, 1) for i in range(len(skins))])
        for ax, m in zip(axes[0], metrics):
            for pattern in sorted({r["pattern"] for r in rows}):
                for skin, colour in zip(skins, colours):
                    pts = sorted((r["separation_mm"], r[m]) for r in rows
                                 if r["pattern"] == pattern and r["skin_mm"] == skin and isinstance(r[m], (int, float)))
                    if pts:
                        xs, ys = zip(*pts)
                        ax.plot(xs, ys, marker=markers.get(pattern, "x"), color=colour, ms=3,
                                label=f"{pattern}, skin {skin:g} mm")
            ax.set_xlabel("marker separation (mm)")
            ax.set_ylabel(f"{m} ({units[m]})")
            ax.grid(True)
        axes[0][0].legend(loc="best")
        fig.suptitle(f"sweep: {experiment}")
        return save_figure(fig, path)
