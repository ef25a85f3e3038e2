"""The digital twin's stereo renderer: markers in the gel, boards for calibration, seen by two OV5693s.

Pipeline of one view (camera ``side``), one module per step:

1. :mod:`~twin.render.scene` — geometry in the sensor frame (mm): marker discs on dark pins, the dark skin
   underside, the mount ring with four LEDs (skin module), or a chessboard / printed marker board (skin-less).
2. :mod:`~twin.render.placement` — refraction: every vertex behind the acrylic/gel stack is moved to its
   *apparent* position for that camera (:func:`twin.optics.apparent_points`, exact Snell per vertex); each
   camera has its own vertex buffers. Also the true calibration and in-view chessboard poses.
3. :mod:`~twin.render.renderer` — a flat-shaded (unlit) pinhole render with a field wider than the output,
   4x MSAA, both views side by side in ONE framebuffer (:class:`twin.render.flat.FlatRenderer`: one clear, resolve
   and read-back).
4. :mod:`~twin.render.lens` — lens distortion: one ``cv2.remap`` for the pair with maps precomputed once:
   for each output pixel the ideal normalised ray (exact inverse of the OpenCV model,
   :func:`twin.camera.pixels_to_normalised`) is looked up in its view's viewport.
5. :mod:`~twin.render.photometry` — LED shading (four point LEDs under the acrylic, irradiance on the
   marker plane), vignetting (one precomputed map), Gaussian blur (σ = ``BLUR_SIGMA_PX``), shot + read
   noise seeded from the caller's rng.

Colours are given to OpenGL in B, G, R order, so the read-back RGB buffer is already BGR.

Public API: :class:`StereoRenderer` (``render_markers``, ``render_board``, ``shading_map``),
:class:`ChessboardSpec`, :func:`chessboard_corners_mm`, :func:`chessboard_poses`,
:func:`render_chessboard_pairs`, :func:`true_calibration`, :func:`marker_rotations`, :func:`project_exact`
(from :mod:`twin.optics`) and :class:`RenderError`; the albedos, blur and noise constants and the
tessellation counts are exported too, so that independent references can use the twin's exact numbers.
"""

from twin.gl import RenderError
from twin.optics import project_exact
from twin.render.photometry import (BLUR_SIGMA_PX, MARKER_BGR, MARKER_SIDE_BGR, PIN_BGR, READ_NOISE_DN,
                                    SHOT_GAIN_DN_PER_E, SKIN_BGR)
from twin.render.placement import chessboard_poses, true_calibration
from twin.render.renderer import StereoRenderer, render_chessboard_pairs
from twin.render.scene import (DISC_SECTIONS, PIN_SECTIONS, ChessboardSpec, chessboard_corners_mm,
                               marker_rotations)

__all__ = [
    "StereoRenderer",
    "ChessboardSpec",
    "true_calibration",
    "project_exact",
    "chessboard_corners_mm",
    "chessboard_poses",
    "render_chessboard_pairs",
    "marker_rotations",
    "RenderError",
    "BLUR_SIGMA_PX",
    "MARKER_BGR",
    "MARKER_SIDE_BGR",
    "PIN_BGR",
    "SKIN_BGR",
    "READ_NOISE_DN",
    "SHOT_GAIN_DN_PER_E",
    "DISC_SECTIONS",
    "PIN_SECTIONS",
]
