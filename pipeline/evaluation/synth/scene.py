"""Scene composition: the room and table, object layouts, cameras and lights.

World frame: the table top is the plane z = 0 (mm), z up. Objects rest on it in one of
their stable poses (``trimesh`` stable poses of the watertight model), with a random
yaw and position, and their footprints (convex hulls projected on the table) do not
overlap, so no two objects interpenetrate. Distractors (plain boxes, cylinders, dishes
outside the dataset) add clutter and occlusion. The room is a tiled floor 750 mm below
the table and four walls. Cameras look at the cluster from varied elevations and
distances, in the OpenCV convention (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Hashable

import numpy as np
import trimesh
from PIL import Image
from scipy.spatial import ConvexHull

from pipeline.method.render import Light, Lighting

from .objects import SynthObject, physics_mesh
from .textures import TABLE_TEXTURES

TABLE_THICKNESS_MM = 30.0
FLOOR_Z_MM = -750.0


# ---------------------------------------------------------------------------- stable poses


@dataclass
class RestingPoses:
    """Stable resting rotations of one object on a horizontal plane.

    rotations: (k, 3, 3) float64 model-to-world rotations with the object's lowest
    point on z = 0 after adding ``lift`` (k,) mm. probs: (k,) float64, sums to 1.
    hull: (h, 3) float64 convex-hull vertices of the model, mm.
    """

    rotations: np.ndarray
    lift: np.ndarray
    probs: np.ndarray
    hull: np.ndarray


def resting_poses(obj: SynthObject | trimesh.Trimesh, min_prob: float = 0.04) -> RestingPoses:
    """Stable poses of an object or a watertight mesh (probability >= ``min_prob``, renormalised).

    Uses the watertight model's centre of mass, so a cup rests on its base or rim
    or its side, as a real one would.
    """
    mesh = obj if isinstance(obj, trimesh.Trimesh) else physics_mesh(obj)
    transforms, probs = trimesh.poses.compute_stable_poses(mesh, n_samples=1, sigma=0.0)
    probs = np.asarray(probs, float)
    keep = probs >= min_prob
    if not np.any(keep):
        keep = probs == probs.max()
    rots = np.asarray(transforms)[keep, :3, :3]
    p = probs[keep] / probs[keep].sum()
    hull_v = np.asarray(mesh.vertices)[ConvexHull(np.asarray(mesh.vertices)).vertices]
    lift = np.array([-(hull_v @ R.T)[:, 2].min() for R in rots])
    return RestingPoses(rots, lift, p, hull_v)


# ---------------------------------------------------------------------------- layout


@dataclass
class Placement:
    """One instance on the table: its key (an obj_id, or a distractor's key),
    model-to-world R (3, 3) and t (3,) mm."""

    key: Hashable
    R: np.ndarray
    t: np.ndarray


def _footprint(hull: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(k, 2) counter-clockwise convex polygon of the posed hull projected on the table."""
    p = (hull @ R.T + t)[:, :2]
    h = ConvexHull(p)
    return p[h.vertices]


def _separated(a: np.ndarray, b: np.ndarray, margin: float) -> bool:
    """True if two convex polygons are more than ``margin`` mm apart along some edge normal."""
    for poly in (a, b):
        e = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([e[:, 1], -e[:, 0]], axis=1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        pa, pb = a @ normals.T, b @ normals.T
        gap = np.maximum(pb.min(axis=0) - pa.max(axis=0), pa.min(axis=0) - pb.max(axis=0))
        if np.any(gap > margin):
            return True
    return False


def layout_objects(
    keys: list[Hashable],
    poses: dict[Hashable, RestingPoses],
    rng: np.random.Generator,
    gap_mm: tuple[float, float] = (3.0, 15.0),
    near_prob: float = 0.75,
    tries: int = 400,
) -> list[Placement]:
    """Place instances (keys of ``poses``) on the table without overlap, clustered for occlusion.

    With probability ``near_prob`` an instance is dropped next to an already placed
    one (a random gap in ``gap_mm``), otherwise anywhere in a disc that grows with the
    instance count; footprints stay at least ``gap_mm[0]`` apart.
    """
    radius = max(100.0, 65.0 * np.sqrt(len(keys)))
    placed: list[Placement] = []
    prints: list[np.ndarray] = []
    for key in keys:
        rp = poses[key]
        for _ in range(tries):
            k = rng.choice(len(rp.probs), p=rp.probs)
            yaw = rng.uniform(0, 2 * np.pi)
            c, s = np.cos(yaw), np.sin(yaw)
            R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ rp.rotations[k]
            local = rp.hull @ R.T
            centre = 0.5 * (local.min(axis=0) + local.max(axis=0))
            if placed and rng.random() < near_prob:
                j = rng.integers(len(placed))
                ang = rng.uniform(0, 2 * np.pi)
                reach = 0.5 * (np.ptp(prints[j], axis=0).max() + np.ptp(local[:, :2], axis=0).max())
                xy = placed[j].t[:2] + (reach + rng.uniform(*gap_mm)) * np.array([np.cos(ang), np.sin(ang)])
            else:
                r = radius * np.sqrt(rng.random())
                ang = rng.uniform(0, 2 * np.pi)
                xy = r * np.array([np.cos(ang), np.sin(ang)])
            t = np.array([xy[0] - centre[0], xy[1] - centre[1], rp.lift[k]])
            fp = _footprint(rp.hull, R, t)
            if all(_separated(fp, other, gap_mm[0]) for other in prints):
                placed.append(Placement(key, R, t))
                prints.append(fp)
                break
        else:
            raise RuntimeError(f"could not place {key!r} without overlap after {tries} tries")
    return placed


# ---------------------------------------------------------------------------- distractors


def make_distractor(rng: np.random.Generator) -> trimesh.Trimesh:
    """A clutter object that is not in the dataset: a box, a cylinder or a flat dish.

    40-150 mm, one or two plain colours, watertight, centred at its bbox centre.
    """
    kind = rng.choice(["box", "cylinder", "dish"])
    if kind == "box":
        mesh = trimesh.creation.box(extents=rng.uniform(35, 140, size=3))
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=rng.uniform(18, 45), height=rng.uniform(40, 150), sections=48)
    else:
        mesh = trimesh.creation.cylinder(radius=rng.uniform(50, 75), height=rng.uniform(12, 25), sections=64)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    base = rng.uniform(30, 240, size=3)
    top = base if rng.random() < 0.5 else rng.uniform(30, 240, size=3)
    # Top and bottom vertices may differ in colour: a two-tone gradient.
    upper = np.asarray(mesh.vertices)[:, 2] > 0
    cols = np.where(upper[:, None], top, base)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.column_stack([cols, np.full(len(cols), 255)]).astype(np.uint8))
    return mesh


# ---------------------------------------------------------------------------- cameras


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera R (3, 3), t (3,) mm of an OpenCV camera at ``eye`` looking at ``target``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z])
    return R, -R @ eye


def project(points_c: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) pixel coordinates of camera-frame points (N, 3) mm."""
    uvw = points_c @ K.T
    return uvw[:, :2] / uvw[:, 2:3]


def sample_views(
    placements: list[Placement],
    n_views: int,
    K: np.ndarray,
    size: tuple[int, int],
    rng: np.random.Generator,
    elevation_deg: tuple[float, float],
    distance_mm: tuple[float, float],
    margin_px: float = 30.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n_views`` world-to-camera poses around the placed objects.

    Azimuths are spread around the table; a view is redrawn (up to 100 times) until
    the centre of every instance projects inside the image with ``margin_px``.
    """
    w, h = size
    centres = np.array([p.t for p in placements])
    target = centres.mean(axis=0)
    target[2] = 30.0
    az0 = rng.uniform(0, 2 * np.pi)
    views = []
    for k in range(n_views):
        for _ in range(100):
            az = az0 + 2 * np.pi * k / n_views + rng.uniform(-0.35, 0.35)
            el = np.radians(rng.uniform(*elevation_deg))
            d = rng.uniform(*distance_mm)
            aim = target + np.array([rng.uniform(-40, 40), rng.uniform(-40, 40), 0.0])
            eye = aim + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            R, t = look_at(eye, aim, roll=np.radians(rng.uniform(-8, 8)))
            uv = project(centres @ R.T + t, K)
            if np.all((uv >= margin_px) & (uv <= np.array([w, h]) - margin_px)):
                break
        views.append((R, t))
    return views


# ---------------------------------------------------------------------------- lights


def kelvin_to_rgb(kelvin: float) -> np.ndarray:
    """(3,) float RGB in [0, 1] of a black body at ``kelvin`` (interpolated sRGB table)."""
    table_k = np.array([2000, 2700, 3500, 4000, 5000, 5500, 6500, 8000])
    table = np.array(
        [[255, 138, 18], [255, 169, 87], [255, 196, 137], [255, 209, 163], [255, 228, 206],
         [255, 236, 224], [255, 249, 253], [227, 233, 255]], float
    )
    return np.array([np.interp(kelvin, table_k, table[:, c]) for c in range(3)]) / 255.0


@dataclass
class SceneLights:
    """Lights fixed in the world frame (mm).

    ambient: (3,) RGB. Each light: kind ("directional", "point" or "spot"), travel
    direction (3,) (directional, spot), position (3,) mm (point, spot), RGB colour,
    intensity (point and spot intensities are scaled by distance^2 in mm^2).
    At most one light of each kind: pyrender sums same-kind lights in an order that
    varies between runs, which would break bit-identical output.
    """

    ambient: np.ndarray
    lights: list[dict]

    def in_camera(self, R_w2c: np.ndarray, t_w2c: np.ndarray) -> Lighting:
        """The renderer's ``Lighting`` for a camera with world-to-camera pose (R, t)."""
        out = []
        for L in self.lights:
            out.append(Light(
                kind=L["kind"],
                direction=tuple(R_w2c @ L["direction"]),
                position=tuple(R_w2c @ L["position"] + t_w2c),
                color=tuple(L["color"]),
                intensity=float(L["intensity"]),
                outer_cone=float(L.get("outer_cone", np.pi / 4)),
                inner_cone=float(L.get("inner_cone", 0.0)),
            ))
        return Lighting(ambient=tuple(self.ambient), lights=out)


def _above(rng: np.random.Generator, target: np.ndarray) -> np.ndarray:
    r, a = rng.uniform(300, 1200), rng.uniform(0, 2 * np.pi)
    return target + np.array([r * np.cos(a), r * np.sin(a), rng.uniform(700, 1600)])


def sample_lights(rng: np.random.Generator, target: np.ndarray) -> SceneLights:
    """Ambient, a directional key light, and maybe a lamp (point) and a spot on ``target``.

    Each light has its own colour temperature (2700-7500 K), so 1-3 lights in all.
    """
    ambient = rng.uniform(0.12, 0.3) * kelvin_to_rgb(rng.uniform(3000, 7000))
    el, az = np.radians(rng.uniform(35, 85)), rng.uniform(0, 2 * np.pi)
    lights = [{
        "kind": "directional",
        "direction": -np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]),
        "position": np.zeros(3),
        "color": kelvin_to_rgb(rng.uniform(2700, 7500)),
        "intensity": rng.uniform(2.0, 4.0),
    }]
    if rng.random() < 0.6:
        pos = _above(rng, target)
        d2 = float(np.sum((pos - target) ** 2))
        lights.append({"kind": "point", "direction": np.array([0.0, 0.0, -1.0]), "position": pos,
                       "color": kelvin_to_rgb(rng.uniform(2700, 7500)), "intensity": rng.uniform(0.8, 2.0) * d2})
    if rng.random() < 0.4:
        pos = _above(rng, target)
        d = target - pos
        outer = np.radians(rng.uniform(20, 40))
        lights.append({"kind": "spot", "direction": d / np.linalg.norm(d), "position": pos,
                       "color": kelvin_to_rgb(rng.uniform(2700, 7500)), "intensity": rng.uniform(1.5, 3.0) * float(d @ d),
                       "outer_cone": outer, "inner_cone": 0.6 * outer})
    # Several lights share the budget so the image is not blown out.
    scale = 1.0 / np.sqrt(len(lights))
    for L in lights:
        L["intensity"] *= scale
    return SceneLights(ambient, lights)


# ---------------------------------------------------------------------------- room


def _textured_quad(x0: float, x1: float, y0: float, y1: float, z: float, image: np.ndarray, tile_mm: float) -> trimesh.Trimesh:
    """Upward-facing rectangle at height z with a texture repeated every ``tile_mm``."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = v[:, :2] / tile_mm
    mat = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(image), metallicFactor=0.0, roughnessFactor=0.85
    )
    mesh = trimesh.Trimesh(v, f, process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, material=mat)
    return mesh


def _coloured(mesh: trimesh.Trimesh, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, colours (V, 3) uint8) of a mesh painted one colour."""
    col = np.tile(np.clip(rgb, 0, 255).astype(np.uint8), (len(mesh.vertices), 1))
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces), col


def _quad(corners: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two triangles over 4 counter-clockwise corners (4, 3), normal by the right-hand rule."""
    col = np.tile(np.clip(rgb, 0, 255).astype(np.uint8), (4, 1))
    return np.asarray(corners, float), np.array([[0, 1, 2], [0, 2, 3]]), col


def _floor_and_walls(half: float, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Tiled floor (tiles over dark grout) and four inward-facing walls of a square room."""
    parts = []
    z = FLOOR_Z_MM
    grout = np.array([60.0, 58.0, 55.0])
    parts.append(_quad(np.array([[-half, -half, z - 1], [half, -half, z - 1], [half, half, z - 1], [-half, half, z - 1]]), grout))
    base = np.array(rng.choice([[180, 170, 150], [120, 120, 125], [150, 110, 80], [200, 195, 185]]), float)
    tile = rng.uniform(300, 600)
    gap = 4.0
    edges = np.arange(-half, half - 1e-6, tile)
    for x0 in edges:
        for y0 in edges:
            x1, y1 = min(x0 + tile, half) - gap, min(y0 + tile, half) - gap
            c = base * rng.uniform(0.88, 1.08)
            parts.append(_quad(np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]), c))
    wall = np.array(rng.choice([[220, 215, 200], [190, 200, 210], [200, 190, 170]]), float)
    for k in range(4):
        a = np.radians(90 * k)
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        # Walls reach below the floor, so floor and wall never meet at equal depth.
        v = np.array([[-half, half, z - 50], [half, half, z - 50], [half, half, z + 2800], [-half, half, z + 2800]]) @ R.T
        parts.append(_quad(v, wall * rng.uniform(0.85, 1.05)))  # normal faces into the room
    return parts


@dataclass
class Room:
    """Static meshes of one scene in world coordinates (mm): name -> trimesh.

    "table": the textured table top (z = 0). "room": table body, floor and walls as
    one vertex-coloured mesh. Within one mesh pyrender draws triangles in a fixed
    order, while the order of separate meshes varies between runs; keeping surfaces
    that may tie in depth (floor, walls) in one mesh keeps renders bit-identical.
    """

    meshes: dict[str, trimesh.Trimesh]


def make_room(style: str, rng: np.random.Generator, centre: np.ndarray) -> Room:
    """A table (textured top of the given style, plain edge), a tiled floor and walls.

    ``centre`` (2,) mm: where the table centre lies relative to the object cluster,
    so that table edges show up in some views.
    """
    tex = TABLE_TEXTURES[style](rng)
    w, d = rng.uniform(1100, 1600), rng.uniform(800, 1100)
    cx, cy = centre
    top = _textured_quad(cx - w / 2, cx + w / 2, cy - d / 2, cy + d / 2, 0.0, tex, tile_mm=rng.uniform(400, 600))
    edge_col = np.array(rng.choice([[120, 80, 50], [60, 60, 65], [200, 200, 195]]), float)
    body = trimesh.creation.box(extents=[w, d, TABLE_THICKNESS_MM - 0.5])
    body.apply_translation([cx, cy, -0.5 - (TABLE_THICKNESS_MM - 0.5) / 2])
    parts = [_coloured(body, edge_col)] + _floor_and_walls(4000.0, rng)
    verts, faces, cols, off = [], [], [], 0
    for v, f, c in parts:
        verts.append(v)
        faces.append(f + off)
        cols.append(c)
        off += len(v)
    room = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    room.visual = trimesh.visual.ColorVisuals(room, vertex_colors=np.column_stack([np.concatenate(cols), np.full(off, 255, np.uint8)]))
    return Room({"table": top, "room": room})
