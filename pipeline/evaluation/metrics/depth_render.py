"""Batched depth renders for VSD: many small crops drawn into one framebuffer, read once.

VSD needs, per image, the depth of the model in each GT pose and in each estimated pose,
and only where the model projects. Drawing each of them through pyrender costs fixed
overhead (scene traversal, 4x multisampled framebuffers, a blit and a readback that
waits for the rasteriser). Here every render of an image gets its own tile of one large
float framebuffer (an *atlas*); the tiles are drawn one after the other with raw OpenGL
calls, and the atlas is read back once.

On Mesa's llvmpipe what remains is mostly triangle setup, ~0.3-0.5 us per triangle
submitted (the ``models_eval`` meshes have triangles of about a pixel, a few thousand per
model). For closed outward-oriented meshes (:func:`is_closed_outward`) each render is
sent only the faces turned towards the camera (:func:`visible_faces`), about half, which
leaves the rendered pixels unchanged. (Also dropping the triangles that hold no pixel
centre was tried: exact too, but testing them in numpy cost more than drawing them.)

Conventions are those of ``pipeline.method.render.renderer``: poses are model-to-camera
(``R`` (3, 3), ``t`` (3,) mm), ``K`` (3, 3) is the OpenCV intrinsic matrix and crop pixel
``(i, j)`` of a box ``(x0, y0, w, h)`` samples the image point ``(x0 + j, y0 + i)`` in
the coordinates of ``K`` (the caller shifts ``K`` to choose where a pixel is sampled, see
``ErrorParams.render_offset``). Depth is float32 mm along the optical axis, 0 where the
model is absent. Like the BOP toolkit's renderers (and unlike pyrender), the fragment
shader writes the camera-frame z of the surface into a 32-bit float colour buffer, and
there is one sample per pixel.
"""

from __future__ import annotations

import ctypes
import os
from dataclasses import dataclass
from typing import Hashable, Sequence

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from .pose_errors import hull_indices  # noqa: E402

#: Near and far clipping planes (mm) used when a model is not entirely between them
#: (the default planes of ``pipeline.method.render.renderer.Renderer``).
ZNEAR: float = 10.0
ZFAR: float = 20000.0

#: EGL_EXT_platform_device's platform (not named by PyOpenGL).
EGL_PLATFORM_DEVICE_EXT = 0x313F

_VERTEX_SHADER = """
#version 330 core
layout(location = 0) in vec3 position;
uniform mat4 mvp;      // model -> clip space of the tile
uniform vec4 z_row;    // third row of the model -> camera transform
out float z_cam;
void main() {
    vec4 p = vec4(position, 1.0);
    z_cam = dot(z_row, p);
    gl_Position = mvp * p;
}
"""

_FRAGMENT_SHADER = """
#version 330 core
in float z_cam;
layout(location = 0) out float depth;
void main() {
    depth = z_cam;
}
"""


def projected_box(
    vertices: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    pad: int = 2,
) -> tuple[int, int, int, int] | None:
    """Pixel box ``(x0, y0, w, h)`` of a ``width`` x ``height`` image that holds the
    model's depth, or None when the model projects outside the image.

    vertices: (V, 3) mm in the model frame. Every rasterised pixel lies in the convex
    hull of the projected vertices, so their bounding box grown by ``pad`` pixels (and
    clipped to the image) is enough. The whole image when a vertex is not between the
    near and far planes (the projection does not bound the render then). The same rule
    as ``Renderer.object_box``, so both renderers draw the same boxes.
    """
    v = vertices @ np.asarray(R, dtype=np.float64).reshape(3, 3).T + np.asarray(t, dtype=np.float64).reshape(3)
    z = v[:, 2]
    if len(v) == 0 or z.min() <= ZNEAR or z.max() >= ZFAR:
        return (0, 0, int(width), int(height))
    K = np.asarray(K, dtype=np.float64)
    u = K[0, 0] * v[:, 0] / z + K[0, 1] * v[:, 1] / z + K[0, 2]
    w = K[1, 1] * v[:, 1] / z + K[1, 2]
    x0 = max(0, int(np.floor(u.min())) - pad)
    y0 = max(0, int(np.floor(w.min())) - pad)
    x1 = min(int(width), int(np.ceil(u.max())) + pad + 1)
    y1 = min(int(height), int(np.ceil(w.max())) + pad + 1)
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1 - x0, y1 - y0)


def is_closed_outward(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether back faces can never be the nearest surface of a mesh seen from outside.

    vertices (V, 3), faces (F, 3) vertex indices. True when every directed edge occurs
    once and its reverse once (closed, consistently wound, sharing vertex indices) and
    every connected part encloses a positive signed volume (faces wound counter-clockwise
    seen from outside). Then a ray from a camera outside the mesh first crosses a face
    towards the inside, i.e. a front face.
    """
    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(F) == 0:
        return False
    n = max(len(V), int(F.max()) + 1)
    a = F.reshape(-1)
    b = F[:, [1, 2, 0]].reshape(-1)
    edges = np.sort(a * n + b)
    if (np.diff(edges) == 0).any():
        return False  # a directed edge twice: not a consistently wound 2-manifold
    if not np.array_equal(edges, np.sort(b * n + a)):
        return False  # an edge without its reverse: a hole (or a flipped face)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    signed = np.einsum("ij,ij->i", p0, np.cross(p1, p2)) / 6.0
    part = label[F[:, 0]]
    volume = np.bincount(part, weights=signed)
    return bool((volume[np.unique(part)] > 0).all())


def tile_projection(K: np.ndarray, box: tuple[int, int, int, int], z_range: tuple[float, float]) -> np.ndarray:
    """(4, 4) float64 matrix from the OpenCV camera frame to the clip space of a tile.

    With the viewport set to the tile (``w`` x ``h`` pixels, window y up), window point
    ``(j + 0.5, i + 0.5)`` of the tile, where OpenGL samples its pixel ``(j, i)``, sees
    the image point ``(x0 + j, y0 + i)`` of ``K``: tile row i is image row ``y0 + i``
    (no flip; the readback's first row is the tile's bottom row, i.e. image row y0).
    ``z_range = (near, far)`` in mm maps to the depth range of the depth test.
    """
    x0, y0, w, h = box
    near, far = z_range
    K = np.asarray(K, dtype=np.float64)
    P = np.zeros((4, 4))
    # x_ndc = 2 (u - x0 + 0.5) / w - 1 with u = (K00 X + K01 Y + K02 Z) / Z.
    P[0, :3] = 2.0 * K[0] / w
    P[0, 2] += 2.0 * (0.5 - x0) / w - 1.0
    P[1, :3] = 2.0 * K[1] / h
    P[1, 2] += 2.0 * (0.5 - y0) / h - 1.0
    # Standard perspective depth: z_ndc = -1 at the near plane, +1 at the far plane.
    P[2, 2] = (far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


@dataclass(frozen=True)
class DepthRequest:
    """One depth render: mesh ``key`` in pose ``(R (3, 3), t (3,) mm)`` seen through
    ``K`` (3, 3), in the image region ``box = (x0, y0, w, h)``."""

    key: Hashable
    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    box: tuple[int, int, int, int]


@dataclass
class PendingDepths:
    """Renders started by :meth:`DepthAtlasRenderer.submit`: the requests, the tiles
    (request index, x, y) of the atlas still to be read back (rows [0, used_height)),
    and the crops read so far (None until read)."""

    requests: Sequence[DepthRequest]
    placed: list[tuple[int, int, int]]
    used_height: int
    out: list


@dataclass
class _Mesh:
    vertices: np.ndarray  # (V, 3) float64 mm
    faces: np.ndarray  # (F, 3) int64, indices into vertices
    base: int  # index of vertex 0 in the shared vertex buffer
    closed: bool  # is_closed_outward: back faces may be skipped
    normals: np.ndarray  # (F, 3) float64 un-normalised face normals (model frame)
    offsets: np.ndarray  # (F,) float64 -normals . first vertex (plane offsets)
    normal_norms: np.ndarray  # (F,) float64 lengths of the normals
    bound: np.ndarray  # (B, 3) float64 convex hull vertices: same boxes and depth ranges


def visible_faces(mesh: _Mesh, R: np.ndarray, t: np.ndarray) -> np.ndarray | None:
    """Indices (k,) into ``mesh.faces`` of the faces worth drawing; None for all.

    For a closed outward mesh (:func:`is_closed_outward`) entirely beyond the near plane
    (so the camera is outside it), the faces turned away from the camera are dropped: the
    nearest surface at any sample is a front face, and a silhouette sample on an edge
    shared by a front and a back face is covered by both or by neither (same edge, same
    fill rule), so the pixels are those of drawing every face. Otherwise every face is
    drawn (a vertex behind the near plane: clipping, the camera possibly inside).
    """
    if not mesh.closed:
        return None
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    z = mesh.bound @ R[2] + t[2]
    if len(z) == 0 or z.min() <= ZNEAR:
        return None
    # In the model frame the camera is at c = -R^T t; a face is seen from its front when
    # n . (c - p0) > 0. The tolerance keeps faces seen almost edge-on.
    side = mesh.offsets - mesh.normals @ (R.T @ t)
    return np.flatnonzero(side >= -1e-9 * mesh.normal_norms * (np.linalg.norm(t) + 1.0))


def _egl_display():
    """The EGL display of the first EGL device (Mesa: the software rasteriser on a
    machine without GPU), as pyrender's EGL platform picks it; the default display when
    the device extension is missing."""
    from OpenGL import EGL
    from OpenGL._opaque import opaque_pointer_cls

    def egl_function(name: bytes, restype):
        # Extension functions, without argtypes: ctypes passes the opaque pointers and
        # ints as they are (the way pyrender calls them).
        address = EGL.eglGetProcAddress(name)
        return ctypes.CFUNCTYPE(restype)(address) if address else None

    query_devices = egl_function(b"eglQueryDevicesEXT", EGL.EGLBoolean)
    platform_display = egl_function(b"eglGetPlatformDisplayEXT", EGL.EGLDisplay)
    if query_devices is not None and platform_display is not None:
        device_type = opaque_pointer_cls("EGLDeviceEXT")
        count = EGL.EGLint()
        if query_devices(0, None, ctypes.pointer(count)) and count.value > 0:
            devices = (device_type * count.value)()
            if query_devices(count.value, devices, ctypes.pointer(count)) and count.value > 0:
                return platform_display(EGL_PLATFORM_DEVICE_EXT, devices[0], None)
    return EGL.eglGetDisplay(EGL.EGL_DEFAULT_DISPLAY)


class _EglContext:
    """A headless OpenGL 3.3 core context (EGL, no surface), made current on creation.

    Set up directly with PyOpenGL's EGL bindings, as pyrender's EGL platform does, so
    that scoring does not import pyrender (about a second per process here).
    """

    def __init__(self) -> None:
        from OpenGL import EGL

        self._egl = EGL
        self.display = _egl_display()
        major, minor = ctypes.c_long(), ctypes.c_long()
        if not EGL.eglInitialize(self.display, major, minor):
            raise RuntimeError("EGL: eglInitialize failed (set PYOPENGL_PLATFORM=egl before importing OpenGL)")
        config_attribs = (EGL.EGLint * 7)(
            EGL.EGL_SURFACE_TYPE, EGL.EGL_PBUFFER_BIT, EGL.EGL_RENDERABLE_TYPE, EGL.EGL_OPENGL_BIT,
            EGL.EGL_CONFORMANT, EGL.EGL_OPENGL_BIT, EGL.EGL_NONE,
        )
        configs = (EGL.EGLConfig * 1)()
        n_configs = ctypes.c_long()
        if not EGL.eglChooseConfig(self.display, config_attribs, configs, 1, n_configs) or n_configs.value < 1:
            raise RuntimeError("EGL: no configuration for desktop OpenGL")
        if not EGL.eglBindAPI(EGL.EGL_OPENGL_API):
            raise RuntimeError("EGL: cannot bind the OpenGL API")
        context_attribs = (EGL.EGLint * 7)(
            EGL.EGL_CONTEXT_MAJOR_VERSION, 3, EGL.EGL_CONTEXT_MINOR_VERSION, 3,
            EGL.EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL.EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT, EGL.EGL_NONE,
        )
        self.context = EGL.eglCreateContext(self.display, configs[0], EGL.EGL_NO_CONTEXT, context_attribs)
        if not self.context:
            raise RuntimeError("EGL: cannot create an OpenGL 3.3 core context")
        self.make_current()

    def make_current(self) -> None:
        EGL = self._egl
        if not EGL.eglMakeCurrent(self.display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, self.context):
            raise RuntimeError("EGL: eglMakeCurrent failed")

    def destroy(self) -> None:
        """Release and destroy the context; the display stays initialised (other
        renderers of the process, pyrender's, may share it)."""
        EGL = self._egl
        EGL.eglMakeCurrent(self.display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
        EGL.eglDestroyContext(self.display, self.context)


class DepthAtlasRenderer:
    """Depth renders of registered meshes, batched in a float32 atlas framebuffer.

    Owns an EGL context (create it in the process that renders: EGL contexts must not
    cross a ``fork``; ``PYOPENGL_PLATFORM=egl`` must be set before OpenGL is first
    imported, which importing this module does when it is not set). Meshes are uploaded
    once (:meth:`add_mesh`); :meth:`render` draws a list of :class:`DepthRequest` into
    tiles of the atlas, as many per readback as fit, and returns their crops.
    """

    def __init__(self, atlas_width: int = 2048, atlas_height: int = 2048):
        from OpenGL import GL as gl

        self._gl = gl
        self.atlas_width = int(atlas_width)
        self.atlas_height = int(atlas_height)
        self._meshes: dict[Hashable, _Mesh] = {}
        self._context: _EglContext | None = None
        self._setup_gl()
        #: Requests drawn, atlas readbacks, triangles drawn / in the meshes (statistics).
        self.stats = {"renders": 0, "readbacks": 0, "faces_drawn": 0, "faces_total": 0}

    # ------------------------------------------------------------------ GL resources

    def _setup_gl(self) -> None:
        """A new context with the program, the atlas and the buffers (meshes uploaded)."""
        gl = self._gl
        self._context = _EglContext()
        self._program = self._link_program()
        self._mvp_loc = gl.glGetUniformLocation(self._program, "mvp")
        self._zrow_loc = gl.glGetUniformLocation(self._program, "z_row")
        self._fbo, self._color_tex, self._depth_rb = self._make_framebuffer()
        # One vertex buffer holds every mesh (re-uploaded when a mesh is added); each
        # batch uploads the indices of the faces it draws into the index buffer.
        self._vao = int(gl.glGenVertexArrays(1))
        self._vbo, self._ebo = (int(b) for b in gl.glGenBuffers(2))
        if self._meshes:
            self._upload_vertices()

    def _make_current(self) -> bool:
        """Make the context current, rebuilding it if it was lost (then True): pyrender
        terminates the EGL display (shared by every context of the process) when one of
        its renderers is deleted, which destroys this context too."""
        from OpenGL.error import GLError

        try:
            self._context.make_current()
        except (GLError, RuntimeError):
            self._setup_gl()
            return True
        return False

    def _link_program(self) -> int:
        gl = self._gl
        program = gl.glCreateProgram()
        shaders = []
        for kind, src in ((gl.GL_VERTEX_SHADER, _VERTEX_SHADER), (gl.GL_FRAGMENT_SHADER, _FRAGMENT_SHADER)):
            sh = gl.glCreateShader(kind)
            gl.glShaderSource(sh, src)
            gl.glCompileShader(sh)
            if not gl.glGetShaderiv(sh, gl.GL_COMPILE_STATUS):
                raise RuntimeError(f"depth shader: {gl.glGetShaderInfoLog(sh).decode(errors='replace')}")
            gl.glAttachShader(program, sh)
            shaders.append(sh)
        gl.glLinkProgram(program)
        if not gl.glGetProgramiv(program, gl.GL_LINK_STATUS):
            raise RuntimeError(f"depth program: {gl.glGetProgramInfoLog(program).decode(errors='replace')}")
        for sh in shaders:
            gl.glDeleteShader(sh)
        return int(program)

    def _make_framebuffer(self) -> tuple[int, int, int]:
        gl = self._gl
        W, H = self.atlas_width, self.atlas_height
        tex = gl.glGenTextures(1)
        gl.glBindTexture(gl.GL_TEXTURE_2D, tex)
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_R32F, W, H, 0, gl.GL_RED, gl.GL_FLOAT, None)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_NEAREST)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAG_FILTER, gl.GL_NEAREST)
        rb = gl.glGenRenderbuffers(1)
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, rb)
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_DEPTH_COMPONENT32F, W, H)
        fbo = gl.glGenFramebuffers(1)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, fbo)
        gl.glFramebufferTexture2D(gl.GL_FRAMEBUFFER, gl.GL_COLOR_ATTACHMENT0, gl.GL_TEXTURE_2D, tex, 0)
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_DEPTH_ATTACHMENT, gl.GL_RENDERBUFFER, rb)
        status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"depth atlas framebuffer incomplete (status {status:#x})")
        return int(fbo), int(tex), int(rb)

    def close(self) -> None:
        """Free the GL objects and the context. The EGL display is not terminated: other
        renderers of the process (pyrender's) share it."""
        if self._context is None:
            return
        from OpenGL.error import GLError

        gl = self._gl
        try:
            self._context.make_current()
        except (GLError, RuntimeError):
            pass  # the display was terminated (see _make_current): nothing left to free
        else:
            gl.glDeleteVertexArrays(1, [self._vao])
            gl.glDeleteBuffers(2, [self._vbo, self._ebo])
            gl.glDeleteFramebuffers(1, [self._fbo])
            gl.glDeleteTextures([self._color_tex])
            gl.glDeleteRenderbuffers(1, [self._depth_rb])
            gl.glDeleteProgram(self._program)
            self._context.destroy()
        self._context = None
        self._meshes.clear()

    def __enter__(self) -> "DepthAtlasRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ meshes

    def has_mesh(self, key: Hashable) -> bool:
        return key in self._meshes

    def add_mesh(self, key: Hashable, vertices: np.ndarray, faces: np.ndarray, hull: np.ndarray | None = None) -> None:
        """Register a triangle mesh: vertices (V, 3) mm, faces (F, 3) vertex indices;
        ``hull``: indices of its convex hull vertices when known (computed otherwise)."""
        V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        base = sum(len(m.vertices) for m in self._meshes.values())
        normals = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        offsets = -np.einsum("ij,ij->i", normals, V[F[:, 0]])
        # Extremes of the depth and of the projection (a linear-fractional map, so
        # convex sets in front of the camera stay convex) are reached at hull vertices.
        bound = V[hull_indices(V) if hull is None else np.asarray(hull)]
        self._meshes[key] = _Mesh(
            V, F, base, is_closed_outward(V, F), normals, offsets, np.linalg.norm(normals, axis=1), bound
        )
        self._upload_vertices()

    def _upload_vertices(self) -> None:
        gl = self._gl
        self._make_current()
        pos = np.ascontiguousarray(np.concatenate([m.vertices for m in self._meshes.values()]), dtype=np.float32)
        gl.glBindVertexArray(self._vao)
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, self._vbo)
        gl.glBufferData(gl.GL_ARRAY_BUFFER, pos.nbytes, pos, gl.GL_STATIC_DRAW)
        gl.glEnableVertexAttribArray(0)
        gl.glVertexAttribPointer(0, 3, gl.GL_FLOAT, gl.GL_FALSE, 12, ctypes.c_void_p(0))
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, self._ebo)
        gl.glBindVertexArray(0)

    def box(self, key: Hashable, R: np.ndarray, t: np.ndarray, K: np.ndarray, width: int, height: int):
        """:func:`projected_box` of a registered mesh in a ``width`` x ``height`` image
        (from its convex hull vertices, which give the same box)."""
        return projected_box(self._meshes[key].bound, R, t, K, width, height)

    # ------------------------------------------------------------------ rendering

    def render(self, requests: Sequence[DepthRequest]) -> list[np.ndarray]:
        """Depth crops (h, w) float32 mm, one per request, in order (0 off the model)."""
        return self.collect(self.submit(requests))

    def submit(self, requests: Sequence[DepthRequest]) -> "PendingDepths":
        """Start rendering ``requests``; :meth:`collect` returns their depth crops.

        Mesa's llvmpipe rasterises on its own threads once the draw calls are flushed, so
        the caller can work (MSSD, MSPD, reading the next depth image) until it collects,
        instead of waiting in the read-back (0.37 s of the bench file's 2.4 s of error
        computation). Nothing else may render on this renderer in between. Requests that
        do not fit in one atlas are drawn and read in full atlases first; only the last
        atlas is left pending."""
        out: list[np.ndarray | None] = [None] * len(requests)
        placed: list[tuple[int, int, int]] = []  # (request index, tile x, tile y)
        x = y = shelf = 0
        for i, req in enumerate(requests):
            _, _, w, h = req.box
            if w > self.atlas_width or h > self.atlas_height:
                raise ValueError(f"render box {req.box} larger than the {self.atlas_width}x{self.atlas_height} atlas")
            if x + w > self.atlas_width:  # next shelf
                x, y, shelf = 0, y + shelf, 0
            if y + h > self.atlas_height:  # atlas full: draw and read what is placed
                self._draw(requests, placed, y)
                self._read(requests, placed, y, out)
                placed, x, y, shelf = [], 0, 0, 0
            placed.append((i, x, y))
            x += w
            shelf = max(shelf, h)
        if placed:
            self._draw(requests, placed, y + shelf)
            self._gl.glFlush()
        return PendingDepths(requests, placed, y + shelf, out)

    def collect(self, pending: "PendingDepths") -> list[np.ndarray]:
        """The depth crops of a :meth:`submit`, waiting for the rasteriser if needed."""
        if pending.placed:
            if self._make_current():  # the context was lost since submit, and its drawing with it
                self._draw(pending.requests, pending.placed, pending.used_height)
            self._read(pending.requests, pending.placed, pending.used_height, pending.out)
            pending.placed = []
        return pending.out  # type: ignore[return-value]

    def _tile_matrices(self, req: DepthRequest) -> tuple[np.ndarray, np.ndarray]:
        """(mvp (4, 4), z_row (4,)) float32 for one request, computed in float64."""
        mesh = self._meshes[req.key]
        M = np.eye(4)
        M[:3, :3] = np.asarray(req.R, dtype=np.float64).reshape(3, 3)
        M[:3, 3] = np.asarray(req.t, dtype=np.float64).reshape(3)
        z = mesh.bound @ M[2, :3] + M[2, 3]
        if len(z) and z.min() > ZNEAR and z.max() < ZFAR:
            # Planes just around the posed model (as Renderer.render_depth_crop), with a
            # margin so that no vertex is clipped.
            margin = 1.0 + 1e-3 * float(z.max())
            z_range = (max(ZNEAR, float(z.min()) - margin), min(ZFAR, float(z.max()) + margin))
        else:
            z_range = (ZNEAR, ZFAR)
        mvp = tile_projection(req.K, req.box, z_range) @ M
        return mvp.astype(np.float32), M[2].astype(np.float32)

    def _draw(self, requests: Sequence[DepthRequest], placed: list[tuple[int, int, int]], used_height: int) -> None:
        """Draw the placed requests into their tiles of the atlas rows [0, used_height)."""
        gl = self._gl
        # Indices of every request's visible faces, in one upload.
        index_lists = []
        for i, _, _ in placed:
            req = requests[i]
            mesh = self._meshes[req.key]
            keep = visible_faces(mesh, req.R, req.t)
            faces = mesh.faces if keep is None else mesh.faces[keep]
            index_lists.append((faces + mesh.base).reshape(-1))
            self.stats["faces_drawn"] += len(faces)
            self.stats["faces_total"] += len(mesh.faces)
        indices = np.ascontiguousarray(np.concatenate(index_lists), dtype=np.uint32)

        self._make_current()
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbo)
        gl.glBindVertexArray(self._vao)
        gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, max(indices.nbytes, 4), indices if indices.size else None, gl.GL_STREAM_DRAW)
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glDisable(gl.GL_BLEND)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glDepthMask(gl.GL_TRUE)
        gl.glEnable(gl.GL_SCISSOR_TEST)
        # Clear only the rows in use (background: depth 0, depth buffer at the far plane).
        gl.glScissor(0, 0, self.atlas_width, used_height)
        gl.glClearColor(0.0, 0.0, 0.0, 0.0)
        gl.glClearDepth(1.0)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        gl.glUseProgram(self._program)
        start = 0
        for (i, tx, ty), idx in zip(placed, index_lists):
            if len(idx) == 0:
                continue
            _, _, w, h = requests[i].box
            mvp, z_row = self._tile_matrices(requests[i])
            # GL reads matrices column-major: transpose=GL_TRUE for row-major arrays.
            gl.glUniformMatrix4fv(self._mvp_loc, 1, gl.GL_TRUE, mvp)
            gl.glUniform4f(self._zrow_loc, *z_row.tolist())
            gl.glViewport(tx, ty, w, h)
            gl.glScissor(tx, ty, w, h)  # keeps every fragment inside its tile
            gl.glDrawElements(gl.GL_TRIANGLES, len(idx), gl.GL_UNSIGNED_INT, ctypes.c_void_p(4 * start))
            start += len(idx)
        gl.glBindVertexArray(0)

    def _read(self, requests: Sequence[DepthRequest], placed: list[tuple[int, int, int]], used_height: int,
              out: list) -> None:
        """Read the atlas rows [0, used_height) once and cut ``out[i]`` from them."""
        gl = self._gl
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbo)
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT0)
        gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 4)
        buf = np.empty((used_height, self.atlas_width), dtype=np.float32)
        gl.glReadPixels(0, 0, self.atlas_width, used_height, gl.GL_RED, gl.GL_FLOAT, buf)
        for i, tx, ty in placed:
            _, _, w, h = requests[i].box
            out[i] = buf[ty : ty + h, tx : tx + w].copy()
        self.stats["renders"] += len(placed)
        self.stats["readbacks"] += 1
