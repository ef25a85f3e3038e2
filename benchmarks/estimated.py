"""What a user's sensor and calibration session hand the pipeline, instead of the twin's exact values.

The twin knows its cameras, refractive index and stack thicknesses exactly; a user does not:

* the stereo calibration is estimated from chessboard pairs (``stereotactip calibrate``:
  :func:`pipeline.geometry.calibration.calibrate_stereo` on the twin's skin-less chessboard renders,
  :func:`twin.render.render_chessboard_pairs`), with the left camera placed at the design's nominal pose;
* the gel index is fitted from a skin-less marker-board press (``stereotactip calibrate-refraction``:
  :func:`pipeline.geometry.index_fit.fit_index_from_press` on frames the twin renders through its true stack);
* the built stack differs from its drawing within manufacturing tolerances: gel thickness
  ±:data:`GEL_TOL_MM`, acrylic thickness ±:data:`ACRYLIC_TOL_MM`, gel index ±:data:`INDEX_TOL`
  (uniform draws from a seeded stream per design).

:func:`sensor_setup` returns the pair of designs (the twin renders and simulates ``twin_design``,
the pipeline is given the nominal ``design``), the calibration and index the pipeline uses, and the
provenance to record. ``mode="oracle"`` is the twin's exact values (the experiments' default).
``sources`` selects the error sources of ``mode="estimated"`` for an ablation: any subset of
:data:`SOURCES`; a source left out takes its exact value.

The chessboard calibration costs seconds: it is cached per design and seed under ``cache_dir``
(OpenCV YAML), and so is the index fit (JSON, keyed by design, seed and sources). A design enters a cache
name by its name and the digest of its content (:func:`pipeline.design.design_digest`), so an edited design,
or an edited base it extends, is calibrated afresh.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from pipeline.design import SensorDesign, design_digest
from pipeline.errors import UserError
from pipeline.types import StereoCalibration

__all__ = ["MODES", "SOURCES", "GEL_TOL_MM", "ACRYLIC_TOL_MM", "INDEX_TOL", "CHESSBOARD_PAIRS",
           "PRESS_STEPS_MM", "SensorSetup", "SetupError", "parse_sources", "draw_stack",
           "estimated_calibration", "fitted_index", "sensor_setup"]

MODES = ("oracle", "estimated")
SOURCES = ("calibration", "index", "thickness")
GEL_TOL_MM = 0.2
ACRYLIC_TOL_MM = 0.1
INDEX_TOL = 0.02
CHESSBOARD_PAIRS = 20                       # the paper's calibration set (Sec. III-B-1)
# skin-less board press for the index fit, mm into the bare gel (paper: 0-8 mm). It starts at 2 mm: the
# Reconstructor's stereo check rejects a board above the rest marker depth (pins.height_mm below the gel surface)
# as a marker bulging out of the skin, so at 0 mm nothing is reconstructed.
PRESS_STEPS_MM = (2.0, 3.5, 5.0, 6.5, 8.0)


class SetupError(UserError, ValueError):
    """Unknown calibration mode or error source."""


@dataclass(frozen=True)
class SensorSetup:
    """The twin's sensor and what the pipeline is told about it.

    ``twin_design`` the sensor as built (the twin renders and simulates it; truth lives in its frame);
    ``design`` the drawing the pipeline is given; ``calib`` and ``n_gel`` the calibration and gel index
    the pipeline uses (``n_gel`` None: the design's own); ``provenance`` JSON-ready record of the mode,
    sources, drawn perturbations and fitted values.
    """

    twin_design: SensorDesign
    design: SensorDesign
    calib: StereoCalibration
    n_gel: float | None = None
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def mode(self) -> str:
        return str(self.provenance.get("mode", "oracle"))

    def reconstructor_kw(self) -> dict[str, Any]:
        """Keyword arguments for :class:`pipeline.runner.Reconstructor` beyond design and calibration."""
        return {} if self.n_gel is None else {"n_gel": float(self.n_gel)}


def parse_sources(sources: str | Iterable[str] | None) -> tuple[str, ...]:
    """``"calibration,index"`` / an iterable / None (all) → a sorted tuple of :data:`SOURCES`."""
    if sources is None:
        return SOURCES
    items = [s.strip() for s in (sources.split(",") if isinstance(sources, str) else sources) if s.strip()]
    bad = [s for s in items if s not in SOURCES]
    if bad or not items:
        raise SetupError(f"error sources {sources!r}: choose one or more of {', '.join(SOURCES)}")
    return tuple(s for s in SOURCES if s in items)


def _rng(seed: int, stream: str) -> np.random.Generator:
    from benchmarks.registry import stream_rng

    return stream_rng(seed, stream)


def draw_stack(design: SensorDesign, seed: int) -> dict[str, float]:
    """Manufacturing deviations of one built sensor (uniform within the tolerances), seeded by design and seed:
    ``{"gel_thickness_mm": dG, "acrylic_thickness_mm": dA, "gel_n": dn}`` (added to the drawing's values)."""
    rng = _rng(seed, f"estimated/stack/{design.name}")
    return {"gel_thickness_mm": float(rng.uniform(-GEL_TOL_MM, GEL_TOL_MM)),
            "acrylic_thickness_mm": float(rng.uniform(-ACRYLIC_TOL_MM, ACRYLIC_TOL_MM)),
            "gel_n": float(rng.uniform(-INDEX_TOL, INDEX_TOL))}


def _cache_file(cache_dir: Path | None, name: str) -> Path | None:
    return None if cache_dir is None else Path(cache_dir) / name


def estimated_calibration(design: SensorDesign, seed: int, *, cache_dir: Path | None = None,
                          n_pairs: int = CHESSBOARD_PAIRS, progress: bool = False) -> tuple[StereoCalibration, dict]:
    """The stereo calibration ``stereotactip calibrate`` estimates from ``n_pairs`` chessboard pairs the twin
    renders of ``design`` (poses and noise seeded by design and seed); (calibration, report summary dict).

    The stack does not enter: the boards are seen through air and the cameras do not depend on it.
    Cached as ``<cache_dir>/calib-<design>-<digest>-seed<seed>-pairs<n>.yaml`` (+ ``.json`` with the report)."""
    import json

    from pipeline.io.atomic import atomic_write_json
    from pipeline.geometry.calibration import calibrate_stereo
    from twin.render import render_chessboard_pairs, true_calibration

    stem = f"calib-{design.name}-{design_digest(design)}-seed{int(seed)}-pairs{int(n_pairs)}"
    yaml_path, json_path = _cache_file(cache_dir, stem + ".yaml"), _cache_file(cache_dir, stem + ".json")
    if yaml_path is not None and yaml_path.is_file() and json_path.is_file():
        return StereoCalibration.load_yaml(yaml_path), {**json.loads(json_path.read_text()), "cached": True}
    pairs = render_chessboard_pairs(design, n_pairs, _rng(seed, f"estimated/chessboard/{design.name}"),
                                    progress=progress)
    calib, report = calibrate_stereo(pairs, board_squares=(9, 7), square_mm=4.0,
                                     sensor_from_left=design.camera_poses()["left"])
    truth = true_calibration(design)
    dR = calib.R @ truth.R.T
    info = {"pairs": int(n_pairs), "pairs_used": len(report.used), "rms_px": float(report.rms_px),
            "baseline_error_mm": float(calib.baseline_mm - truth.baseline_mm),
            "rotation_error_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))}
    info["focal_error_max_px"] = float(max(abs(est[i, i] - tru[i, i]) for est, tru in
                                           ((calib.K1, truth.K1), (calib.K2, truth.K2)) for i in (0, 1)))
    if yaml_path is not None:
        yaml_path.parent.mkdir(parents=True, exist_ok=True)
        calib.save_yaml(yaml_path)
        atomic_write_json(json_path, info)
    return calib, {**info, "cached": False}


def fitted_index(twin_design: SensorDesign, design: SensorDesign, calib: StereoCalibration, seed: int, *,
                 key: str, cache_dir: Path | None = None, progress: bool = False) -> dict:
    """The gel index ``stereotactip calibrate-refraction`` fits from a skin-less board press: the twin renders
    the board through ``twin_design``'s stack at :data:`PRESS_STEPS_MM`, the pipeline (``design``, ``calib``)
    matches it. Returns the fit as a dict (``n`` the exact model's gel index, which the pipeline's default exact
    correction uses; ``n_linear_effective`` the linear model's; ``steps_mm``); cached
    under ``cache_dir`` as ``index-<key>.json``."""
    import gc
    import json

    from pipeline.io.atomic import atomic_write_json
    from pipeline.geometry.index_fit import fit_index_from_press
    from twin.render import StereoRenderer

    path = _cache_file(cache_dir, f"index-{key}.json")
    if path is not None and path.is_file():
        return {**json.loads(path.read_text()), "cached": True}
    renderer = StereoRenderer(twin_design, rng=_rng(seed, f"estimated/press/{twin_design.name}"))
    frames = []
    for d in PRESS_STEPS_MM:   # board face pressed d mm into the bare gel, whose free surface is z = -skin thickness
        pose = np.eye(4)
        pose[2, 3] = -twin_design.skin.thickness_mm - d
        frames.append(renderer.render_board("marker_board", pose, through_stack=True))
    del renderer
    gc.collect()  # one headless GL context at a time
    fit = fit_index_from_press(frames, PRESS_STEPS_MM, design, calib, progress=progress, echo=lambda s: None)
    info = {"n": float(fit.n_gel_exact), "exact_residual_rms_mm": fit.exact_residual_rms_mm,
            "n_linear_effective": float(fit.linear.n), "linear_r2": float(fit.linear.r2),
            "samples": int(fit.linear.n_points), "steps_mm": list(PRESS_STEPS_MM)}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(path, info)
    return {**info, "cached": False}


def sensor_setup(design: SensorDesign, *, mode: str = "oracle", seed: int = 0,
                 sources: str | Iterable[str] | None = None, cache_dir: Path | None = None,
                 progress: bool = False) -> SensorSetup:
    """The twin's sensor and the pipeline's knowledge of it, for ``mode`` in :data:`MODES` (see module doc)."""
    from twin.render import true_calibration

    if mode not in MODES:
        raise SetupError(f"calibration mode {mode!r}: choose one of {', '.join(MODES)}")
    if mode == "oracle":
        return SensorSetup(design, design, true_calibration(design), None,
                           {"mode": "oracle", "note": "the pipeline is given the twin's exact cameras, index and stack"})
    srcs = parse_sources(sources)
    drawn = draw_stack(design, seed)
    o = design.optics
    applied = {"optics.gel_thickness_mm": o.gel_thickness_mm + drawn["gel_thickness_mm"],
               "optics.acrylic_thickness_mm": o.acrylic_thickness_mm + drawn["acrylic_thickness_mm"]} \
        if "thickness" in srcs else {}
    if "index" in srcs:
        applied["optics.gel_n"] = o.gel_n + drawn["gel_n"]
    twin_design = design.with_overrides(applied, name=design.name) if applied else design
    prov: dict[str, Any] = {"mode": "estimated", "sources": list(srcs), "seed": int(seed),
                            "tolerances": {"gel_thickness_mm": GEL_TOL_MM, "acrylic_thickness_mm": ACRYLIC_TOL_MM,
                                           "gel_n": INDEX_TOL},
                            "drawn": {k: (v if (k == "gel_n" and "index" in srcs) or
                                          (k != "gel_n" and "thickness" in srcs) else 0.0)
                                      for k, v in drawn.items()},
                            "true_stack": {"gel_thickness_mm": twin_design.optics.gel_thickness_mm,
                                           "acrylic_thickness_mm": twin_design.optics.acrylic_thickness_mm,
                                           "gel_n": twin_design.optics.gel_n},
                            "assumed_stack": {"gel_thickness_mm": o.gel_thickness_mm,
                                              "acrylic_thickness_mm": o.acrylic_thickness_mm, "gel_n": o.gel_n}}
    if "calibration" in srcs:
        calib, info = estimated_calibration(design, seed, cache_dir=cache_dir, progress=progress)
        prov["calibration"] = {"route": "chessboard (calibrate_stereo)", **info}
    else:
        calib = true_calibration(design)
        prov["calibration"] = {"route": "exact (twin cameras, nominal pose)"}
    n_gel = None
    if "index" in srcs:
        key = f"{design.name}-{design_digest(design)}-seed{int(seed)}-{'+'.join(srcs)}"
        fit = fitted_index(twin_design, design, calib, seed, key=key, cache_dir=cache_dir, progress=progress)
        n_gel = fit["n"]
        prov["index"] = {"route": "skin-less board press (fit_index_from_press)", **fit}
        prov["assumed_stack"]["gel_n"] = n_gel
    else:
        prov["index"] = {"route": "exact (the drawing's gel_n)"}
    return SensorSetup(twin_design, design, calib, n_gel, prov)
