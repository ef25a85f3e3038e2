"""The read-out of a skin simulation: what the current MuJoCo state says in the sensor frame, in mm.

:class:`SkinReadout` is the base of :class:`twin.physics.SkinSim` that only reads: mesh vertices, the outer
skin, marker face centres and pin axes, the indenter's surface at the current pose, the vertices touching it
and the gap there, the contact force, the frame's physical validity (:mod:`twin.validity`) and the
:class:`~twin.truth.Truth` the benchmarks score against. Nothing here steps the physics or changes the state,
so a frame's truth is the same however often it is read. The state itself (``design``, ``indenter``,
``mesh``, ``pose``, MuJoCo's ``model``/``data``, the index arrays ``_free``, ``_pins``, ``_top_geom``) and its
warning counters (``warnings()``) are :class:`~twin.physics.SkinSim`'s.
"""

from __future__ import annotations

import numpy as np

from pipeline.types import HeightMap
from twin import units
from twin.mesh import pin_markers
from twin.model import _FLIP
from twin.truth import Truth
from twin.validity import FrameValidity, frame_validity, rim_overlap_mm, skin_penetration

__all__ = ["SkinReadout"]


class SkinReadout:
    """Read-only views of a :class:`~twin.physics.SkinSim`'s current state (sensor frame, mm)."""

    def nodes_mm(self) -> np.ndarray:
        """Current positions of all mesh vertices, sensor frame (V, 3) mm."""
        V = len(self.mesh.nodes_mm)
        return units.m_to_mm(self.data.flexvert_xpos[:V]) * _FLIP

    def skin_vertices_mm(self) -> np.ndarray:
        """Deformed outer skin surface vertices (Vt, 3), sensor frame; faces: ``mesh.top_faces``."""
        return self.nodes_mm()[self.mesh.top]

    def markers(self) -> tuple[np.ndarray, np.ndarray]:
        """Marker face centres (N, 3) mm and unit pin axes (N, 3), sensor frame, canonical order."""
        return pin_markers(self.nodes_mm(), self._pins, self.design.pins.height_mm)

    def indenter_heightmap(self, *, spacing_mm: float = 0.2) -> HeightMap:
        """Indenter contact surface in the sensor frame at the current pose."""
        x, y, depth, yaw = self.pose
        return self.indenter.sensor_heightmap(x, y, depth, yaw, half_mm=self.design.gel.radius_mm + 2.0,
                                              spacing_mm=spacing_mm)

    def indenter_z_at(self, xy_mm: np.ndarray) -> np.ndarray:
        """Indenter surface sensor z (mm) above sensor points (N, 2); NaN off the part."""
        from twin.indenters import sensor_to_indenter_xy

        x, y, depth, yaw = self.pose
        xi, yi = sensor_to_indenter_xy(xy_mm[:, 0], xy_mm[:, 1], x, y, yaw)
        return self.indenter.top_mm - self.indenter.height(xi, yi) - depth

    def touching(self) -> np.ndarray:
        """Mesh indices of the outer-surface vertices whose contact sphere touches the indenter."""
        out = set()
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            for gid in c.geom:
                if int(gid) in self._top_geom and c.dist < 1e-5:
                    out.add(self._top_geom[int(gid)])
        return np.array(sorted(out), dtype=np.int64)

    def gap_mm(self) -> np.ndarray:
        """Indenter − skin height (mm) at touching vertices (positive: a gap, negative: penetration)."""
        idx = self.touching()
        X = self.nodes_mm()[idx]
        return self.indenter_z_at(X[:, :2]) - X[:, 2]

    def contact_force_n(self) -> float:
        """Total force the indenter exerts on the skin along the press direction (N).

        Summed from the constraint forces on the vertex DOFs (the only constraints are the
        skin–indenter contacts), along world +z = sensor −z.
        """
        qz = self.data.qfrc_constraint[:3 * len(self._free)][2::3]
        return float(np.sum(qz))

    def validity(self, *, settled: bool, in_motion: bool = False) -> FrameValidity:
        """Physical validity of the current state (:mod:`twin.validity`): the outer skin's penetration
        into the indenter's true surface at vertices, face centroids, edge midpoints and the indenter's
        own 0.1 mm samples over the deformable skin (the clamped rim is the rigid mount: how far the
        indenter reaches below it is recorded as ``rim_overlap_mm``); how far the deepest pin's tip lies
        beyond the gel, into the acrylic window (``pin_overrun_mm``); the contact force; ``settled``;
        MuJoCo's warning counters so far; ``in_motion``: filmed while the indenter moves (never valid)."""
        top = self.skin_vertices_mm()
        free = ~self.mesh.pinned[self.mesh.top]
        pen = skin_penetration(top, self.mesh.top_faces, self.indenter_z_at, free=free)
        overrun = max(0.0, float(self.design.gel_acrylic_z_mm - self.markers()[0][:, 2].min()))
        return frame_validity(pen, contact_force_n=self.contact_force_n(), settled=settled,
                              mujoco_warnings=self.warnings(), rim_overlap=rim_overlap_mm(top, ~free, self.indenter_z_at),
                              pin_overrun=overrun, in_motion=in_motion)

    def truth(self, *, settled: bool | None = None, in_motion: bool = False) -> Truth:
        """Truth of the current state (sensor frame, mm); with ``settled`` given, its physics validity
        (:meth:`validity`, ``in_motion`` passed on) is recorded in it."""
        xyz, axis = self.markers()
        x, y, depth, yaw = self.pose
        val = None if settled is None else self.validity(settled=settled, in_motion=in_motion).to_dict()
        return Truth(np.arange(len(xyz)), xyz, axis, self.skin_vertices_mm(), self.mesh.top_faces,
                     self.indenter_heightmap(), np.array([x, y, -depth, yaw]), val)
