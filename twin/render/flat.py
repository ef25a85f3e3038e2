"""The twin's flat renderer: unlit single-colour triangle meshes in several viewports of one framebuffer.

:class:`FlatRenderer` is what the twin's renderer draws with: pyrender's headless context
(:func:`twin.gl.offscreen_renderer`), but one tiny unlit shader and several viewports in one framebuffer
(both stereo views in one clear / resolve / read-back), without pyrender's per-frame scene traversal
(≈ 15-35 ms of Python per view measured here). Choosing and setting up the OpenGL platform is
:mod:`twin.gl`.
"""

from __future__ import annotations

import numpy as np

from twin.gl import RenderError, _import_gl, offscreen_renderer

__all__ = ["FlatRenderer"]

_FLAT_VERT = """#version 330 core
layout(location = 0) in vec3 position;
uniform mat4 mvp;
void main() { gl_Position = mvp * vec4(position, 1.0); }
"""
_FLAT_FRAG = """#version 330 core
uniform vec3 colour;
out vec4 frag_colour;
void main() { frag_colour = vec4(colour, 1.0); }
"""


class FlatRenderer:
    """Unlit, single-colour triangle meshes drawn into several viewports of ONE offscreen framebuffer.

    pyrender supplies only the headless context (:func:`offscreen_renderer`: EGL/OSMesa choice and the
    safe EGL teardown); drawing is one tiny shader program and one vertex array per mesh. Compared with
    ``pyrender.Renderer.render`` per camera, this saves the scene traversal and uniform set-up in Python,
    and a stereo pair costs one clear, one MSAA resolve and one read-back instead of two.

    Parameters
    ----------
    width_px, height_px : int
        Size of the whole framebuffer (e.g. two views side by side).
    samples : int
        MSAA samples per pixel (0 = no multisampling).

    Notes
    -----
    Colours are written as given (three floats in [0, 1]); the read-back is (H, W, 4) uint8 in the
    same channel order plus alpha, BOTTOM row first (OpenGL order). Depth test on; back faces are drawn unless a
    mesh asks for culling.
    """

    def __init__(self, width_px: int, height_px: int, *, samples: int = 4) -> None:
        GL, shaders = _import_gl()

        self._GL = GL
        self.width, self.height, self.samples = int(width_px), int(height_px), int(samples)
        self._offscreen = offscreen_renderer(8, 8)          # context owner only (its own buffers stay tiny)
        self._platform = self._offscreen._platform
        self._meshes: dict[object, list] = {}      # key -> [vao, vbo, ibo, n_index, n_vertex, colour, cull]
        self._readback = np.empty((self.height, self.width, 4), dtype=np.uint8)
        self._platform.make_current()
        try:
            self._program = shaders.compileProgram(shaders.compileShader(_FLAT_VERT, GL.GL_VERTEX_SHADER),
                                                   shaders.compileShader(_FLAT_FRAG, GL.GL_FRAGMENT_SHADER),
                                                   validate=False)
            self._loc_mvp = GL.glGetUniformLocation(self._program, "mvp")
            self._loc_colour = GL.glGetUniformLocation(self._program, "colour")
            w, h = self.width, self.height
            self._rb = GL.glGenRenderbuffers(3)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._rb[0])
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, self.samples, GL.GL_RGBA8, w, h)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._rb[1])
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, self.samples, GL.GL_DEPTH_COMPONENT24, w, h)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._rb[2])
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, w, h)
            self._fb_draw, self._fb_read = GL.glGenFramebuffers(2)
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fb_draw)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._rb[0])
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._rb[1])
            ok = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER) == GL.GL_FRAMEBUFFER_COMPLETE
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fb_read)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._rb[2])
            ok = ok and GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER) == GL.GL_FRAMEBUFFER_COMPLETE
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
            if not ok:
                raise RenderError(f"cannot create a {w}x{h} framebuffer with {self.samples} MSAA samples")
        finally:
            self._platform.make_uncurrent()

    def set_mesh(self, key, positions: np.ndarray, faces: np.ndarray | None, colour, *,
                 cull_back: bool = False) -> None:
        """Create or update mesh ``key``: positions (V, 3) float; faces (F, 3) int (None: keep the old ones).

        ``cull_back`` skips triangles seen from behind (counter-clockwise around their outward normal
        = front): only for closed, consistently outward-wound shells whose back half is hidden anyway.
        """
        GL = self._GL
        pos = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
        entry = self._meshes.get(key)
        self._platform.make_current()
        try:
            if entry is None:
                if faces is None:
                    raise RenderError(f"mesh {key!r}: faces are needed the first time")
                vao = GL.glGenVertexArrays(1)
                vbo, ibo = GL.glGenBuffers(2)
                GL.glBindVertexArray(vao)
                GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
                GL.glEnableVertexAttribArray(0)
                GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, 12, None)
                GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ibo)   # recorded in the VAO
                GL.glBindVertexArray(0)
                entry = [vao, vbo, ibo, 0, -1, None, False]
                self._meshes[key] = entry
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, entry[1])
            if len(pos) == entry[4]:
                GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, pos.nbytes, pos)
            else:
                GL.glBufferData(GL.GL_ARRAY_BUFFER, pos.nbytes, pos, GL.GL_DYNAMIC_DRAW)
                entry[4] = len(pos)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
            if faces is not None:
                idx = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1)
                if idx.size and (idx.max() >= len(pos)):
                    raise RenderError(f"mesh {key!r}: face index {int(idx.max())} >= {len(pos)} vertices")
                GL.glBindVertexArray(entry[0])
                GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, idx.nbytes, idx, GL.GL_STATIC_DRAW)
                GL.glBindVertexArray(0)
                entry[3] = idx.size
            entry[5] = np.asarray(colour, dtype=np.float32).reshape(3)
            entry[6] = bool(cull_back)
        finally:
            self._platform.make_uncurrent()

    def has_mesh(self, key) -> bool:
        return key in self._meshes

    def render(self, passes, background) -> np.ndarray:
        """Draw ``passes`` and read the framebuffer back.

        Parameters
        ----------
        passes : list of (viewport (x, y, w, h) px, mvp (4, 4) float, keys)
            Each pass draws the meshes ``keys`` into its viewport with the clip-from-world matrix ``mvp``.
        background : 3 floats
            Clear colour of the whole framebuffer.

        Returns
        -------
        (H, W, 4) uint8 view of a buffer reused by the next call: the three colour channels as given,
        then alpha; bottom row first. (RGBA reads straight into memory; an RGB read-back repacks every
        pixel and took ~2 ms of a 1520x574 frame on llvmpipe, RGBA 0.2 ms.)
        """
        GL = self._GL
        self._platform.make_current()
        try:
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._fb_draw)
            GL.glViewport(0, 0, self.width, self.height)
            GL.glClearColor(float(background[0]), float(background[1]), float(background[2]), 1.0)
            GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
            GL.glEnable(GL.GL_DEPTH_TEST)
            GL.glDepthFunc(GL.GL_LESS)
            GL.glDisable(GL.GL_CULL_FACE)
            GL.glFrontFace(GL.GL_CCW)
            GL.glCullFace(GL.GL_BACK)
            culling = False
            GL.glDisable(GL.GL_BLEND)
            if self.samples > 0:
                GL.glEnable(GL.GL_MULTISAMPLE)
            GL.glUseProgram(self._program)
            GL.glEnable(GL.GL_SCISSOR_TEST)      # a guard-band rasteriser must not spill into the next viewport
            for viewport, mvp, keys in passes:
                GL.glViewport(*(int(v) for v in viewport))
                GL.glScissor(*(int(v) for v in viewport))
                GL.glUniformMatrix4fv(self._loc_mvp, 1, GL.GL_TRUE, np.ascontiguousarray(mvp, dtype=np.float32))
                for key in keys:
                    vao, _, _, n_index, _, colour, cull = self._meshes[key]
                    if n_index == 0:
                        continue
                    if cull != culling:
                        (GL.glEnable if cull else GL.glDisable)(GL.GL_CULL_FACE)
                        culling = cull
                    GL.glUniform3fv(self._loc_colour, 1, colour)
                    GL.glBindVertexArray(vao)
                    GL.glDrawElements(GL.GL_TRIANGLES, n_index, GL.GL_UNSIGNED_INT, None)
            GL.glBindVertexArray(0)
            GL.glUseProgram(0)
            GL.glDisable(GL.GL_CULL_FACE)
            GL.glDisable(GL.GL_SCISSOR_TEST)
            w, h = self.width, self.height
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._fb_draw)
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._fb_read)
            GL.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST)
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._fb_read)
            GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
            GL.glReadPixels(0, 0, w, h, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE, self._readback)
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        finally:
            self._platform.make_uncurrent()
        return self._readback

    def delete(self) -> None:
        """Free the GL objects and the context."""
        if self._offscreen is None:
            return
        GL = self._GL
        try:
            self._platform.make_current()
            for vao, vbo, ibo, *_ in self._meshes.values():
                GL.glDeleteVertexArrays(1, [vao])
                GL.glDeleteBuffers(2, [vbo, ibo])
            GL.glDeleteFramebuffers(2, [self._fb_draw, self._fb_read])
            GL.glDeleteRenderbuffers(3, list(self._rb))
            GL.glDeleteProgram(self._program)
            self._platform.make_uncurrent()
        except Exception:  # noqa: BLE001 (best effort at teardown; the context goes next)
            pass
        self._meshes.clear()
        self._offscreen.delete()
        self._offscreen = None

    def __del__(self) -> None:
        try:
            self.delete()
        except Exception:  # noqa: BLE001
            pass
