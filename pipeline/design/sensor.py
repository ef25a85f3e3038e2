"""The whole skin module + cameras (:class:`SensorDesign`) and the geometry derived from it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from pipeline.design.layout import marker_layout
from pipeline.design.schema import TWIN_KEYS, Cameras, DesignError, Gel, Markers, MonoCamera, Optics, Pattern, Pins, Skin


@dataclass(frozen=True)
class SensorDesign:
    """A whole skin module + cameras. Build with :func:`load_design`."""

    name: str
    description: str
    pattern: Pattern
    skin: Skin
    pins: Pins
    markers: Markers
    optics: Optics
    gel: Gel
    cameras: Cameras | None      # the stereo pair; None for a monocular design
    source_file: str = ""
    camera: MonoCamera | None = None   # the single camera of a monocular design
    twin: tuple[tuple[str, float], ...] = ()   # the [twin] section, sorted (key, value)

    @property
    def monocular(self) -> bool:
        return self.camera is not None

    def twin_params(self) -> dict[str, float]:
        """The ``[twin]`` section over its defaults (:data:`TWIN_KEYS`)."""
        return {**TWIN_KEYS, **dict(self.twin)}

    # ----- derived geometry -------------------------------------------------------------
    @property
    def marker_count(self) -> int:
        return int(self.rest_markers_mm().shape[0])

    @property
    def marker_depth_mm(self) -> float:
        """Distance from the outer skin surface to the marker faces at rest, T + H (mm)."""
        return self.skin.thickness_mm + self.pins.height_mm

    @property
    def gel_acrylic_z_mm(self) -> float:
        return -(self.skin.thickness_mm + self.optics.gel_thickness_mm)

    @property
    def acrylic_air_z_mm(self) -> float:
        return self.gel_acrylic_z_mm - self.optics.acrylic_thickness_mm

    @property
    def camera_z_mm(self) -> float:
        return self.acrylic_air_z_mm - self.optics.air_gap_mm

    def rest_markers_mm(self) -> np.ndarray:
        """Rest marker face centres in the sensor frame, (N, 3) float64, mm, canonical order."""
        xy, _ = marker_layout(self.pattern)
        if self.pattern.mapping == "arc":
            p, n = self.arc_surface(xy)
            return p - self.marker_depth_mm * n
        z = np.full(len(xy), -self.marker_depth_mm) + self.dome_z_mm(xy)
        return np.column_stack([xy, z])

    def dome_radius_mm(self) -> float:
        """Radius of the sphere the dome is a cap of (mm); inf for a flat skin."""
        h, a = self.pattern.dome_height_mm, self.gel.radius_mm
        return math.inf if h <= 0 else (a * a + h * h) / (2 * h)

    def arc_surface(self, layout_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Outer-surface points and outward unit normals (N, 3) of layout points laid on the dome by arc
        length from the apex (``mapping = "arc"``)."""
        xy = np.asarray(layout_xy, dtype=np.float64).reshape(-1, 2)
        R = self.dome_radius_mm()
        s = np.hypot(xy[:, 0], xy[:, 1])
        th = s / R
        az = np.arctan2(xy[:, 1], xy[:, 0])
        n = np.column_stack([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), np.cos(th)])
        return n * R - np.array([0.0, 0.0, R]), n

    def marker_layers(self) -> np.ndarray:
        """Layer (ring) index of each marker in canonical order, (N,) int64; 0 = centre."""
        return marker_layout(self.pattern)[1]

    def pattern_radius_mm(self) -> float:
        xy, _ = marker_layout(self.pattern)
        return float(np.max(np.hypot(xy[:, 0], xy[:, 1])))

    def dome_z_mm(self, xy_mm: np.ndarray) -> np.ndarray:
        """Height of the (possibly domed) rest skin above z=0 at sensor x-y, (N,) mm.

        A spherical cap of sagitta ``dome_height_mm`` spanning the gel radius, apex at z = 0 (the
        sensor origin) and falling to ``-dome_height_mm`` at the rim; 0 everywhere for flat skins.
        """
        xy_mm = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        h = self.pattern.dome_height_mm
        if h <= 0:
            return np.zeros(len(xy_mm))
        a = self.gel.radius_mm
        R = (a * a + h * h) / (2 * h)
        r2 = np.minimum(np.sum(xy_mm**2, axis=1), a * a)
        return np.sqrt(R * R - r2) - R

    def camera_pose(self) -> np.ndarray:
        """sensor_from_camera (4x4, mm) of a monocular design's camera."""
        if self.camera is None:
            raise DesignError(f"design {self.name!r} is a stereo design (no [camera] block)")
        c = self.camera
        r = math.radians(c.roll_deg)
        T = np.eye(4)
        T[:3, :3] = [[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = [c.x_mm, c.y_mm, self.camera_z_mm]
        return T

    def camera_poses(self) -> dict[str, np.ndarray]:
        """Nominal camera poses: ``{'left': T, 'right': T}``, each 4x4 sensor_from_camera (mm).

        Camera axes are OpenCV's. Each camera yaws by half the toe-in toward the sensor axis.
        """
        if self.cameras is None:
            raise DesignError(f"design {self.name!r} is monocular: it has no stereo [cameras] block")
        half = math.radians(self.cameras.toe_in_deg) / 2.0
        out = {}
        for side, sign in (("left", -1.0), ("right", 1.0)):
            yaw = -sign * half  # left camera (x<0) turns toward +x
            c, s = math.cos(yaw), math.sin(yaw)
            R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # rotation about +y
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = [sign * self.cameras.baseline_mm / 2.0, 0.0, self.camera_z_mm]
            out[side] = T
        return out

    def with_overrides(self, overrides: Mapping[str, Any], *, name: str | None = None) -> "SensorDesign":
        """A copy with dotted-key overrides, e.g. ``{"skin.thickness_mm": 0.5}``; validated."""
        # the writer and the validator are built on this class: imported when first asked for
        from pipeline.design.validation import design_from_dict
        from pipeline.design.writing import to_dict

        raw = to_dict(self)
        for key, value in overrides.items():
            parts = key.split(".")
            if len(parts) == 2 and parts[0] == "twin" and parts[1] in TWIN_KEYS:
                # the [twin] section is optional and holds only what a design changes from its defaults
                raw.setdefault("twin", {}).setdefault(parts[1], TWIN_KEYS[parts[1]])
            node = raw
            for p in parts[:-1]:
                if p not in node or not isinstance(node[p], dict):
                    raise DesignError(f"override {key!r}: no section {p!r}")
                node = node[p]
            if parts[-1] not in node:
                raise DesignError(f"override {key!r}: unknown key {parts[-1]!r}")
            node[parts[-1]] = value
        raw["name"] = name or (self.name + "+" + ",".join(f"{k}={v}" for k, v in overrides.items()))
        return design_from_dict(raw, source=self.source_file or "<overrides>")
