"""A parsed design mapping checked key by key and value by value, and turned into a :class:`SensorDesign`."""

from __future__ import annotations

import math
from typing import Any, Mapping

from pipeline.design.layout import analytic_pattern_radius_mm
from pipeline.design.schema import (PATTERN_KINDS, PATTERN_MAPPINGS, TWIN_KEYS, Camera, Cameras, DesignError, Gel,
                                    Markers, MonoCamera, Optics, Pattern, Pins, Skin)
from pipeline.design.sensor import SensorDesign
from pipeline.types.calibration import FOCAL_PER_WIDTH_RANGE, MAX_ABS_DISTORTION, lens_folds_over

_SCHEMA: dict[str, dict[str, type | tuple[type, ...]]] = {
    "pattern": {"kind": str, "layers": int, "links": int, "separation_mm": float, "dome_height_mm": float},
    "skin": {"thickness_mm": float, "material": str, "youngs_modulus_mpa": float, "poisson_ratio": float,
             "source": str},
    "pins": {"height_mm": float, "diameter_mm": float, "youngs_modulus_mpa": float},
    "markers": {"diameter_mm": float, "thickness_mm": float},
    "optics": {"air_gap_mm": float, "acrylic_thickness_mm": float, "acrylic_n": float,
               "gel_thickness_mm": float, "gel_n": float},
    "gel": {"material": str, "youngs_modulus_mpa": float, "poisson_ratio": float, "radius_mm": float,
            "source": str},
    "cameras": {"width_px": int, "height_px": int, "fps": float, "baseline_mm": float, "toe_in_deg": float,
                "model_note": str, "left": dict, "right": dict},
}
_CAMERA_KEYS = {"fx_px": float, "fy_px": float, "cx_px": float, "cy_px": float, "dist": list}
_MONO_KEYS = {"width_px": int, "height_px": int, "fps": float, "model_note": str, **_CAMERA_KEYS}
_MONO_OPTIONAL = {"x_mm": float, "y_mm": float, "roll_deg": float}
_PATTERN_OPTIONAL = {"mapping": str}
_OPTIONAL_SECTIONS = ("camera", "twin")
_TOP = {"name": str, "description": str}
#: Keys about the file itself, never inherited through ``extends``: a design's name and description are its
#: own, and a base's ``abstract`` mark is not passed to the designs built on it.
_CHAIN_KEYS = ("name", "description", "extends", "abstract")


def _check(value: Any, typ: type, where: str) -> Any:
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise DesignError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise DesignError(f"{where}: must be finite, got {value!r}")
        return float(value)
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise DesignError(f"{where}: expected an integer, got {value!r}")
        return int(value)
    if not isinstance(value, typ):
        raise DesignError(f"{where}: expected {typ.__name__}, got {value!r}")
    return value


def _section(raw: Mapping[str, Any], keys: Mapping[str, type], where: str,
             optional: Mapping[str, type] | None = None) -> dict[str, Any]:
    optional = optional or {}
    unknown = sorted(set(raw) - set(keys) - set(optional))
    if unknown:
        raise DesignError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join([*keys, *optional])})")
    missing = [k for k in keys if k not in raw]
    if missing:
        raise DesignError(f"{where}: missing key {missing[0]!r}")
    out = {k: _check(raw[k], t, f"{where}.{k}") for k, t in keys.items()}
    out.update({k: _check(raw[k], t, f"{where}.{k}") for k, t in optional.items() if k in raw})
    return out


def _dist(values: list, where: str) -> tuple[float, ...]:
    if len(values) != 5:
        raise DesignError(f"{where}: expected 5 coefficients (k1, k2, p1, p2, k3)")
    return tuple(_check(d, float, where) for d in values)


def design_from_dict(raw: Mapping[str, Any], *, source: str = "<dict>", where: str | None = None) -> SensorDesign:
    """Validate a parsed design mapping; errors name ``where`` (default ``source``) and the offending key.

    The mapping is a whole design: ``extends`` is resolved by :func:`load_design`, which reads files."""
    where = source if where is None else where
    if "extends" in raw:
        raise DesignError(f"{where}: extends: a base is merged in when a design file is loaded "
                          f"(load_design), not in a parsed mapping")
    if raw.get("abstract") is True:
        raise DesignError(f"{where}: is a base (abstract = true), not a design")
    raw = {k: v for k, v in raw.items() if not (k == "abstract" and v is False)}
    allowed = set(_TOP) | set(_SCHEMA) | set(_OPTIONAL_SECTIONS)
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise DesignError(f"{where}: unknown key {unknown[0]!r}")
    mono = "camera" in raw
    if mono and "cameras" in raw:
        raise DesignError(f"{where}: give either a stereo [cameras] block or a monocular [camera] block, not both")
    required = [k for k in list(_TOP) + list(_SCHEMA) if not (mono and k == "cameras")]
    for k in required:
        if k not in raw:
            raise DesignError(f"{where}: missing key {k!r}" + (" (or a monocular [camera] block)"
                                                                if k == "cameras" else ""))
    top = {k: _check(raw[k], t, f"{where}: {k}") for k, t in _TOP.items()}

    def table(name: str) -> Mapping[str, Any]:
        return raw[name] if isinstance(raw[name], Mapping) else _check(raw[name], dict, f"{where}: {name}")

    sec = {name: _section(table(name), keys, f"{where}: {name}",
                          _PATTERN_OPTIONAL if name == "pattern" else None)
           for name, keys in _SCHEMA.items() if name in raw}

    cameras = camera = None
    if mono:
        c = _section(table("camera"), _MONO_KEYS, f"{where}: camera", _MONO_OPTIONAL)
        c["dist"] = _dist(c["dist"], f"{where}: camera.dist")
        camera = MonoCamera(**c)
    else:
        cams = {}
        for side in ("left", "right"):
            c = _section(sec["cameras"][side], _CAMERA_KEYS, f"{where}: cameras.{side}")
            c["dist"] = _dist(c["dist"], f"{where}: cameras.{side}.dist")
            cams[side] = Camera(**c)
        cam_fields = {k: v for k, v in sec["cameras"].items() if k not in ("left", "right")}
        cameras = Cameras(**cam_fields, left=cams["left"], right=cams["right"])
    twin: tuple[tuple[str, float], ...] = ()
    if "twin" in raw:
        t = _section(table("twin"), {}, f"{where}: twin", {k: float for k in TWIN_KEYS})
        twin = tuple(sorted(t.items()))
    design = SensorDesign(
        name=top["name"], description=top["description"],
        pattern=Pattern(**sec["pattern"]), skin=Skin(**sec["skin"]), pins=Pins(**sec["pins"]),
        markers=Markers(**sec["markers"]), optics=Optics(**sec["optics"]), gel=Gel(**sec["gel"]),
        cameras=cameras, source_file=source, camera=camera, twin=twin,
    )
    _validate_values(design, where)
    return design


#: Physical-sense limits of a design (a fingertip-sized skin module seen by two small cameras).
MAX_LAYERS = 40               # 40 hexagon rings = 4681 markers; the built-in modules have 5-9
MAX_LINKS = 64
MAX_LENGTH_MM = 1000.0        # no part of a tactile skin module is a metre long
POISSON_RANGE = (0.0, 0.5)    # open interval: 0.5 is incompressible (no finite bulk modulus), <= 0 auxetic
MAX_YOUNGS_MPA = 1e6          # 1 TPa (diamond) is the stiffest solid there is
MAX_FRICTION = 10.0           # Coulomb coefficient; elastomers on clean hard surfaces reach ~3, nothing dry reaches 10
TOE_IN_RANGE_DEG = (-60.0, 60.0)
FPS_RANGE = (0.0, 10000.0)    # open at 0
# focal length per image width and distortion bounds: the calibration's (FOCAL_PER_WIDTH_RANGE, MAX_ABS_DISTORTION)
#: Each camera delivers one half of the 1280x480 concatenated frame.
CAMERA_SIZE_PX = (640, 480)


def _positive(value: float, where: str, upper: float = MAX_LENGTH_MM) -> None:
    if not 0 < value <= upper:
        raise DesignError(f"{where}: must be in (0, {upper:g}], got {value!r}")


def _validate_values(d: SensorDesign, where: str) -> None:
    """Physical sense, every check before anything is built from the numbers (the marker layout is
    never computed here: a design with a million layers is refused in microseconds)."""
    if d.pattern.kind not in PATTERN_KINDS:
        raise DesignError(f"{where}: pattern.kind: {d.pattern.kind!r} is not one of {PATTERN_KINDS}")
    if not 2 <= d.pattern.layers <= MAX_LAYERS:
        raise DesignError(f"{where}: pattern.layers: must be in [2, {MAX_LAYERS}], got {d.pattern.layers}")
    if not 1 <= d.pattern.links <= MAX_LINKS:
        raise DesignError(f"{where}: pattern.links: must be in [1, {MAX_LINKS}], got {d.pattern.links}")
    for key, value in ([("pattern.separation_mm", d.pattern.separation_mm), ("skin.thickness_mm", d.skin.thickness_mm),
                       ("pins.height_mm", d.pins.height_mm), ("pins.diameter_mm", d.pins.diameter_mm),
                       ("markers.diameter_mm", d.markers.diameter_mm),
                       ("markers.thickness_mm", d.markers.thickness_mm), ("optics.air_gap_mm", d.optics.air_gap_mm),
                       ("optics.acrylic_thickness_mm", d.optics.acrylic_thickness_mm),
                       ("optics.gel_thickness_mm", d.optics.gel_thickness_mm), ("gel.radius_mm", d.gel.radius_mm)]
                       + ([("cameras.baseline_mm", d.cameras.baseline_mm)] if d.cameras is not None else [])):
        _positive(value, f"{where}: {key}")
    for key, value in [("skin.youngs_modulus_mpa", d.skin.youngs_modulus_mpa),
                       ("gel.youngs_modulus_mpa", d.gel.youngs_modulus_mpa),
                       ("pins.youngs_modulus_mpa", d.pins.youngs_modulus_mpa)]:
        _positive(value, f"{where}: {key}", MAX_YOUNGS_MPA)
    for key, nu in [("skin.poisson_ratio", d.skin.poisson_ratio), ("gel.poisson_ratio", d.gel.poisson_ratio)]:
        if not POISSON_RANGE[0] < nu < POISSON_RANGE[1]:
            raise DesignError(f"{where}: {key}: must be in ({POISSON_RANGE[0]:g}, {POISSON_RANGE[1]:g}), got {nu!r}")
    if not 0.0 <= d.twin_params()["friction"] <= MAX_FRICTION:
        raise DesignError(f"{where}: twin.friction: must be a Coulomb coefficient in [0, {MAX_FRICTION:g}], "
                          f"got {d.twin_params()['friction']!r}")
    if not 0 <= d.pattern.dome_height_mm <= MAX_LENGTH_MM:
        raise DesignError(f"{where}: pattern.dome_height_mm: must be in [0, {MAX_LENGTH_MM:g}], "
                          f"got {d.pattern.dome_height_mm!r}")
    for key, n in [("optics.acrylic_n", d.optics.acrylic_n), ("optics.gel_n", d.optics.gel_n)]:
        if not 1.0 <= n <= 3.0:
            raise DesignError(f"{where}: {key}: refractive index {n} outside [1, 3]")
    # the stack, from the outside in: skin, then pins hanging into the gel, then the acrylic
    T, H, G = d.skin.thickness_mm, d.pins.height_mm, d.optics.gel_thickness_mm
    if T >= G:
        raise DesignError(f"{where}: skin.thickness_mm = {T:g} must be smaller than optics.gel_thickness_mm = {G:g}")
    if H >= G:
        raise DesignError(f"{where}: pins.height_mm = {H:g} must be smaller than optics.gel_thickness_mm = {G:g}")
    if d.markers.thickness_mm >= H:
        raise DesignError(f"{where}: markers.thickness_mm = {d.markers.thickness_mm:g} must be smaller than "
                          f"pins.height_mm = {H:g} (the marker is the pin's tip)")
    if d.markers.diameter_mm > d.pins.diameter_mm:
        raise DesignError(f"{where}: markers.diameter_mm = {d.markers.diameter_mm:g} must be at most "
                          f"pins.diameter_mm = {d.pins.diameter_mm:g} (the marker is the pin's tip)")
    if d.markers.diameter_mm >= d.pattern.separation_mm:
        raise DesignError(f"{where}: markers.diameter_mm must be smaller than pattern.separation_mm")
    if d.pins.diameter_mm >= d.pattern.separation_mm:
        raise DesignError(f"{where}: pins.diameter_mm = {d.pins.diameter_mm:g} must be smaller than "
                          f"pattern.separation_mm = {d.pattern.separation_mm:g} (neighbouring pins would touch)")
    a, h = d.gel.radius_mm, d.pattern.dome_height_mm
    if h > a:
        raise DesignError(f"{where}: pattern.dome_height_mm = {h:g} must be at most gel.radius_mm = {a:g} "
                          f"(a spherical cap over the gel is at most a hemisphere)")
    if H + h >= G:
        raise DesignError(f"{where}: pins.height_mm + pattern.dome_height_mm = {H + h:g} must be smaller than "
                          f"optics.gel_thickness_mm = {G:g} (the rim's markers would sit in the acrylic)")
    if d.pattern.mapping not in PATTERN_MAPPINGS:
        raise DesignError(f"{where}: pattern.mapping: {d.pattern.mapping!r} is not one of {PATTERN_MAPPINGS}")
    radius = analytic_pattern_radius_mm(d.pattern)
    if d.pattern.mapping == "arc":
        if h <= 0:
            raise DesignError(f"{where}: pattern.mapping = 'arc' lays the pattern on a dome: "
                              f"pattern.dome_height_mm must be > 0")
        R = (a * a + h * h) / (2 * h)
        arc = R * math.asin(min(a / R, 1.0)) if h <= R else R * (math.pi - math.asin(a / R))
        if radius + d.pattern.separation_mm / 2 > arc:
            raise DesignError(f"{where}: the marker pattern (arc radius {radius:.2f} mm) does not fit on the dome "
                              f"(arc length {arc:.2f} mm from apex to rim)")
    elif radius + d.pattern.separation_mm / 2 > a:
        raise DesignError(f"{where}: the marker pattern (radius {radius:.2f} mm) does not fit "
                          f"inside gel.radius_mm = {a}")
    if d.camera is not None:
        _validate_mono(d, where)
        return
    c = d.cameras
    if (c.width_px, c.height_px) != CAMERA_SIZE_PX:
        raise DesignError(f"{where}: cameras.width_px x height_px must be {CAMERA_SIZE_PX[0]}x{CAMERA_SIZE_PX[1]} "
                          f"(each view of the 1280x480 stereo frame), got {c.width_px}x{c.height_px}")
    _validate_fps(c.fps, "cameras", where)
    if not TOE_IN_RANGE_DEG[0] < c.toe_in_deg < TOE_IN_RANGE_DEG[1]:
        raise DesignError(f"{where}: cameras.toe_in_deg: must be in ({TOE_IN_RANGE_DEG[0]:g}, "
                          f"{TOE_IN_RANGE_DEG[1]:g}) deg, got {c.toe_in_deg!r}")
    for side, cam in (("left", c.left), ("right", c.right)):
        _validate_lens(cam, (c.width_px, c.height_px), f"cameras.{side}", where)
        if lens_folds_over(cam.K, cam.D, (c.width_px, c.height_px)):
            raise DesignError(f"{where}: cameras.{side}.dist: the radial distortion folds over inside the "
                              f"{c.width_px}x{c.height_px} image (r_d must grow with r out to the corners)")


def _validate_fps(fps: float, key: str, where: str) -> None:
    if not FPS_RANGE[0] < fps <= FPS_RANGE[1]:
        raise DesignError(f"{where}: {key}.fps: must be in ({FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}], got {fps!r}")


def _validate_lens(cam: Camera | MonoCamera, size: tuple[int, int], key: str, where: str) -> None:
    """Focal lengths, principal point and distortion bounds of one camera (``key`` names its block)."""
    width, height = size
    lo, hi = FOCAL_PER_WIDTH_RANGE[0] * width, FOCAL_PER_WIDTH_RANGE[1] * width
    for k, f in (("fx_px", cam.fx_px), ("fy_px", cam.fy_px)):
        if not lo <= f <= hi:
            raise DesignError(f"{where}: {key}.{k}: must be in [{lo:g}, {hi:g}] px "
                              f"({FOCAL_PER_WIDTH_RANGE[0]:g}-{FOCAL_PER_WIDTH_RANGE[1]:g} x width_px), got {f!r}")
    if not (0 <= cam.cx_px <= width and 0 <= cam.cy_px <= height):
        raise DesignError(f"{where}: {key}: principal point ({cam.cx_px:g}, {cam.cy_px:g}) px must lie "
                          f"inside the {width}x{height} image")
    if max(abs(v) for v in cam.dist) > MAX_ABS_DISTORTION:
        raise DesignError(f"{where}: {key}.dist: coefficients must lie in [-{MAX_ABS_DISTORTION:g}, "
                          f"{MAX_ABS_DISTORTION:g}]")


def _validate_mono(d: SensorDesign, where: str) -> None:
    c = d.camera
    if not (16 <= c.width_px <= 8192 and 16 <= c.height_px <= 8192):
        raise DesignError(f"{where}: camera.width_px x height_px must each be in [16, 8192], "
                          f"got {c.width_px}x{c.height_px}")
    _validate_fps(c.fps, "camera", where)
    _validate_lens(c, (c.width_px, c.height_px), "camera", where)
    if abs(c.x_mm) >= d.gel.radius_mm or abs(c.y_mm) >= d.gel.radius_mm:
        raise DesignError(f"{where}: camera.x_mm / y_mm must lie inside gel.radius_mm = {d.gel.radius_mm:g}")
    if not -180.0 <= c.roll_deg <= 180.0:
        raise DesignError(f"{where}: camera.roll_deg: must be in [-180, 180], got {c.roll_deg!r}")
    t = d.twin_params()
    if not t["bending_ratio"] > 0 or not t["edge_px"] > 0 or t["noise_grey"] < 0 or not t["marker_scale"] > 0:
        raise DesignError(f"{where}: twin: bending_ratio, edge_px and marker_scale must be > 0, noise_grey >= 0")
    if not 0.0 <= t["pin_rotation"] <= 1.0:
        raise DesignError(f"{where}: twin.pin_rotation: must be in [0, 1] (the fraction of the skin's rotation "
                          f"the pins follow), got {t['pin_rotation']!r}")
    if not 0.0 <= t["tap_friction"] <= MAX_FRICTION:
        raise DesignError(f"{where}: twin.tap_friction: must be a Coulomb coefficient in [0, {MAX_FRICTION:g}], "
                          f"got {t['tap_friction']!r}")
    for key in ("marker_grey", "background_grey"):
        if not 0 <= t[key] <= 255:
            raise DesignError(f"{where}: twin.{key}: must be in [0, 255], got {t[key]!r}")
