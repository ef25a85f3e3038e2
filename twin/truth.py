"""Ground truth of one captured twin frame (sensor frame, mm), saved beside ``frame_XXXX.png``."""

from __future__ import annotations

import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.types import DataError, HeightMap, checked_array

__all__ = ["Truth"]


@dataclass(frozen=True)
class Truth:
    """Truth at one instant, sensor frame (mm).

    Parameters
    ----------
    marker_ids : (N,) int64 canonical marker ids (rows of ``design.rest_markers_mm()``)
    marker_xyz_mm : (N, 3) float64 marker face centres
    marker_axis : (N, 3) float64 unit pin directions, from the skin toward the marker (≈ (0, 0, -1) at rest)
    skin_vertices_mm : (V, 3) float64 deformed OUTER skin surface vertices
    skin_faces : (F, 3) int64 triangles into ``skin_vertices_mm``
    indenter : HeightMap of the indenter's contact surface in the sensor frame (NaN off the part)
    robot_pose : (4,) float64 ``(x_mm, y_mm, z_mm, yaw_deg)``: the indenter's reference point (its top)
        in the sensor frame, i.e. ``z_mm = -depth``, and its yaw about the sensor axis
    validity : :class:`twin.validity.FrameValidity` as a dict (penetration max/p99, gap where touching,
        contact force, settle, MuJoCo warnings, ``valid`` and ``reasons``); None for truths made
        without physics (files written before the check existed load as None)
    """

    marker_ids: np.ndarray
    marker_xyz_mm: np.ndarray
    marker_axis: np.ndarray
    skin_vertices_mm: np.ndarray
    skin_faces: np.ndarray
    indenter: HeightMap
    robot_pose: np.ndarray
    validity: dict | None = None

    @property
    def physics_valid(self) -> bool | None:
        """The frame passed every physics check (None: not checked)."""
        return None if self.validity is None else bool(self.validity["valid"])

    @property
    def in_motion(self) -> bool:
        """Filmed while the indenter moved (:class:`twin.validity.FrameValidity`): a tracking input, never scored."""
        return bool(self.validity is not None and self.validity.get("in_motion", False))

    def __post_init__(self) -> None:
        f = lambda name, **kw: object.__setattr__(self, name, checked_array(f"Truth.{name}", getattr(self, name), **kw))
        f("marker_ids", dtype=np.int64, shape=(-1,))
        f("marker_xyz_mm", dtype=np.float64, shape=(len(self.marker_ids), 3))
        f("marker_axis", dtype=np.float64, shape=(len(self.marker_ids), 3))
        f("skin_vertices_mm", dtype=np.float64, shape=(-1, 3))
        f("skin_faces", dtype=np.int64, shape=(-1, 3))
        f("robot_pose", dtype=np.float64, shape=(4,))
        if len(self.marker_axis) and not np.allclose(np.linalg.norm(self.marker_axis, axis=1), 1.0, atol=1e-6):
            raise DataError("Truth.marker_axis: not unit vectors")
        if len(self.skin_faces) and (self.skin_faces.min() < 0 or self.skin_faces.max() >= len(self.skin_vertices_mm)):
            raise DataError("Truth.skin_faces: index out of range")
        if not isinstance(self.indenter, HeightMap):
            raise DataError(f"Truth.indenter: expected a HeightMap, got {type(self.indenter).__name__}")

    def save_npz(self, path: str | Path) -> None:
        """Write all fields to one compressed ``.npz`` (atomically: a truth file is complete or absent)."""
        from pipeline.io.atomic import atomic_open

        with atomic_open(path, "wb") as fh:
            self._savez(fh)

    def _savez(self, fh) -> None:
        np.savez_compressed(fh, marker_ids=self.marker_ids, marker_xyz_mm=self.marker_xyz_mm,
                            marker_axis=self.marker_axis, skin_vertices_mm=self.skin_vertices_mm,
                            skin_faces=self.skin_faces, indenter_x_mm=self.indenter.x_mm,
                            indenter_y_mm=self.indenter.y_mm, indenter_z_mm=self.indenter.z_mm,
                            robot_pose=self.robot_pose,
                            **({} if self.validity is None else {"validity_json": np.array(json.dumps(self.validity))}))

    @classmethod
    def load_npz(cls, path: str | Path) -> "Truth":
        """Read a file written by :meth:`save_npz`."""
        path = Path(path)
        if not path.is_file():
            raise DataError(f"truth file {path} does not exist")
        try:
            with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
                return cls(z["marker_ids"], z["marker_xyz_mm"], z["marker_axis"], z["skin_vertices_mm"],
                           z["skin_faces"], HeightMap(z["indenter_x_mm"], z["indenter_y_mm"], z["indenter_z_mm"]),
                           z["robot_pose"],
                           json.loads(str(z["validity_json"])) if "validity_json" in z.files else None)
        except json.JSONDecodeError as exc:
            raise DataError(f"truth file {path}: unreadable validity record ({exc})") from None
        except KeyError as exc:
            raise DataError(f"truth file {path}: missing array {exc}") from None
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise DataError(f"truth file {path}: unreadable or truncated ({type(exc).__name__})") from None
