"""Headless OpenGL for the twin's renderer (pyrender on EGL, or OSMesa as a fallback), CPU only.

Import :func:`import_pyrender` instead of ``import pyrender``: it chooses the PyOpenGL platform before
OpenGL is first imported (``PYOPENGL_PLATFORM`` must be set before that and cannot change afterwards),
and installs the ``np.infty`` alias that pyrender 0.1.45 still uses but numpy 2 removed.

Platform choice: an explicit ``PYOPENGL_PLATFORM`` in the environment wins. Otherwise EGL is probed with
``ctypes`` (load ``libEGL``, ``eglGetDisplay`` + ``eglInitialize`` on the default display, no OpenGL
import); if that fails and ``libOSMesa`` is present, OSMesa is used.

:func:`offscreen_renderer` also replaces pyrender's frame read-back by a colour-only one: pyrender always
reads and linearises the depth buffer too, which costs about as much as rendering a flat-shaded frame on
llvmpipe. The fast read-back returns the RGBA buffer bottom row first (OpenGL order); the caller's
lens remap absorbs the vertical flip.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import types

import numpy as np

from pipeline.errors import UserError

__all__ = ["RenderError", "setup_gl", "import_pyrender", "offscreen_renderer", "gl_platform"]


class RenderError(UserError, RuntimeError):
    """Headless OpenGL is not available or a render request is invalid."""


_PLATFORM: str | None = None
_EGL_PLATFORM_DEVICE_EXT = 0x313F


def _egl_works() -> bool:
    """Probe EGL the way pyrender uses it: first EGL device, platform display, eglInitialize."""
    name = ctypes.util.find_library("EGL")
    if name is None:
        return False
    try:
        egl = ctypes.CDLL(name)
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
        egl.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
        egl.eglInitialize.restype = ctypes.c_uint
        egl.eglTerminate.argtypes = [ctypes.c_void_p]
        query_addr = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
        display_addr = egl.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
        if not query_addr or not display_addr:
            return False
        query = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p),
                                 ctypes.POINTER(ctypes.c_int))(query_addr)
        get_display = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p)(display_addr)
        devices = (ctypes.c_void_p * 4)()
        count = ctypes.c_int()
        if not query(4, devices, ctypes.byref(count)) or count.value < 1:
            return False
        display = get_display(_EGL_PLATFORM_DEVICE_EXT, devices[0], None)
        if not display:
            return False
        major, minor = ctypes.c_int(), ctypes.c_int()
        ok = bool(egl.eglInitialize(display, ctypes.byref(major), ctypes.byref(minor)))
        if ok:
            egl.eglTerminate(display)
        return ok
    except (OSError, AttributeError):
        return False


def setup_gl() -> str:
    """Choose the headless PyOpenGL platform (once per process) and return it ("egl" or "osmesa").

    Raises
    ------
    RenderError
        If neither EGL nor OSMesa is usable and ``PYOPENGL_PLATFORM`` is not set.
    """
    global _PLATFORM
    if not hasattr(np, "infty"):
        np.infty = np.inf  # pyrender 0.1.45 uses the alias numpy 2 removed
    if _PLATFORM is not None:
        return _PLATFORM
    chosen = os.environ.get("PYOPENGL_PLATFORM")
    if not chosen:
        if "OpenGL" in sys.modules:
            # OpenGL already imported with its own platform choice; do not pretend we can change it.
            chosen = "egl"
        elif _egl_works():
            chosen = "egl"
        elif ctypes.util.find_library("OSMesa"):
            chosen = "osmesa"
        else:
            raise RenderError("headless OpenGL: EGL cannot initialise a display and libOSMesa is not "
                              "installed; install Mesa EGL (libegl1 + libegl-mesa0) or OSMesa "
                              "(libosmesa6), or set PYOPENGL_PLATFORM")
        os.environ["PYOPENGL_PLATFORM"] = chosen
    _PLATFORM = chosen
    return chosen


def gl_platform() -> str | None:
    """The platform chosen by :func:`setup_gl`, or None if it has not run yet."""
    return _PLATFORM


def import_pyrender() -> types.ModuleType:
    """``pyrender``, imported after :func:`setup_gl`."""
    setup_gl()
    import pyrender  # noqa: PLC0415 (deliberately late: platform must be chosen first)

    return pyrender


def _read_colour_only(self, scene, flags):
    """Replacement for ``pyrender.Renderer._read_main_framebuffer``: colour only, RGBA, bottom-up."""
    from OpenGL import GL  # noqa: PLC0415

    width, height = self._main_fb_dims[0], self._main_fb_dims[1]
    GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
    GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
    GL.glBlitFramebuffer(0, 0, width, height, 0, 0, width, height, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST)
    GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
    buf = GL.glReadPixels(0, 0, width, height, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE)
    return np.frombuffer(buf, dtype=np.uint8).reshape(height, width, 4)


def offscreen_renderer(width_px: int, height_px: int):
    """A ``pyrender.OffscreenRenderer`` whose ``render`` returns only the colour buffer.

    Returns
    -------
    pyrender.OffscreenRenderer
        ``render(scene, flags)`` returns an (H, W, 4) uint8 RGBA image with the BOTTOM row first.

    Raises
    ------
    RenderError
        If the OpenGL context cannot be created.
    """
    pyrender = import_pyrender()
    try:
        r = pyrender.OffscreenRenderer(int(width_px), int(height_px))
    except Exception as exc:  # EGL/OSMesa failures surface as assorted exception types
        raise RenderError(f"cannot create a {width_px}x{height_px} headless OpenGL context on platform "
                          f"{os.environ.get('PYOPENGL_PLATFORM')!r}: {exc}; try PYOPENGL_PLATFORM=osmesa "
                          "or egl") from exc
    r._renderer._read_main_framebuffer = types.MethodType(_read_colour_only, r._renderer)
    platform = r._platform
    if hasattr(platform, "_egl_display"):
        # pyrender's EGL teardown calls eglTerminate on the device's display, which Mesa shares between
        # all contexts of the process: deleting one renderer would break every other one. Destroy only
        # this renderer's context.
        platform.delete_context = types.MethodType(_egl_delete_context_only, platform)
    return r


def _egl_delete_context_only(self) -> None:
    from OpenGL.EGL import eglDestroyContext  # noqa: PLC0415

    if self._egl_display is not None and self._egl_context is not None:
        eglDestroyContext(self._egl_display, self._egl_context)
    self._egl_context = None
    self._egl_display = None


def upload_positions(renderer, primitive, positions: np.ndarray) -> None:
    """Replace the vertex positions of a pyrender primitive in place (CPU copy and GL buffer).

    The primitive must have been created with positions (+ optional ``color_0``) only, no normals,
    tangents or texture coordinates, so that its GL vertex buffer is ``[xyz rgba]`` interleaved.
    """
    from OpenGL import GL  # noqa: PLC0415

    positions = np.asarray(positions, dtype=np.float32)
    primitive.positions = positions
    if not primitive._in_context():
        return  # uploaded on the next render
    data = positions if primitive.color_0 is None else np.hstack([positions, primitive.color_0])
    data = np.ascontiguousarray(data, dtype=np.float32).ravel()
    renderer._platform.make_current()
    try:
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, primitive._buffers[0])
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, data.nbytes, data)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
    finally:
        renderer._platform.make_uncurrent()
