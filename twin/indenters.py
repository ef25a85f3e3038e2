"""Rigid indenters: a registry of named, validated, parametric shapes.

Each indenter is described in its OWN frame, contact face up (+z), as it would sit on the desk:
``height(x_mm, y_mm)`` is the height of the contact face (NaN off the part) and ``top_mm`` its highest
point. The twin mounts it facing the sensor: a rotation of 180° about x, a yaw about the sensor axis
and a translation, so that at press depth ``d`` the indenter's top is at sensor ``z = -d``
(depth 0: the top touches the undeformed skin). :meth:`Indenter.sensor_heightmap` gives the surface
in the sensor frame; :func:`sensor_to_indenter_xy` is the one place the mounting is written down.

Registered names: ``gaussian``, ``sine``, ``sphere``, ``letter``, ``flat``, ``marker_board``, ``chessboard``,
``terrain`` (see :func:`list_indenters` / :func:`indenter_params`). Each also takes ``friction``, the skin's
Coulomb coefficient on the part's material (default: the design's).

Collision: every indenter collides in MuJoCo as a height field sampled from ``height`` (its true,
possibly non-convex shape — sine valleys, letter counters, terrain), never as a convex hull.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from pipeline.errors import UserError
from pipeline.types import HeightMap

__all__ = ["IndenterError", "Param", "Indenter", "make_indenter", "list_indenters", "indenter_params",
           "parse_params", "sensor_to_indenter_xy"]

COLLISION_SPACING_MM = 0.2   # height-field sampling of the collision shape (>= 5 samples per skin cell)
BASE_MM = 2.0                # thickness of the block below the lowest point of the contact face (mesh only)


class IndenterError(UserError, ValueError):
    """Unknown indenter name, unknown parameter or a parameter outside its valid range."""


@dataclass(frozen=True)
class Param:
    """One indenter parameter: default value, type and valid range (inclusive) or choices."""

    name: str
    default: Any
    kind: type = float
    lo: float | None = None
    hi: float | None = None
    choices: tuple = ()
    doc: str = ""

    def check(self, value: Any, where: str) -> Any:
        if self.kind is float:
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise IndenterError(f"{where}: {self.name} must be a number, got {value!r}") from None
            if not math.isfinite(v):
                raise IndenterError(f"{where}: {self.name} must be finite, got {value!r}")
            if (self.lo is not None and v < self.lo) or (self.hi is not None and v > self.hi):
                raise IndenterError(f"{where}: {self.name}={v:g} outside [{self.lo}, {self.hi}]")
            return v
        if self.kind is str:
            v = str(value)
            if self.choices and v not in self.choices:
                raise IndenterError(f"{where}: {self.name}={v!r} is not one of {', '.join(self.choices)}")
            return v
        if not isinstance(value, self.kind):
            raise IndenterError(f"{where}: {self.name} must be a {self.kind.__name__}, got {type(value).__name__}")
        return value


@dataclass(frozen=True, eq=False)
class Indenter:
    """A rigid indenter (own frame, mm, contact face up). Build with :func:`make_indenter`.

    Attributes
    ----------
    name, params : registry name and validated parameters
    half_size_mm : (hx, hy) half extent of the part in its own x and y (mm)
    top_mm : highest point of the contact face (mm)
    friction : the Coulomb coefficient of the skin on this part's material (e.g. a resin print smoother than a
        PLA one), or None for the design's ``[twin] friction``; a press's own ``friction`` overrides both
        (:func:`twin.stick.resolve_friction`)
    """

    name: str
    params: Mapping[str, Any]
    half_size_mm: tuple[float, float]
    _height: Callable[[np.ndarray, np.ndarray], np.ndarray] = field(repr=False)
    top_mm: float = 0.0
    friction: float | None = None

    def height(self, x_mm, y_mm) -> np.ndarray:
        """Contact-face height (mm) at own-frame points; NaN off the part. Broadcasts its inputs."""
        x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64))
        z = np.asarray(self._height(x, y), dtype=np.float64)
        hx, hy = self.half_size_mm
        return np.where((np.abs(x) <= hx + 1e-9) & (np.abs(y) <= hy + 1e-9), z, np.nan)

    def grid(self, spacing_mm: float = COLLISION_SPACING_MM) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Own-frame sample grid: ``x (W,), y (H,), z (H, W)`` (rows = y), NaN off the part."""
        hx, hy = self.half_size_mm
        nx, ny = max(2, int(round(2 * hx / spacing_mm)) + 1), max(2, int(round(2 * hy / spacing_mm)) + 1)
        x, y = np.linspace(-hx, hx, nx), np.linspace(-hy, hy, ny)
        return x, y, self.height(x[None, :], y[:, None])

    def mesh(self, spacing_mm: float = 0.25):
        """Closed trimesh of the part (own frame, mm): contact face + side walls + flat bottom."""
        import trimesh

        x, y, z = self.grid(spacing_mm)
        z = np.where(np.isfinite(z), z, np.nanmin(z))
        base = float(np.nanmin(z)) - BASE_MM
        H, W = z.shape
        gx, gy = np.meshgrid(x, y)
        top = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
        bot = np.column_stack([gx.ravel(), gy.ravel(), np.full(H * W, base)])
        idx = np.arange(H * W).reshape(H, W)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
        faces = [np.column_stack([a, b, c]), np.column_stack([a, c, d])]
        n = H * W
        faces += [np.column_stack([a + n, c + n, b + n]), np.column_stack([a + n, d + n, c + n])]
        ring = np.concatenate([idx[0, :], idx[1:, -1], idx[-1, -2::-1], idx[-2:0:-1, 0]])
        r0, r1 = ring, np.roll(ring, -1)
        faces += [np.column_stack([r0, r0 + n, r1]), np.column_stack([r1, r0 + n, r1 + n])]
        m = trimesh.Trimesh(np.vstack([top, bot]), np.vstack(faces), process=False)
        m.fix_normals()
        return m

    def sensor_heightmap(self, x_off_mm: float, y_off_mm: float, depth_mm: float, yaw_deg: float, *,
                         half_mm: float = 22.0, spacing_mm: float = 0.2) -> HeightMap:
        """The contact face in the sensor frame at a robot pose: ``z = top - height - depth`` (mm).

        Grid: square of half width ``half_mm`` around the sensor axis; NaN where the part is absent.
        """
        ax = np.arange(-half_mm, half_mm + 1e-9, spacing_mm)
        gx, gy = np.meshgrid(ax, ax)
        xi, yi = sensor_to_indenter_xy(gx, gy, x_off_mm, y_off_mm, yaw_deg)
        z = self.top_mm - self.height(xi, yi) - float(depth_mm)
        return HeightMap(ax, ax, z)


def sensor_to_indenter_xy(xs_mm, ys_mm, x_off_mm: float, y_off_mm: float, yaw_deg: float):
    """Sensor-frame x-y → the indenter's own x-y, for an indenter mounted facing the sensor.

    Mounting: own frame rotated 180° about x (contact face toward the skin), yawed by ``yaw_deg``
    about the sensor z axis, own origin at sensor ``(x_off, y_off)``.
    """
    u, v = np.asarray(xs_mm, float) - x_off_mm, np.asarray(ys_mm, float) - y_off_mm
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return c * u + s * v, -(-s * u + c * v)


# ----- shapes ----------------------------------------------------------------------------------

def _gaussian(p):
    h, s2 = p["h_mm"], p["sigma2_mm2"]
    half = p["half_size_mm"]
    return (half, half), lambda x, y: h * np.exp(-(x * x + y * y) / (2.0 * s2)), h


def _sine(p):
    a, w = p["amplitude_mm"], p["omega_rad_per_mm"]
    half = p["half_size_mm"]
    r0, rho = p["relief_radius_mm"], p["roll_off_radius_mm"]
    xs = np.linspace(-half, half, 4001)
    top = float(np.max(a * np.sin(w * xs)))
    if r0 <= 0:
        return (half, half), lambda x, y: a * np.sin(w * x) + 0.0 * y, top

    def h(x, y):
        # the relief inside r0; beyond it the plate rounds off downward along a parabola of apex radius rho,
        # whose curvature the face contact sees as that of a cap (twin.contact)
        d = np.maximum(np.hypot(x, y) - r0, 0.0)
        return a * np.sin(w * x) - d * d / (2.0 * rho)
    return (half, half), h, top


def _sphere(p):
    r = p["radius_mm"]
    return (r, r), lambda x, y: np.sqrt(np.maximum(r * r - x * x - y * y, 0.0)), r


def _grid_height(x_ax: np.ndarray, y_ax: np.ndarray, z: np.ndarray):
    from scipy.interpolate import RegularGridInterpolator

    f = RegularGridInterpolator((y_ax, x_ax), z, bounds_error=False, fill_value=np.nan)
    return lambda x, y: f(np.stack([y, x], axis=-1))


def _letter(p):
    import cv2

    ppm = 20.0                       # raster pixels per mm
    size, ext = p["size_mm"], p["height_mm"]
    font, thick_px = cv2.FONT_HERSHEY_SIMPLEX, max(1, int(round(p["stroke_mm"] * ppm)))
    scale = 1.0
    (tw, th), base = cv2.getTextSize(p["char"], font, scale, thick_px)
    scale = size * ppm / max(th + base, 1)
    (tw, th), base = cv2.getTextSize(p["char"], font, scale, thick_px)
    margin = int(3 * ppm)
    img = np.zeros((th + base + 2 * margin, tw + 2 * margin), np.uint8)
    cv2.putText(img, p["char"], (margin, margin + th), font, scale, 255, thick_px, cv2.LINE_AA)
    rows, cols = np.nonzero(img)
    rc, cc = (rows.min() + rows.max()) / 2.0, (cols.min() + cols.max()) / 2.0
    x_ax = (np.arange(img.shape[1]) - cc) / ppm
    y_ax = -(np.arange(img.shape[0]) - rc) / ppm          # image rows grow downward, own y upward
    z = img.astype(np.float64) / 255.0 * ext
    y_ax, z = y_ax[::-1], z[::-1]
    half = (min(-x_ax[0], x_ax[-1]), min(-y_ax[0], y_ax[-1]))
    return half, _grid_height(x_ax, y_ax, z), ext


def _flat(p):
    return (p["half_x_mm"], p["half_y_mm"]), lambda x, y: np.zeros(np.broadcast(x, y).shape), 0.0


def _terrain(p):
    hm: HeightMap = p["height_map"]
    z = np.asarray(hm.z_mm, dtype=np.float64)
    if not np.any(np.isfinite(z)):
        raise IndenterError("terrain: height_map has no finite heights")
    # sensor-frame rest surface z_s(x, y) -> own frame (contact face up): h(x, y) = -z_s(x, -y)
    x_ax = np.asarray(hm.x_mm, dtype=np.float64)
    y_ax = -np.asarray(hm.y_mm, dtype=np.float64)[::-1]
    h = -z[::-1]
    half = (min(-x_ax[0], x_ax[-1]), min(-y_ax[0], y_ax[-1]))
    if half[0] <= 0 or half[1] <= 0:
        raise IndenterError("terrain: height_map must span the origin in x and y")
    return half, _grid_height(x_ax, y_ax, h), float(np.nanmax(h))


_REGISTRY: dict[str, tuple[dict[str, Param], Callable]] = {
    "gaussian": ({"h_mm": Param("h_mm", 5.0, float, 0.1, 20.0, doc="peak height"),
                  "sigma2_mm2": Param("sigma2_mm2", 10.0, float, 0.1, 500.0, doc="variance σ² of z = h exp(-r²/2σ²)"),
                  "half_size_mm": Param("half_size_mm", 25.0, float, 5.0, 60.0, doc="half width of the block")},
                 _gaussian),
    "sine": ({"amplitude_mm": Param("amplitude_mm", 2.5, float, 0.1, 10.0, doc="A in z = A sin(ωx)"),
              "omega_rad_per_mm": Param("omega_rad_per_mm", 2 * math.pi / 15, float, 0.01, 5.0, doc="ω"),
              "half_size_mm": Param("half_size_mm", 25.0, float, 5.0, 60.0, doc="half width of the block"),
              "relief_radius_mm": Param("relief_radius_mm", 0.0, float, 0.0, 60.0,
                                        doc="radius of the sine relief; beyond it the plate rounds off downward "
                                            "(0: the relief covers the whole block)"),
              "roll_off_radius_mm": Param("roll_off_radius_mm", 2.0, float, 0.5, 100.0,
                                          doc="apex radius of the parabola the plate rounds off along beyond "
                                              "relief_radius_mm: the plate falls d^2 / (2 R) at d mm outside it")},
             _sine),
    "sphere": ({"radius_mm": Param("radius_mm", 10.0, float, 1.0, 19.0,
                                   doc="radius R of the spherical cap (contact mechanics checks: Hertz)")}, _sphere),
    "letter": ({"char": Param("char", "G", str, choices=("G", "e", "o"), doc="glyph"),
                "size_mm": Param("size_mm", 12.0, float, 3.0, 30.0, doc="glyph height"),
                "height_mm": Param("height_mm", 3.0, float, 0.5, 10.0, doc="extrusion height"),
                "stroke_mm": Param("stroke_mm", 1.6, float, 0.3, 5.0, doc="stroke width")},
               _letter),
    "flat": ({"half_x_mm": Param("half_x_mm", 25.0, float, 1.0, 100.0),
              "half_y_mm": Param("half_y_mm", 25.0, float, 1.0, 100.0)}, _flat),
    "marker_board": ({"half_x_mm": Param("half_x_mm", 25.0, float, 1.0, 100.0),
                      "half_y_mm": Param("half_y_mm", 25.0, float, 1.0, 100.0)}, _flat),
    "chessboard": ({"half_x_mm": Param("half_x_mm", 22.0, float, 1.0, 100.0),
                    "half_y_mm": Param("half_y_mm", 18.0, float, 1.0, 100.0)}, _flat),
    "terrain": ({"height_map": Param("height_map", None, HeightMap,
                                     doc="rest surface in the SENSOR frame (z >= 0 in front of the skin)")},
                _terrain),
}


def list_indenters() -> list[str]:
    """Registered indenter names."""
    return sorted(_REGISTRY)


def indenter_params(name: str) -> dict[str, Param]:
    """The parameters of one registered indenter (raises :class:`IndenterError` for unknown names)."""
    if name not in _REGISTRY:
        raise IndenterError(f"unknown indenter {name!r}; known: {', '.join(list_indenters())}")
    return dict(_REGISTRY[name][0])


def _resolve_key(name: str, key: str, spec: Mapping[str, Param]) -> str:
    if key in spec:
        return key
    hits = [k for k in spec if k.startswith(key + "_")]
    if len(hits) == 1:
        return hits[0]
    raise IndenterError(f"indenter {name!r}: unknown parameter {key!r} (allowed: {', '.join(spec)})")


#: Not a shape parameter: every indenter takes it (``make_indenter(..., friction=MU)``, ``--param friction=MU``).
FRICTION_KEY = "friction"


def make_indenter(name: str, *, friction: Any = None, **params: Any) -> Indenter:
    """Build a registered indenter; parameters may be abbreviated by dropping the unit (``sigma2``).
    ``friction``: the skin's Coulomb coefficient on this part (None: the design's), in [0, MAX_FRICTION]."""
    spec = indenter_params(name)
    if friction is not None:
        from pipeline.design import MAX_FRICTION

        friction = Param(FRICTION_KEY, None, float, 0.0, MAX_FRICTION).check(friction, f"indenter {name!r}")
    values = {k: p.default for k, p in spec.items()}
    for key, value in params.items():
        values[_resolve_key(name, key, spec)] = value
    checked = {}
    for k, p in spec.items():
        if values[k] is None:
            raise IndenterError(f"indenter {name!r}: parameter {k!r} is required")
        checked[k] = p.check(values[k], f"indenter {name!r}")
    half, fn, top = _REGISTRY[name][1](checked)
    return Indenter(name, checked, (float(half[0]), float(half[1])), fn, float(top), friction)


def parse_params(name: str, items: Sequence[str]) -> dict[str, Any]:
    """CLI ``key=value`` strings → parameters for :func:`make_indenter` (validated there)."""
    spec = indenter_params(name)
    out = {}
    for item in items:
        if "=" not in item:
            raise IndenterError(f"--param {item!r}: expected key=value")
        key, value = item.split("=", 1)
        if key.strip() == FRICTION_KEY:
            out[FRICTION_KEY] = value.strip()
            continue
        k = _resolve_key(name, key.strip(), spec)
        out[k] = value.strip() if spec[k].kind is str else value
    return out
