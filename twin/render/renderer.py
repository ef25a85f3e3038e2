"""The stereo renderer: one GL context, both views per frame, scene -> placement -> lens -> photometry.

See :mod:`twin.render` for the steps of one view and the modules that hold each.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from pipeline.design import SensorDesign
from pipeline.types import StereoFrame
from twin.gl import RenderError
from twin.render.flat import FlatRenderer
from twin.optics import FlatStack
from twin.render.lens import QUALITY_SCALE, SIDES, ZNEAR_MM, distort_and_shade, make_lens
from twin.render.photometry import (BACKGROUND_BGR, LAB_BACKGROUND_BGR, MARKER_BGR, MARKER_SIDE_BGR, PIN_BGR,
                                    SKIN_BGR, SensorResponse)
from twin.render.placement import apparent, chessboard_poses
from twin.render.scene import (CULLED_MESHES, board_meshes, marker_rotations, marker_template, module_meshes,
                               place_markers, skin_underside)

MSAA_SAMPLES = 4                         # edge anti-aliasing of the pinhole render (centroids to < 0.05 px)
MARKER_COLOURS = {"marker_face": MARKER_BGR, "marker_wall": MARKER_SIDE_BGR, "pins": PIN_BGR, "skin": SKIN_BGR}


class StereoRenderer:
    """Renders :class:`pipeline.types.StereoFrame` pairs of the twin's sensor (see :mod:`twin.render`).

    Parameters
    ----------
    design : SensorDesign
        Cameras, stack, marker and pin sizes.
    rng : numpy.random.Generator
        Source of the sensor noise (one draw per rendered frame).
    noise : bool
        False renders noise-free frames (blur and shading still applied).
    quality : "draft" | "fast" | "high"
        "fast": pinhole render at 0.8x the output's centre resolution with 4x MSAA (see
        ``QUALITY_SCALE``); "draft": 0.6x; "high": 2x the resolution, distorted at 2x and area-averaged
        down (slower, for accuracy studies).

    Notes
    -----
    One OpenGL context and one framebuffer holding both views side by side (left viewport | right
    viewport); meshes, lens maps and shading maps are created once, each frame only uploads new vertex
    positions. Pixels are OpenCV ``(u, v)``, centre of the top-left pixel at (0, 0).
    ``last_timing_ms`` holds the stage times of the last frame (refraction, upload, GL, lens, photometry).
    """

    def __init__(self, design: SensorDesign, *, rng: np.random.Generator, noise: bool = True,
                 quality: str = "fast") -> None:
        if not isinstance(rng, np.random.Generator):
            raise RenderError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
        if quality not in QUALITY_SCALE:
            raise RenderError(f"quality: expected one of {sorted(QUALITY_SCALE)}, got {quality!r}")
        self.design = design
        self.rng = rng
        self.noise = bool(noise)
        self.quality = quality
        self._focal_scale, self._scale = QUALITY_SCALE[quality]
        self._stack = FlatStack.from_design(design)
        self._w_out, self._h_out = design.cameras.width_px, design.cameras.height_px
        self._lens = make_lens(design, self._stack, self._focal_scale, self._scale)
        self._views = self._lens.views
        self._w_r, self._h_r = self._lens.render_size
        self._gl = FlatRenderer(2 * self._w_r, self._h_r, samples=MSAA_SAMPLES)
        self._faces: dict[tuple[str, str], np.ndarray] = {}     # (side, name) -> faces last uploaded
        self._marker_templates: dict[int, tuple] = {}
        self._static_done: set[str] = set()
        self._frame_index = 0
        self.last_timing_ms: dict[str, float] = {}
        self._timing: dict[str, float] = {}
        self._sensor = SensorResponse(self._w_out, self._h_out)
        self._bufs: dict[str, np.ndarray] = {}

    # ----- setup ---------------------------------------------------------------------------
    def _buf(self, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        """A per-renderer scratch image, reused between frames (fresh multi-MB arrays cost page faults:
        ~1 ms per 7 MB float image here). Never handed to the caller."""
        b = self._bufs.get(name)
        if b is None or b.shape != tuple(shape) or b.dtype != np.dtype(dtype):
            b = self._bufs[name] = np.empty(shape, dtype)
        return b

    def _set_mesh(self, side: str, name: str, positions: np.ndarray, faces: np.ndarray, bgr) -> None:
        """Create or update the mesh ``name`` of camera ``side`` (indices re-uploaded only if they change)."""
        key = (side, name)
        old = self._faces.get(key)
        same = old is not None and (old is faces or (old.shape == faces.shape and np.array_equal(old, faces)))
        self._gl.set_mesh(key, positions, None if same else faces, bgr, cull_back=name in CULLED_MESHES)
        if not same:
            self._faces[key] = faces

    def _refracted(self, side: str, pts: np.ndarray, through_stack: bool) -> np.ndarray:
        return apparent(pts, self._views[side].centre, self._stack, through_stack)

    def _ensure_module_static(self) -> None:
        """Mount ring, LEDs and (when no skin mesh is given) the flat skin underside; refracted once."""
        if "module" in self._static_done:
            return
        meshes = module_meshes(self.design)
        for side in SIDES:
            for name, (v, f, bgr) in meshes.items():
                # the LEDs sit in air under the acrylic: seen directly, not through the stack
                self._set_mesh(side, name, self._refracted(side, v, name != "leds"), f, bgr)
        self._static_done.add("module")

    def _marker_template(self, n: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Local vertices and tiled faces of n markers (cached for the last n)."""
        tpl = self._marker_templates.get(n)
        if tpl is None:
            tpl = marker_template(self.design, n)
            self._marker_templates = {n: tpl}
        return tpl

    def shading_map(self, side: str, *, through_stack: bool = True) -> np.ndarray:
        """Relative illumination of camera ``side`` per output pixel, (H, W) float32.

        LED shading × vignetting for the skin module (``through_stack=True``), vignetting only for the
        skin-less calibration set-up. The rendered DN of a surface of albedo a is ``255 · a · shading``
        before blur and noise.
        """
        if side not in self._views:
            raise RenderError(f"side: expected 'left' or 'right', got {side!r}")
        v = self._views[side]
        m = (v.shade_module if through_stack else v.shade_lab)[..., 0]
        if self._scale > 1:
            m = cv2.resize(m, (self._w_out, self._h_out), interpolation=cv2.INTER_AREA)
        return m.copy()

    # ----- rendering --------------------------------------------------------------------------
    def _render_pair(self, visible: list[str], lab: bool) -> np.ndarray:
        """Both views in one GL pass, lens-distorted and shaded: (H, 2W, 3) float32 DN, left | right."""
        t0 = time.perf_counter()
        passes = []
        for k, side in enumerate(SIDES):
            keys = [(side, name) for name in visible if self._gl.has_mesh((side, name))]
            passes.append(((k * self._w_r, 0, self._w_r, self._h_r), self._views[side].mvp, keys))
        buf = self._gl.render(passes, LAB_BACKGROUND_BGR if lab else BACKGROUND_BGR)
        t1 = time.perf_counter()
        img = distort_and_shade(buf, self._lens, lab, self._scale, (self._w_out, self._h_out), self._buf)
        self._timing["gl"] = (t1 - t0) * 1e3
        self._timing["lens"] = (time.perf_counter() - t1) * 1e3
        return img

    def _finish(self, pair: np.ndarray, source: str) -> StereoFrame:
        t0 = time.perf_counter()
        out = self._sensor.apply(pair, self.rng if self.noise else None, self._buf)
        frame = StereoFrame(out, timestamp_s=0.0, index=self._frame_index, source=source)
        self._frame_index += 1
        self._timing["photometry"] = (time.perf_counter() - t0) * 1e3
        self.last_timing_ms = dict(self._timing)
        self._timing.clear()
        return frame

    def render_markers(self, marker_xyz_mm: np.ndarray, marker_axis: np.ndarray, *,
                       skin_vertices_mm: np.ndarray | None = None,
                       skin_faces: np.ndarray | None = None) -> StereoFrame:
        """Render the installed skin module: markers on pins in the gel, behind acrylic + gel.

        Parameters
        ----------
        marker_xyz_mm : (N, 3) float
            Marker face centres (the face seen by the cameras), sensor frame, mm.
        marker_axis : (N, 3) float
            Unit pin directions from the skin toward the marker (≈ (0, 0, −1) at rest). The disc's
            thickness and the pin extend from the face back along −axis.
        skin_vertices_mm, skin_faces : (V, 3) float, (F, 3) int, optional
            The deformed OUTER skin surface; its underside (offset by the skin thickness along the
            vertex normals) is drawn dark. Without it a flat underside at z = −T is drawn.

        Returns
        -------
        StereoFrame
            1280x480 BGR, left | right.
        """
        d = self.design
        P = np.asarray(marker_xyz_mm, dtype=np.float64)
        A = np.asarray(marker_axis, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3 or not np.all(np.isfinite(P)):
            raise RenderError(f"marker_xyz_mm: expected a finite (N, 3) array, got shape {P.shape}")
        if A.shape != P.shape or not np.all(np.isfinite(A)):
            raise RenderError(f"marker_axis: expected a finite array of shape {P.shape}, got {A.shape}")
        if np.any(P[:, 2] <= d.gel_acrylic_z_mm):
            raise RenderError(f"marker_xyz_mm: markers must lie in the gel (z > {d.gel_acrylic_z_mm:.2f} mm)")
        if (skin_vertices_mm is None) != (skin_faces is None):
            raise RenderError("skin_vertices_mm and skin_faces must be given together")
        self._ensure_module_static()
        parts = place_markers(self._marker_template(len(P)), P, marker_rotations(A))
        names = ["mount", "leds", "marker_face", "marker_wall", "pins"]
        if skin_vertices_mm is not None:
            parts["skin"] = skin_underside(skin_vertices_mm, skin_faces, d.skin.thickness_mm)
            names.append("skin")
        else:
            names.append("skin_flat")
        order = list(parts)
        all_world = np.vstack([parts[k][0] for k in order])
        splits = np.cumsum([len(parts[k][0]) for k in order])[:-1]
        for side in SIDES:
            t0 = time.perf_counter()
            apparent_parts = np.split(self._refracted(side, all_world, True), splits)
            t1 = time.perf_counter()
            for name, app in zip(order, apparent_parts):
                self._set_mesh(side, name, app, parts[name][1], MARKER_COLOURS[name])
            self._timing[f"refract_{side}"] = (t1 - t0) * 1e3
            self._timing[f"upload_{side}"] = (time.perf_counter() - t1) * 1e3
        return self._finish(self._render_pair(names, lab=False), source=f"twin:{d.name}:markers")

    def render_board(self, kind: str, sensor_from_board: np.ndarray, *, through_stack: bool,
                     board_design=None) -> StereoFrame:
        """Render a skin-less board: a chessboard or a flat board printed with the marker pattern.

        Parameters
        ----------
        kind : "chessboard" | "marker_board"
        sensor_from_board : (4, 4) float
            Board pose in the sensor frame, mm. The printed face is the board frame's z = 0 plane and
            faces the board's −z (see :class:`ChessboardSpec`; the marker board's dots sit at the
            design's rest marker x-y).
        through_stack : bool
            False: the whole skin module is removed (calibration set-up, lab background, no LEDs).
            True: acrylic + gel between cameras and board (board pressed against the gel, no skin);
            the board must then lie inside the gel.
        board_design : ChessboardSpec | SensorDesign | None
            Chessboard geometry (default 9x7 squares of 4 mm) or the design whose marker pattern is
            printed (default: this renderer's design).
        """
        d = self.design
        T = np.asarray(sensor_from_board, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise RenderError(f"sensor_from_board: expected a finite (4, 4) rigid transform, got shape {T.shape}")
        if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise RenderError("sensor_from_board: rotation part is not orthonormal")
        meshes = board_meshes(kind, board_design, d, through_stack=through_stack)
        world = {name: (v @ T[:3, :3].T + T[:3, 3], f, c) for name, (v, f, c) in meshes.items()}
        names = set(meshes)
        if through_stack:
            self._check_board_in_gel(world)
            self._ensure_module_static()
            names |= {"mount", "leds"}
        else:
            self._check_board_before_cameras(world)
        for side in SIDES:
            for name, (w, f, c) in world.items():
                self._set_mesh(side, name, self._refracted(side, w, through_stack), f, c)
        return self._finish(self._render_pair(sorted(names), lab=not through_stack), source=f"twin:{d.name}:{kind}")

    def _check_board_in_gel(self, world: dict) -> None:
        d = self.design
        lowest = min(float(w.min(axis=0)[2]) for w, _, _ in world.values())
        if lowest <= d.gel_acrylic_z_mm:
            raise RenderError(f"sensor_from_board: with through_stack=True the board must lie inside the gel "
                              f"(z > {d.gel_acrylic_z_mm:.2f} mm); its lowest point is at z = {lowest:.2f} mm")

    def _check_board_before_cameras(self, world: dict) -> None:
        for side in SIDES:
            zmin = min(float(((w - self._views[side].centre) @ self._views[side].pose[:3, 2]).min())
                       for w, _, _ in world.values())
            if zmin <= ZNEAR_MM:
                raise RenderError(f"sensor_from_board: the board reaches behind or too close to the {side} "
                                  f"camera ({zmin:.2f} mm in front of it)")


def render_chessboard_pairs(design: SensorDesign, n: int, rng: np.random.Generator, *,
                            poses: list[np.ndarray] | None = None, progress: bool = True) -> list[StereoFrame]:
    """``n`` skin-less chessboard stereo frames (the paper's 20-pair calibration), poses from ``rng``."""
    from tqdm import tqdm  # noqa: PLC0415

    poses = chessboard_poses(n, rng, design=design) if poses is None else list(poses)
    renderer = StereoRenderer(design, rng=rng)
    frames = []
    for i, T in enumerate(tqdm(poses, desc="chessboard pairs", disable=not progress or len(poses) < 5)):
        f = renderer.render_board("chessboard", T, through_stack=False)
        frames.append(StereoFrame(f.image, timestamp_s=float(i), index=i, source=f"twin:{design.name}:chessboard"))
    return frames
