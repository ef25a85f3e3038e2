"""The terrain demonstration (paper, "Experiments III"): tap-scan the world relief, merge, score.

For each region (``twin.terrain.REGIONS``): zigzag tap centres with 15 mm steps over the region's box;
each tap lowers the downward-facing sensor from global z = 8 mm to the tap plane (the paper: z = 0,
sea level) and records the skin as points in the SENSOR frame; the points go to the global frame by
the tap pose (``pipeline.geometry.merge.tap_points_to_global``), are merged with the paper's overlap rule and
mollified (``pipeline.geometry.merge.merge_taps``), gridded, and compared with the DEM-derived truth.

Tap back ends (``sensor=``):

* ``"ideal"`` — a perfectly conforming skin read out at the design's rest marker x-y positions:
  z_skin = max(relief, tap plane) in the global frame. No physics, no optics: it measures what the
  scan geometry, marker sampling and merge alone allow, and is the upper bound of any real sensor.
* ``"twin"`` — the digital twin: ``twin.terrain.tap_indenter`` -> ``twin.simulate.press`` (MuJoCo skin)
  -> ``twin.render.StereoRenderer`` -> the unchanged pipeline (``pipeline.runner.Reconstructor``) ->
  skin points (the twin's physics and renderer must be installed); see :func:`_twin_tap`.

Outputs in ``out_dir``: ``taps/<region>_<k>.npz`` (one per finished tap: resumable; a tap file is
reused only if it loads and carries the same key — :meth:`TapJob.key`, a digest of region, index,
centre, tap plane, sensor back end, seed, scan step, the sensor design's content and
:data:`TAP_CODE_VERSION` — so a changed ``--tap-z`` or a truncated file recomputes the tap), per region
``<region>_height.npz`` (pipeline HeightMap, global frame), ``<region>_points.ply``, ``<region>.png``
(truth | reconstruction | error), ``world.png``, and ``terrain.json`` (metrics, tap counts, wall time).

One module (just over ~400 lines) on purpose: a tap's job, its key and its file are one contract
(resuming depends on all three agreeing), kept beside the scan that plans, runs and merges the taps; the
regions and the zigzag plan are :mod:`benchmarks.terrain_regions`, the scoring and figures
:mod:`benchmarks.terrain_score`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from pipeline.errors import UserError
from pipeline.io.files import write_ply
from pipeline.geometry.merge import (MOLLIFIER_EPS_MM, OVERLAP_THRESHOLD_MM, grid_points, merge_taps,
                                     tap_points_to_global)
from pipeline.types import HeightMap
from benchmarks.terrain_regions import REGIONS, plan_scan, region
from benchmarks.terrain_score import FEATURE_CRITERIA, region_panel, score_region, world_panel

__all__ = ["DESIGN_NAME", "DESIGN_OVERRIDES", "TapJob", "plan_jobs", "run_tap", "load_tap", "run_scan"]

DESIGN_NAME = "hexagon217_sep180"               # the paper's "dense markers"
DESIGN_OVERRIDES = {"skin.thickness_mm": 0.5}   # the paper's terrain sensor: skin 0.5 mm
GRID_STEP_MM = 0.25                              # output grid, = the mollifier's eps
MAX_GAP_MM = 2.0                                 # > marker spacing 1.8 mm: no holes between markers
QUICK_REGIONS = ("drake", "english_channel")     # --quick: two small regions, few taps


class TerrainScanError(UserError, ValueError):
    """Bad terrain-scan options (unknown region or sensor back end, missing twin modules)."""


#: Bump when a tap's computation changes in a way that changes its points (then no old tap file is
#: reused). 2: tap files carry their resume key. 3: and the pressed frame's physics verdict. 4: face contact.
#: 5: friction from the design's [twin] friction (1 by default), part of the key.
TAP_CODE_VERSION = 5
#: The skin mesh of a twin tap (``twin.physics.MeshSpec`` fields). Face contact: the outer faces also collide
#: with spheres on the relief's crests, cliffs and steep flanks (``twin.contact``); with vertex contact alone
#: the faces sat 0.57-0.99 mm inside the relief on every quick tap (all five invalid), with it 0.000-0.032 mm
#: (all five valid).
TAP_MESH = {"face_contact": True}
#: Global z of the tap plane: from the flattened ocean floor (-2 mm) to below the approach height (8 mm).
TAP_Z_RANGE_MM = (-2.0, 8.0)


@dataclass(frozen=True)
class TapJob:
    region: str
    index: int
    centre_mm: tuple[float, float]      # map/global x, y of the tap
    tap_z_mm: float                     # global z of the undeformed skin at the bottom of the tap
    sensor: str
    seed: int
    path: str                           # where the finished tap is written

    step_mm: float = 15.0               # scan step the centre came from
    setup: Any = None                   # benchmarks.estimated.SensorSetup of the 'twin' back end (None: oracle)

    def origin_mm(self) -> np.ndarray:
        return np.array([self.centre_mm[0], self.centre_mm[1], self.tap_z_mm])

    def key(self) -> str:
        """Digest of everything that determines this tap's points (not where it is written)."""
        from pipeline.design import to_dict

        design = _design()
        inputs = {"region": self.region, "index": self.index, "centre_mm": [round(v, 9) for v in self.centre_mm],
                  "tap_z_mm": round(self.tap_z_mm, 9), "sensor": self.sensor, "seed": self.seed,
                  "step_mm": round(self.step_mm, 9), "design": to_dict(design), "code": TAP_CODE_VERSION,
                  "mesh": TAP_MESH, "friction": design.twin_params()["friction"]}
        if self.setup is not None and self.setup.mode != "oracle":
            inputs["calibration"] = self.setup.provenance
        return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()


def _design():
    from pipeline.design import load_design

    return load_design(DESIGN_NAME).with_overrides(DESIGN_OVERRIDES)


def plan_jobs(regions: Sequence[str], out_dir: Path, *, sensor: str, tap_z_mm: float = 0.0,
              step_mm: float = 15.0, seed: int = 0, max_taps: int | None = None) -> dict[str, list[TapJob]]:
    """Tap jobs per region (zigzag order), each with its own output file under ``out_dir/taps``."""
    jobs: dict[str, list[TapJob]] = {}
    for key in regions:
        r = region(key)
        centres = plan_scan(r.box_mm(), step_mm=step_mm)
        if max_taps is not None:
            centres = centres[:max_taps]
        jobs[key] = [TapJob(key, k, (float(c[0]), float(c[1])), float(tap_z_mm), sensor, seed * 100003 + k,
                            str(out_dir / "taps" / f"{key}_{k:03d}.npz"), float(step_mm))
                     for k, c in enumerate(centres)]
    return jobs


# ----- one tap ------------------------------------------------------------------------------

def _ideal_tap(job: TapJob) -> np.ndarray:
    """Skin points (sensor frame) of a perfectly conforming skin at the rest marker x-y."""
    from twin.terrain import load_terrain_map

    xy = _design().rest_markers_mm()[:, :2]
    # sensor (x_s, y_s) of the downward-facing sensor looks at global (cx + x_s, cy - y_s)
    # (twin.terrain.tap_indenter); the object there sits at sensor z = tap_z - relief
    h = load_terrain_map().sample_z_mm(job.centre_mm[0] + xy[:, 0], job.centre_mm[1] - xy[:, 1], frame="global")
    z_obj = job.tap_z_mm - h
    # the skin (rest at z = 0) is pushed back wherever the object is behind z = 0
    return np.column_stack([xy, np.minimum(z_obj, 0.0)])


def _twin_tap(job: TapJob) -> tuple[np.ndarray, np.ndarray, dict | None]:
    """Skin points (sensor frame) from the digital twin and the unchanged pipeline, and the tap origin.

    The terrain patch under the sensor is a ``terrain`` indenter (its rest surface in the sensor frame
    touches the skin at its highest point); ``twin.simulate.press`` pushes it in by ``depth`` — how far
    the relief's highest point under the sensor passes the tap plane — and renders the pressed frame,
    which goes through :class:`pipeline.runner.Reconstructor` with the twin's true calibration. The
    reconstructed skin points are what the tap reports; truth is not read.

    The press is capped at the twin's deepest allowed press (``twin.physics.max_depth_mm``: gel −
    pin − margin, 7.5 mm for the terrain sensor), as a real robot stops at its force limit; a capped
    tap's skin then rests higher than the tap plane, and the returned origin says where (global z of
    the undeformed skin centre = highest relief point − depth), so the global chain stays exact.

    Returns
    -------
    points_sensor_mm : (N, 3) reconstructed outer-skin points, sensor frame (mm)
    origin_mm : (3,) global position of the undeformed skin centre at the bottom of the tap (mm)
    validity : the pressed frame's physics verdict (:class:`twin.validity.FrameValidity` as a dict)
    """
    try:
        from twin import indenters, simulate
        from twin.physics import MeshSpec, max_depth_mm
        from pipeline.runner import Reconstructor
    except ImportError as exc:
        raise TerrainScanError(f"sensor 'twin' needs the twin's physics/renderer ({exc}); use --sensor ideal") from None
    from twin.terrain import load_terrain_map, tap_indenter

    from benchmarks.estimated import sensor_setup

    # the twin presses the sensor as built; the pipeline is given the drawing and the setup's calibration
    setup = job.setup if job.setup is not None else sensor_setup(_design())
    built, design = setup.twin_design, setup.design
    tmap = load_terrain_map()
    # indenter surface at the bottom of the tap (sensor frame, +z toward the object); depth is how far
    # the relief's highest point under the sensor is pushed past the rest skin
    bottom = tap_indenter(tmap, job.centre_mm, skin_z_mm=job.tap_z_mm, radius_mm=design.gel.radius_mm + 2.0,
                          spacing_mm=0.2)
    want = max(0.0, -float(np.nanmin(bottom.z_mm)))
    depth = min(want, max_depth_mm(built))
    rest_surface = HeightMap(bottom.x_mm, bottom.y_mm, bottom.z_mm + want)
    indenter = indenters.make_indenter("terrain", height_map=rest_surface)
    rng = np.random.default_rng(job.seed)
    pairs = simulate.press(built, indenter, depth_mm=depth, rng=rng, mesh=MeshSpec(**TAP_MESH))  # [(frame, truth)]
    rec = Reconstructor(design, setup.calib, **setup.reconstructor_kw())
    last = [rec.process(frame) for frame, _truth in pairs][-1]
    origin = job.origin_mm()
    origin[2] += want - depth       # capped press: the skin stopped (want - depth) mm above the tap plane
    if last.skin is None:
        # a frame the pipeline cannot turn into a surface is an outcome of the scan, as on a real robot: the tap
        # is kept with no points and the reason, and its region is merged from the taps that have points
        return (np.empty((0, 3)), origin, pairs[-1][1].validity,
                f"too few markers identified for a surface ({last.n_matched} of {design.marker_count})")
    return np.asarray(last.skin.xyz_mm, dtype=np.float64), origin, pairs[-1][1].validity, None


def _tap_outcome(job: TapJob):
    """A tap on its back end: (points (N, 3) sensor frame, origin (3,), physics verdict or None, why there are no
    points or None). The ideal back end has no physics to check and always gives points."""
    if job.sensor == "ideal":
        return _ideal_tap(job), job.origin_mm(), None, None
    if job.sensor == "twin":
        return _twin_tap(job)
    raise TerrainScanError(f"unknown sensor back end {job.sensor!r} (ideal, twin)")


def run_tap(job: TapJob) -> str:
    """Run one tap and write its file (atomically); returns the path. Top-level for spawn pickling."""
    t0 = time.perf_counter()
    pts, origin, validity, failure = _tap_outcome(job)
    from pipeline.io.atomic import atomic_open

    with atomic_open(job.path, "wb") as fh:
        np.savez_compressed(fh, points_sensor_mm=pts, origin_mm=origin, region=job.region,
                            index=job.index, sensor=job.sensor, wall_s=time.perf_counter() - t0, key=job.key(),
                            validity_json=json.dumps(validity), failure=failure or "")
    return str(job.path)


class Tap(NamedTuple):
    """A finished tap as its file holds it."""

    points_sensor_mm: np.ndarray   # (N, 3) outer-skin points, sensor frame
    origin_mm: np.ndarray          # (3,) global position of the undeformed skin centre at the bottom of the tap
    validity: dict | None          # the physics verdict (twin.validity.FrameValidity as a dict: valid,
    #                                reasons, penetration max/p99, ...), None for the 'ideal' back end
    failure: str | None = None     # why the tap has no points (its frame could not be reconstructed), else None


def load_tap(path: str | Path, key: str | None = None) -> Tap:
    """Points, origin and physics verdict of a tap file; :class:`TerrainScanError` naming the file if it is
    unreadable, truncated, holds non-finite or misshapen arrays or an unreadable verdict, or (``key``
    given) was computed from other inputs."""
    try:
        # our own handle: np.load leaves a file it opened itself open when the zip is truncated
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as f:
            pts, origin = np.asarray(f["points_sensor_mm"]), np.asarray(f["origin_mm"])
            stored = str(f["key"]) if "key" in f.files else None
            validity_json = str(f["validity_json"]) if "validity_json" in f.files else None
            failure = str(f["failure"]) if "failure" in f.files else ""
    except (OSError, KeyError, ValueError, TypeError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise TerrainScanError(f"tap file {path}: unreadable or truncated ({type(exc).__name__})") from None
    if key is not None and stored != key:
        raise TerrainScanError(f"tap file {path}: computed from other inputs (resume key differs)")
    if (pts.ndim != 2 or pts.shape[1] != 3 or origin.shape != (3,) or pts.dtype.kind != "f"
            or not np.all(np.isfinite(pts)) or not np.all(np.isfinite(origin))):
        raise TerrainScanError(f"tap file {path}: points must be finite (N, 3) and the origin (3,)")
    if len(pts) == 0 and not failure:
        raise TerrainScanError(f"tap file {path}: no points and no reason")
    try:
        validity = json.loads(validity_json) if validity_json is not None else None
    except ValueError as exc:
        raise TerrainScanError(f"tap file {path}: unreadable validity record ({type(exc).__name__})") from None
    return Tap(pts, origin, validity, failure or None)


def _tap_is_done(job: TapJob) -> bool:
    if not Path(job.path).is_file():
        return False
    try:
        load_tap(job.path, key=job.key())
    except TerrainScanError:
        return False
    return True


# ----- the experiment -----------------------------------------------------------------------

def _region_keys(regions: Sequence[str] | str, quick: bool) -> list[str]:
    """The region keys asked for, each checked against the known regions."""
    if isinstance(regions, str):
        keys = (list(QUICK_REGIONS) if quick else list(REGIONS)) if regions == "all" else \
            [k.strip() for k in regions.split(",") if k.strip()]
    else:
        keys = list(regions)
    for k in keys:
        region(k)  # validates the name
    return keys


def _check_options(sensor: str, tap_z_mm: float) -> None:
    if sensor not in ("ideal", "twin"):
        raise TerrainScanError(f"unknown sensor back end {sensor!r} (ideal, twin)")
    if not (isinstance(tap_z_mm, (int, float)) and math.isfinite(tap_z_mm) and TAP_Z_RANGE_MM[0] <= tap_z_mm
            < TAP_Z_RANGE_MM[1]):
        raise TerrainScanError(f"--tap-z {tap_z_mm!r}: must be in [{TAP_Z_RANGE_MM[0]:g}, {TAP_Z_RANGE_MM[1]:g}) mm "
                               "(from the ocean floor to below the 8 mm approach height)")


def _run_taps(todo: list[TapJob], n_total: int, *, workers: int | None, engine, progress: bool):
    """Compute the taps not yet on disk; returns the engine used. Raises naming the taps that failed."""
    n_reused = n_total - len(todo)
    if progress or n_reused:
        import sys

        print(f"[terrain] reusing {n_reused} of {n_total} finished tap(s) (same region, tap, tap plane, sensor, "
              f"seed, design and tap code); computing {len(todo)}", file=sys.stderr, flush=True)
    from benchmarks.executor import InlineEngine, LocalEngine, in_cell, run_cells

    if engine is None:
        engine = InlineEngine() if in_cell() and not workers else \
            LocalEngine(max(1, min(workers or os.cpu_count() or 1, max(1, len(todo)))))
    outcomes = run_cells(run_tap, [(j,) for j in todo], engine=engine, desc="terrain taps", progress=progress,
                         already_done=n_reused)
    failed = [(j, o.error) for j, o in zip(todo, outcomes) if not o.ok]
    if failed:  # every other tap is on disk: a rerun computes only these
        raise TerrainScanError(f"{len(failed)} of {len(todo)} tap(s) failed (the others are kept for a resumed run): "
                               + "; ".join(f"{j.region}#{j.index}: {(e or '').splitlines()[0]}" for j, e in failed))
    return engine


def _physics_health(verdicts: list[dict | None]) -> dict[str, Any]:
    """A region with a tap whose skin passed into the relief, did not settle or drew MuJoCo warnings is
    marked invalid (and kept out of the scan's scores by the experiment)."""
    checked = [v for v in verdicts if v is not None]
    bad = [v for v in checked if not v.get("valid", False)]
    return dict(physics_checked=bool(checked), n_taps_invalid=len(bad), physics_valid=not bad,
                penetration_max_mm=max((float(v.get("penetration_max_mm") or 0.0) for v in checked),
                                       default=float("nan")),
                invalid_reasons=sorted({r for v in bad for r in v.get("reasons", [])}))


def _region_result(out: Path, key: str, js: list[TapJob], tmap, tap_z_mm: float) -> dict[str, Any]:
    """Merge a region's taps, grid and score them against the DEM, write its height map, points and figure."""
    from twin.terrain import lat_from_y_mm, lon_from_x_mm

    r = region(key)
    taps, verdicts, failed = [], [], []
    for j in js:
        tap = load_tap(j.path, key=j.key())
        verdicts.append(tap.validity)
        if tap.failure:
            failed.append(f"{key}#{j.index}: {tap.failure}")
        else:
            taps.append(tap_points_to_global(tap.points_sensor_mm, tap.origin_mm))
    merged = merge_taps(taps or [np.empty((0, 3))], threshold_mm=OVERLAP_THRESHOLD_MM, eps_mm=MOLLIFIER_EPS_MM)
    x0, x1, y0, y1 = r.box_mm()
    xs = np.arange(x0, x1 + 1e-9, GRID_STEP_MM)
    ys = np.arange(y0, y1 + 1e-9, GRID_STEP_MM)
    recon = grid_points(merged.points_mm, xs, ys, max_gap_mm=MAX_GAP_MM)
    X, Y = np.meshgrid(xs, ys)
    truth = HeightMap(xs, ys, tmap.sample_z_mm(X, Y, frame="global"))
    li = np.clip(np.searchsorted(tmap.lat_deg, lat_from_y_mm(Y)), 0, len(tmap.lat_deg) - 1)
    lj = np.clip(np.searchsorted(tmap.lon_deg, lon_from_x_mm(X)), 0, len(tmap.lon_deg) - 1)
    land = tmap.land[li, lj]
    metrics = score_region(key, recon, truth, land, tap_z_mm)
    metrics.update(_physics_health(verdicts))
    metrics.update(n_taps_unreconstructed=len(failed), unreconstructed_taps=failed)
    metrics.update(n_taps=len(js), n_points_raw=int(len(merged.selection.points_mm)),
                   n_points_merged=int(len(merged.points_mm)),
                   n_overlap_points=int(merged.selection.overlap.sum()))
    recon.save_npz(out / f"{key}_height.npz")
    write_ply(out / f"{key}_points.ply", merged.points_mm,
              comment="StereoTacTip terrain scan, global frame (z = 0 at sea level), mm")
    centres = np.array([j.centre_mm for j in js])
    region_panel(out / f"{key}.png", f"{r.name}: {len(js)} taps, RMS {metrics['rms_err_mm']:.2f} mm "
                 f"(reachable {metrics['rms_err_reachable_mm']:.2f} mm), resolved: {metrics['resolved']}",
                 truth, recon, centres)
    return {"metrics": metrics, "recon": recon}


def run_scan(out_dir: str | Path, *, regions: Sequence[str] | str = "all", sensor: str = "ideal",
             quick: bool = False, workers: int | None = None, tap_z_mm: float = 0.0, seed: int = 0,
             progress: bool = True, engine=None, setup=None) -> dict[str, Any]:
    """Run (or resume) the terrain scan and write every output; returns the ``terrain.json`` dict.

    ``regions``: ``"all"``, a comma-separated string or a list of region keys. ``quick``: the two
    small regions of :data:`QUICK_REGIONS` (unless regions are given) with at most 4 taps each.
    ``workers``: processes for the taps (default: all cores); taps already on disk are not rerun.
    ``engine``: where the taps run instead (:mod:`benchmarks.executor`, e.g. a Dask cluster whose
    workers share ``out_dir``: each tap writes its own file). A tap that fails does not stop the others;
    the scan then raises naming the failed taps, and a rerun computes only those.
    ``setup``: the :class:`benchmarks.estimated.SensorSetup` of the 'twin' back end (None: the twin's exact sensor).
    """
    from twin.terrain import load_terrain_map

    t_start = time.perf_counter()
    out = Path(out_dir)
    (out / "taps").mkdir(parents=True, exist_ok=True)
    keys = _region_keys(regions, quick)
    _check_options(sensor, tap_z_mm)
    jobs = plan_jobs(keys, out, sensor=sensor, tap_z_mm=tap_z_mm, seed=seed, max_taps=4 if quick else None)
    if setup is not None and sensor == "twin":
        jobs = {k: [dataclasses.replace(j, setup=setup) for j in js] for k, js in jobs.items()}
    todo = [j for js in jobs.values() for j in js if not _tap_is_done(j)]
    n_total = sum(len(js) for js in jobs.values())
    engine = _run_taps(todo, n_total, workers=workers, engine=engine, progress=progress)

    tmap = load_terrain_map()
    results = {key: _region_result(out, key, js, tmap, tap_z_mm) for key, js in jobs.items()}
    world_panel(out / "world.png", tmap, results)

    from benchmarks.results import git_commit

    design = _design()
    record = {
        "experiment": "terrain", "sensor": sensor, "design": design.name, "seed": seed, "commit": git_commit(),
        "quick": quick, "units": {"length": "mm", "frame": "global: x east from 180E, y north from 90S, z up, 0 at sea level"},
        "tap_plane_z_mm": tap_z_mm, "approach_z_mm": 8.0, "step_mm": 15.0,
        "overlap_threshold_mm": OVERLAP_THRESHOLD_MM, "mollifier_eps_mm": MOLLIFIER_EPS_MM,
        "terrain_source": tmap.source, "criteria": FEATURE_CRITERIA,
        "n_taps": n_total, "n_taps_run_now": len(todo), "n_taps_reused": n_total - len(todo),
        "workers": engine.workers, "engine": engine.describe(),
        "wall_time_s": time.perf_counter() - t_start,
        "regions": {k: v["metrics"] for k, v in results.items()},
    }
    from pipeline.io.atomic import atomic_write_json

    atomic_write_json(out / "terrain.json", record, indent=2, default=float)
    return record
