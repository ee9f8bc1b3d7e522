"""Building blocks for procedural meshes with near-uniform vertex spacing.

Every object is assembled from *patches*: planar regions (with holes), walls extruded
from 2D loops, surfaces of revolution and spheres. Each builder takes a target edge
length ``spacing`` (mm), so the same construction yields the coloured model (about
2 mm edges, fine enough for vertex colours to carry a printed label) and the
``models_eval`` mesh (coarser, vertices roughly uniform over the surface).

Patches that meet along an edge sample that edge identically, so merging coincident
vertices gives a watertight mesh; the coloured model keeps patches unmerged so that
normals stay sharp at creases.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import trimesh
from matplotlib.path import Path as MplPath
from scipy.spatial import Delaunay

ColorFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(vertices (V, 3) mm, uv (V, 2) mm) -> colours (V, 3) uint8."""


@dataclass
class Patch:
    """One smooth piece of surface.

    vertices: (V, 3) float64 mm. faces: (F, 3) int64, counter-clockwise seen from
    outside. uv: (V, 2) float64 mm, patch-local coordinates used to print labels.
    colors: (V, 3) uint8 or None until painted.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    colors: np.ndarray | None = None

    def transformed(self, T: np.ndarray) -> "Patch":
        """Copy moved by the rigid (4, 4) transform ``T`` (colours and uv kept)."""
        v = self.vertices @ T[:3, :3].T + T[:3, 3]
        return Patch(v, self.faces.copy(), self.uv.copy(), None if self.colors is None else self.colors.copy())

    def painted(self, color: ColorFn | Sequence[int]) -> "Patch":
        """Copy with colours from a colour function or one RGB triple."""
        if callable(color):
            cols = np.asarray(color(self.vertices, self.uv))
        else:
            cols = np.tile(np.asarray(color, dtype=np.uint8), (len(self.vertices), 1))
        cols = np.clip(np.round(cols), 0, 255).astype(np.uint8) if cols.dtype != np.uint8 else cols
        if cols.shape != (len(self.vertices), 3):
            raise ValueError(f"colour function returned shape {cols.shape}, expected ({len(self.vertices)}, 3)")
        return Patch(self.vertices, self.faces, self.uv, cols)


# ---------------------------------------------------------------------------- 2D loops


def circle(radius: float, n: int, center: Sequence[float] = (0.0, 0.0), phase: float = 0.0) -> np.ndarray:
    """(n, 2) counter-clockwise points on a circle, the first at angle ``phase`` (rad)."""
    a = phase + 2.0 * np.pi * np.arange(n) / n
    return np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)], axis=1)


def circle_count(radius: float, spacing: float, multiple: int = 4) -> int:
    """Number of segments giving edges of about ``spacing`` mm, rounded up to ``multiple``."""
    n = max(int(np.ceil(2.0 * np.pi * radius / spacing)), 3 * multiple)
    return int(np.ceil(n / multiple) * multiple)


def rectangle(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """(4, 2) counter-clockwise corners of an axis-aligned rectangle."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def signed_area(loop: np.ndarray) -> float:
    """Shoelace area of a closed (n, 2) loop; positive when counter-clockwise."""
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def resample_loop(loop: np.ndarray, spacing: float) -> np.ndarray:
    """Subdivide every edge of a closed (n, 2) loop into pieces of at most ``spacing``.

    The original corners are kept, and an edge is split into ``ceil(length / spacing)``
    equal parts, so two loops that share an edge sample it at the same points.
    """
    out = []
    n = len(loop)
    for i in range(n):
        a, b = loop[i], loop[(i + 1) % n]
        k = max(int(np.ceil(np.linalg.norm(b - a) / spacing - 1e-9)), 1)
        t = np.arange(k)[:, None] / k
        out.append(a + t * (b - a))
    return np.concatenate(out, axis=0)


def _segments(loops: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    a = np.concatenate([lp for lp in loops])
    b = np.concatenate([np.roll(lp, -1, axis=0) for lp in loops])
    return a, b


def _distance_to_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Distance (P,) of points p (P, 2) to the nearest of the segments a-b (S, 2)."""
    out = np.empty(len(p))
    ab = b - a
    ab2 = np.maximum(np.sum(ab * ab, axis=1), 1e-30)
    for s in range(0, len(p), chunk):
        q = p[s : s + chunk, None, :]
        t = np.clip(np.sum((q - a) * ab, axis=2) / ab2, 0.0, 1.0)
        d = q - (a + t[..., None] * ab)
        out[s : s + chunk] = np.sqrt(np.min(np.sum(d * d, axis=2), axis=1))
    return out


def triangulate_region(outer: np.ndarray, holes: Sequence[np.ndarray], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate a planar region with holes, vertices about ``spacing`` apart.

    outer: (n, 2) closed loop, already resampled (``resample_loop``); holes: loops,
    resampled too. The result keeps every boundary point as a vertex, in order (outer
    first, then holes), and adds a triangular lattice inside. Boundary segments are at
    most ``spacing`` long and lattice points keep 0.55 * spacing away from them, so
    every segment is a Gabriel edge and the Delaunay triangulation contains it.

    Returns points (V, 2) float64 and faces (F, 3) int64, counter-clockwise.
    """
    outer = np.asarray(outer, float)
    if signed_area(outer) < 0:
        raise ValueError("triangulate_region: outer loop must be counter-clockwise")
    holes = [np.asarray(h, float) for h in holes]
    loops = [outer] + holes
    boundary = np.concatenate(loops)
    lo, hi = outer.min(axis=0), outer.max(axis=0)
    row = spacing * np.sqrt(3.0) / 2.0
    ys = np.arange(lo[1] + 0.5 * row, hi[1], row)
    pts = []
    for j, y in enumerate(ys):
        xs = np.arange(lo[0] + (0.25 if j % 2 else 0.75) * spacing, hi[0], spacing)
        pts.append(np.stack([xs, np.full_like(xs, y)], axis=1))
    lattice = np.concatenate(pts) if pts else np.zeros((0, 2))
    if len(lattice):
        inside = MplPath(outer).contains_points(lattice)
        for h in holes:
            inside &= ~MplPath(h).contains_points(lattice)
        lattice = lattice[inside]
    if len(lattice):
        a, b = _segments(loops)
        lattice = lattice[_distance_to_segments(lattice, a, b) >= 0.55 * spacing]
    points = np.concatenate([boundary, lattice])
    tri = Delaunay(points)
    faces = tri.simplices.astype(np.int64)
    p = points[faces]
    cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    faces[cross < 0] = faces[cross < 0][:, [0, 2, 1]]
    centroid = p.mean(axis=1)
    keep = MplPath(outer).contains_points(centroid) & (np.abs(cross) > 1e-12 * spacing**2)
    for h in holes:
        keep &= ~MplPath(h).contains_points(centroid)
    faces = faces[keep]
    _check_boundary_edges(loops, faces)
    return points, faces


def _check_boundary_edges(loops: Sequence[np.ndarray], faces: np.ndarray) -> None:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    have = set(map(tuple, edges.tolist()))
    start = 0
    for lp in loops:
        idx = np.arange(start, start + len(lp))
        for a, b in zip(idx, np.roll(idx, -1)):
            if (min(a, b), max(a, b)) not in have:
                raise RuntimeError(f"triangulate_region: boundary edge {a}-{b} missing (loops too close for the spacing?)")
        start += len(lp)


# ---------------------------------------------------------------------------- patches


def planar_patch(
    outer: np.ndarray,
    holes: Sequence[np.ndarray],
    spacing: float,
    origin: Sequence[float],
    u_axis: Sequence[float],
    v_axis: Sequence[float],
) -> Patch:
    """A planar region in 3D: point (x, y) of the 2D region goes to origin + x u + y v.

    The face normal is ``u x v``; loops must already be resampled.
    """
    pts, faces = triangulate_region(outer, holes, spacing)
    o, u, v = (np.asarray(a, float) for a in (origin, u_axis, v_axis))
    verts = o + pts[:, :1] * u + pts[:, 1:2] * v
    return Patch(verts, faces, pts.copy())


def _corner_runs(loop: np.ndarray, crease_deg: float) -> list[np.ndarray]:
    """Split a closed loop into index runs at corners sharper than ``crease_deg``."""
    n = len(loop)
    d_in = loop - np.roll(loop, 1, axis=0)
    d_out = np.roll(loop, -1, axis=0) - loop
    cosang = np.sum(d_in * d_out, axis=1) / (np.linalg.norm(d_in, axis=1) * np.linalg.norm(d_out, axis=1))
    corners = np.flatnonzero(cosang < np.cos(np.radians(crease_deg)))
    if len(corners) == 0:
        return [np.append(np.arange(n), 0)]
    runs = []
    for k, c in enumerate(corners):
        nxt = corners[(k + 1) % len(corners)]
        length = (nxt - c) % n or n
        runs.append((c + np.arange(length + 1)) % n)
    return runs


def wall_patches(loop: np.ndarray, z0: float, z1: float, spacing: float, crease_deg: float = 30.0) -> list[Patch]:
    """Side walls of a loop extruded from z0 to z1 (the loop lies in the xy plane).

    The wall's normal points to the right of the loop direction: outward for a
    counter-clockwise outer boundary, into the hole for a clockwise hole loop. One
    patch per run between sharp corners, so normals stay sharp at corners.
    """
    nz = max(int(np.ceil((z1 - z0) / spacing - 1e-9)), 1)
    zs = np.linspace(z0, z1, nz + 1)
    patches = []
    for run in _corner_runs(loop, crease_deg):
        pts = loop[run]
        m = len(pts)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        verts = np.concatenate([np.column_stack([pts, np.full(m, z)]) for z in zs])
        uv = np.concatenate([np.column_stack([arc, np.full(m, z)]) for z in zs])
        i = np.arange(m - 1)[None, :] + m * np.arange(nz)[:, None]
        i = i.ravel()
        faces = np.concatenate([np.stack([i, i + 1, i + 1 + m], 1), np.stack([i, i + 1 + m, i + m], 1)])
        patches.append(Patch(verts, faces.astype(np.int64), uv))
    return patches


def _flip_y(loop: np.ndarray) -> np.ndarray:
    """Mirror a loop in y and reverse it, so a CCW loop stays CCW."""
    return (loop * np.array([1.0, -1.0]))[::-1]


def horizontal_patch(outer: np.ndarray, holes: Sequence[np.ndarray], z: float, spacing: float, up: bool) -> Patch:
    """Planar region at height z facing +z (``up``) or -z; loops resampled, outer CCW.

    The region covers the same 3D points either way, so the two caps of an
    extrusion share their rims with the walls.
    """
    if up:
        return planar_patch(outer, holes, spacing, (0, 0, z), (1, 0, 0), (0, 1, 0))
    return planar_patch(_flip_y(outer), [_flip_y(h) for h in holes], spacing, (0, 0, z), (1, 0, 0), (0, -1, 0))


def extrude_patches(outer: np.ndarray, holes: Sequence[np.ndarray], z0: float, z1: float, spacing: float) -> dict[str, list[Patch]]:
    """Closed prism of a 2D region with holes between heights z0 < z1.

    Returns {"top": [...], "bottom": [...], "walls": [...], "hole_walls": [...]}. Loops
    may have any orientation; they are resampled to ``spacing``.
    """
    outer = resample_loop(np.asarray(outer, float), spacing)
    if signed_area(outer) < 0:
        outer = outer[::-1]
    hl = []
    for h in holes:
        h = resample_loop(np.asarray(h, float), spacing)
        hl.append(h if signed_area(h) < 0 else h[::-1])
    return {
        "top": [horizontal_patch(outer, hl, z1, spacing, up=True)],
        "bottom": [horizontal_patch(outer, hl, z0, spacing, up=False)],
        "walls": wall_patches(outer, z0, z1, spacing),
        "hole_walls": [p for h in hl for p in wall_patches(h, z0, z1, spacing)],
    }


def revolve_patch(profile: np.ndarray, n: int, phase: float = 0.0) -> Patch:
    """Surface of revolution about z of an open (m, 2) profile of (r, z) points, r >= 0.

    ``n`` sections per ring, the first at angle ``phase``. A profile walked
    counter-clockwise in the (r, z) half-plane (material on its left) gives outward
    normals. uv = (angle * r, arc length along the profile) in mm.
    """
    profile = np.asarray(profile, float)
    m = len(profile)
    a = phase + 2.0 * np.pi * np.arange(n) / n
    r, z = profile[:, 0], profile[:, 1]
    verts = np.stack(
        [np.outer(r, np.cos(a)).ravel(), np.outer(r, np.sin(a)).ravel(), np.repeat(z, n)], axis=1
    )
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(profile, axis=0), axis=1))])
    uv = np.stack([np.outer(r, a).ravel(), np.repeat(arc, n)], axis=1)
    j = np.arange(m - 1)[:, None] * n
    k = np.arange(n)[None, :]
    k1 = (k + 1) % n
    p00, p01, p10, p11 = (j + k).ravel(), (j + k1).ravel(), (j + n + k).ravel(), (j + n + k1).ravel()
    # Order (theta before s) makes the normal d(theta) x d(s): outward for a CCW profile.
    faces = np.concatenate([np.stack([p00, p01, p11], 1), np.stack([p00, p11, p10], 1)])
    # A ring on the axis (a cone's apex) collapses to its first vertex.
    remap = np.arange(m * n)
    for ring in np.flatnonzero(r < 1e-9):
        remap[ring * n : (ring + 1) * n] = ring * n
    faces = remap[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    return compact(Patch(verts, faces.astype(np.int64), uv))


def compact(patch: Patch) -> Patch:
    """Drop vertices no face uses, renumbering faces."""
    used = np.unique(patch.faces)
    if len(used) == len(patch.vertices):
        return patch
    remap = np.full(len(patch.vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    cols = None if patch.colors is None else patch.colors[used]
    return Patch(patch.vertices[used], remap[patch.faces], patch.uv[used], cols)


def resample_profile(points: np.ndarray, spacing: float) -> np.ndarray:
    """Subdivide an open (m, 2) polyline so that no piece exceeds ``spacing``."""
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        k = max(int(np.ceil(np.linalg.norm(b - a) / spacing - 1e-9)), 1)
        t = np.arange(1, k + 1)[:, None] / k
        out.append(a + t * (b - a))
    return np.concatenate(out)


def disc_patch(radius: float, n: int, z: float, spacing: float, up: bool, hole: tuple[float, int] | None = None) -> Patch:
    """Horizontal disc (or annulus with ``hole`` = (radius, count)) at height z.

    Its rim uses ``circle(radius, n)`` so it meets walls built from the same circle.
    """
    holes = [circle(hole[0], hole[1])[::-1]] if hole else []
    return horizontal_patch(circle(radius, n), holes, z, spacing, up)


def sphere_patch(radius: float, spacing: float, center: Sequence[float] = (0.0, 0.0, 0.0)) -> Patch:
    """Icosphere whose edges are about ``spacing`` mm; uv = (longitude * r, z)."""
    sub = max(int(np.ceil(np.log2(1.05 * radius / spacing))), 1)
    ico = trimesh.creation.icosphere(subdivisions=sub, radius=radius)
    v = np.asarray(ico.vertices, float)
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) * radius, v[:, 2]], axis=1)
    return Patch(v + np.asarray(center, float), np.asarray(ico.faces, np.int64), uv)


def box_patches(
    extents: Sequence[float],
    spacing: float,
    top_holes: Sequence[np.ndarray] = (),
    skip: Sequence[str] = (),
) -> dict[str, Patch]:
    """The six faces of an axis-aligned box centred at the origin, by name.

    Names: front (-y), back (+y), right (+x), left (-x), top (+z), bottom (-z). Each
    face's uv runs from (0, 0) at its lower-left corner seen from outside (z up for
    the sides), so labels print upright. ``top_holes``: loops in top-face uv
    (resampled, clockwise) cut out of the top, e.g. where another part stands.
    """
    X, Y, Z = (float(e) for e in extents)
    hx, hy, hz = X / 2, Y / 2, Z / 2
    faces = {
        "front": ((-hx, -hy, -hz), (1, 0, 0), (0, 0, 1), X, Z),
        "back": ((hx, hy, -hz), (-1, 0, 0), (0, 0, 1), X, Z),
        "right": ((hx, -hy, -hz), (0, 1, 0), (0, 0, 1), Y, Z),
        "left": ((-hx, hy, -hz), (0, -1, 0), (0, 0, 1), Y, Z),
        "top": ((-hx, -hy, hz), (1, 0, 0), (0, 1, 0), X, Y),
        "bottom": ((-hx, hy, -hz), (1, 0, 0), (0, -1, 0), X, Y),
    }
    out = {}
    for name, (o, u, v, w, h) in faces.items():
        if name in skip:
            continue
        holes = list(top_holes) if name == "top" else []
        out[name] = planar_patch(resample_loop(rectangle(0, 0, w, h), spacing), holes, spacing, o, u, v)
    return out


# ---------------------------------------------------------------------------- assembly


def concatenate(patches: Sequence[Patch]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Stack patches: vertices (V, 3), faces (F, 3) int64, colours (V, 3) uint8 or None."""
    verts, faces, cols = [], [], []
    off = 0
    for p in patches:
        verts.append(p.vertices)
        faces.append(p.faces + off)
        cols.append(p.colors)
        off += len(p.vertices)
    colors = None if any(c is None for c in cols) else np.concatenate(cols)
    return np.concatenate(verts), np.concatenate(faces), colors


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) float64."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def merged_mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """Mesh with coincident vertices merged (watertight when the patches close up)."""
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    mesh.merge_vertices(merge_tex=True, merge_norm=True, digits_vertex=6)
    mesh.remove_unreferenced_vertices()
    return mesh
