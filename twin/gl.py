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

:class:`twin.render.flat.FlatRenderer` is what the twin's renderer draws with, in the context this module
sets up.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import types

import numpy as np

from pipeline.errors import UserError

__all__ = ["RenderError", "INSTALL_HINT", "setup_gl", "import_pyrender", "offscreen_renderer", "gl_platform"]


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
        # pyrender reads the variable at every context creation: keep it in step with the platform
        # OpenGL was imported with, even if the caller's environment changed since (a test's monkeypatch)
        os.environ["PYOPENGL_PLATFORM"] = _PLATFORM
        return _PLATFORM
    chosen = os.environ.get("PYOPENGL_PLATFORM")
    if chosen and "OpenGL" not in sys.modules:
        _check_requested_platform(chosen)
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


#: What each headless back end needs, in the words of the package that provides it (Debian names).
INSTALL_HINT = {
    "egl": "Mesa's EGL: install libegl1 and libegl-mesa0 (Debian/Ubuntu: apt-get install libegl1 libegl-mesa0)",
    "osmesa": "OSMesa: install libosmesa6 (Debian/Ubuntu: apt-get install libosmesa6)",
}


def _check_requested_platform(chosen: str) -> None:
    """An explicit ``PYOPENGL_PLATFORM`` must name a back end that can work here; PyOpenGL itself only
    fails later, with ``AttributeError: 'NoneType' object has no attribute 'glGetError'``."""
    if chosen == "osmesa" and ctypes.util.find_library("OSMesa") is None:
        raise RenderError("PYOPENGL_PLATFORM=osmesa but libOSMesa is not installed; "
                          f"{INSTALL_HINT['osmesa']}, or unset PYOPENGL_PLATFORM to use EGL")
    if chosen == "egl" and not _egl_works():
        raise RenderError("PYOPENGL_PLATFORM=egl but EGL cannot initialise a headless display; "
                          f"{INSTALL_HINT['egl']}, or set PYOPENGL_PLATFORM=osmesa with libosmesa6")
    if chosen not in ("egl", "osmesa"):
        raise RenderError(f"PYOPENGL_PLATFORM={chosen!r}: the twin renders headless with 'egl' or 'osmesa' "
                          f"({INSTALL_HINT['egl']}; or {INSTALL_HINT['osmesa']})")


def gl_platform() -> str | None:
    """The platform chosen by :func:`setup_gl`, or None if it has not run yet."""
    return _PLATFORM


def import_pyrender() -> types.ModuleType:
    """``pyrender``, imported after :func:`setup_gl`."""
    platform = setup_gl()
    try:
        import pyrender  # noqa: PLC0415 (deliberately late: platform must be chosen first)
    except (ImportError, AttributeError, OSError, RuntimeError) as exc:
        # PyOpenGL raises assorted errors when its platform library is missing or broken
        raise RenderError(f"headless OpenGL ({platform}) cannot be loaded ({type(exc).__name__}: {exc}); "
                          f"{INSTALL_HINT.get(platform, INSTALL_HINT['egl'])}") from None
    return pyrender


def _import_gl():
    """``OpenGL.GL`` and its ``shaders`` module, imported after :func:`setup_gl` chose the platform;
    a missing or broken platform library is a :class:`RenderError` naming what to install."""
    platform = setup_gl()
    try:
        from OpenGL import GL  # noqa: PLC0415
        from OpenGL.GL import shaders  # noqa: PLC0415
    except (ImportError, AttributeError, OSError, RuntimeError) as exc:
        raise RenderError(f"headless OpenGL ({platform}) cannot be loaded ({type(exc).__name__}: {exc}); "
                          f"{INSTALL_HINT.get(platform, INSTALL_HINT['egl'])}") from None
    return GL, shaders


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
        platform = os.environ.get("PYOPENGL_PLATFORM")
        raise RenderError(f"cannot create a {width_px}x{height_px} headless OpenGL context on platform "
                          f"{platform!r} ({type(exc).__name__}: {exc}); "
                          f"{INSTALL_HINT.get(platform or 'egl', INSTALL_HINT['egl'])}") from None
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
