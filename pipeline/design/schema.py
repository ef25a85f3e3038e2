"""The design's parts: one frozen dataclass per TOML table, and the ``[twin]`` defaults."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import UserError

PATTERN_KINDS = ("hexagon", "circular", "square")
PATTERN_MAPPINGS = ("vertical", "arc")


class DesignError(UserError, ValueError):
    """A design file is missing, malformed, or has an unknown or missing key."""


@dataclass(frozen=True)
class Pattern:
    kind: str              # hexagon | circular | square
    layers: int            # DTRC layer count m (rings including the centre marker)
    links: int             # DTRC links l of an interior marker (reciprocal links: 2 x neighbours)
    separation_mm: float   # nearest-neighbour spacing of markers (ring spacing for circular)
    dome_height_mm: float  # 0 for a flat skin; sagitta of a spherical dome over the pattern radius
    #: how the planar layout is laid on the dome: "vertical" (x-y kept, z from the dome: the shallow caps of
    #: the StereoTacTip modules) or "arc" (a marker's distance from the centre in the layout is its arc length
    #: along the dome from the apex: pins evenly spaced over a deep, e.g. hemispherical, TacTip dome)
    mapping: str = "vertical"


@dataclass(frozen=True)
class Skin:
    thickness_mm: float
    material: str
    youngs_modulus_mpa: float
    poisson_ratio: float
    source: str


@dataclass(frozen=True)
class Pins:
    height_mm: float
    diameter_mm: float
    youngs_modulus_mpa: float


@dataclass(frozen=True)
class Markers:
    diameter_mm: float
    thickness_mm: float


@dataclass(frozen=True)
class Optics:
    air_gap_mm: float
    acrylic_thickness_mm: float
    acrylic_n: float
    gel_thickness_mm: float
    gel_n: float


@dataclass(frozen=True)
class Gel:
    material: str
    youngs_modulus_mpa: float
    poisson_ratio: float
    radius_mm: float       # clamped rim of the gel / skin (inner radius of the rigid mount)
    source: str


class _Lens:
    """The pinhole-plus-distortion model of a camera with ``fx_px, fy_px, cx_px, cy_px`` and ``dist``."""

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix, float64."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> np.ndarray:
        """Distortion coefficients (5,), float64, OpenCV order."""
        return np.asarray(self.dist, dtype=np.float64)


@dataclass(frozen=True)
class Camera(_Lens):
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist: tuple[float, ...]  # OpenCV order (k1, k2, p1, p2, k3)


@dataclass(frozen=True)
class Cameras:
    width_px: int
    height_px: int
    fps: float
    baseline_mm: float
    toe_in_deg: float     # total convergence angle; each camera yaws toe_in/2 toward the centre
    model_note: str
    left: Camera
    right: Camera


@dataclass(frozen=True)
class MonoCamera(_Lens):
    """The single camera of a monocular (TacTip-type) sensor: on the sensor axis below the skin, looking
    along +z (OpenCV axes = sensor axes); ``roll_deg`` turns it about its optical axis."""

    width_px: int
    height_px: int
    fps: float
    model_note: str
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist: tuple[float, ...]
    x_mm: float = 0.0
    y_mm: float = 0.0
    roll_deg: float = 0.0


#: Keys of the optional ``[twin]`` section (the simulated skin's contact friction; rendering appearance and tap
#: physics of a monocular design), with their defaults; every value is a finite number. ``twin.physics`` and
#: ``twin.tactip`` give them their meaning.
TWIN_KEYS: dict[str, float] = {
    "friction": 1.0,               # Coulomb coefficient skin/indenter the twin presses with (0: frictionless); 1.0:
                                   # elastomer on a smooth hard polymer, not measured for Agilus30 (sim_assets/README.md)
    "bending_ratio": 0.3,          # membrane bending / stretching stiffness (mm^2)
    "depth_offset_mm": 0.0,        # tap depth of the labels minus the depth into the undeformed dome
    "tilt_frame_deg": 0.0,         # angle of the robot's tilt axes about the sensor axis
    "tilt_mirror": 0.0,            # 1: the second tilt angle turns the other way
    "tilt_pivot_mm": 0.0,          # height of the tap's tilt pivot above the dome's centre of curvature
    "pin_rotation": 1.0,           # fraction of the skin normal's rotation the pins' axes follow (0..1)
    "tap_friction": 0.0,           # Coulomb coefficient of the TacTip tap's plane on the skin (0: frictionless)
    "marker_grey": 180.0,          # marker grey level at the image centre
    "marker_shading": 0.0,         # relative marker brightening per squared normalised image radius
    "background_grey": 20.0,       # grey level between the markers
    "edge_px": 1.0,                # Gaussian edge blur (px)
    "noise_grey": 1.0,             # pixel noise sigma (grey levels)
    "marker_scale": 1.0,           # apparent marker diameter / design diameter
}
