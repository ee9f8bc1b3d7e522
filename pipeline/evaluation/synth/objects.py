"""The procedural object set: ten textured objects spanning what BOP datasets contain.

=====  ==============  ===========================================  =====================
obj    name            kind                                         declared symmetry
=====  ==============  ===========================================  =====================
1      cereal_box      texture-rich box, different print per face   none
2      soup_can        can with a printed wrap-around label         none (label)
3      u_channel       texture-less aluminium extrusion profile     2-fold (1 discrete)
4      bracket         texture-less L plate with four holes         none
5      hex_nut         texture-less hex nut                         12 elements (11 discrete)
6      cup             plain cup, colour bands around it            continuous about z
7      spool           thread spool, symmetric both ends            continuous z + flip
8      toy_truck       toy from coloured boxes and wheels           none
9      toy_tower       toy: block, tower, cone roof, ball           none
10     painted_block   box with one colour per face pair            3 discrete (D2)
=====  ==============  ===========================================  =====================

Symmetries are declared only where shape *and* colour are invariant (the can's label
breaks its rotational symmetry, so it declares none). Models are in mm with the origin
at the centre of the bounding box, as in BOP; discrete symmetries are (4, 4) transforms
without the identity, continuous ones {"axis", "offset"} (a point on the axis, mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import trimesh

from pipeline.formats.bop import ModelInfo
from pipeline.formats.bop.extent import point_cloud_diameter

from .meshkit import (
    Patch,
    box_patches,
    circle,
    circle_count,
    concatenate,
    disc_patch,
    extrude_patches,
    merged_mesh,
    rectangle,
    resample_loop,
    resample_profile,
    revolve_patch,
    sphere_patch,
    vertex_normals,
)
from .textures import Label

MODEL_SPACING_MM = 2.0
"""Edge length of the coloured models: fine enough for vertex colours to print labels."""


@dataclass
class Design:
    """What a builder returns: painted patches and the symmetries of the result."""

    patches: list[Patch]
    discrete: list[np.ndarray] = field(default_factory=list)
    continuous: list[dict[str, np.ndarray]] = field(default_factory=list)


@dataclass
class SynthObject:
    """One object of the set.

    model: coloured mesh (vertex colours, vertex normals), mm, origin at bbox centre.
    eval_mesh: same geometry, vertices about ``eval_spacing`` mm apart, merged, no colour.
    symmetries_discrete: (4, 4) float64 transforms (mm), identity excluded.
    symmetries_continuous: dicts with "axis" (3,) unit and "offset" (3,) mm.
    """

    obj_id: int
    name: str
    model: trimesh.Trimesh
    eval_mesh: trimesh.Trimesh
    eval_spacing: float
    symmetries_discrete: list[np.ndarray]
    symmetries_continuous: list[dict[str, np.ndarray]]

    @property
    def diameter(self) -> float:
        return point_cloud_diameter(np.asarray(self.model.vertices))

    def model_info(self) -> ModelInfo:
        v = np.asarray(self.model.vertices)
        lo, hi = v.min(axis=0), v.max(axis=0)
        return ModelInfo(
            diameter=self.diameter,
            min_xyz=lo,
            size_xyz=hi - lo,
            symmetries_discrete=[s.copy() for s in self.symmetries_discrete],
            symmetries_continuous=[{k: np.asarray(v).copy() for k, v in s.items()} for s in self.symmetries_continuous],
        )


# ---------------------------------------------------------------------------- helpers


def rot(axis: str, deg: float) -> np.ndarray:
    """(4, 4) rotation about a coordinate axis through the origin."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    T = np.eye(4)
    T[i, i], T[i, j], T[j, i], T[j, j] = c, -s, s, c
    # Snap the exact zeros and ones of multiples of 90 degrees.
    T[np.abs(T) < 1e-15] = 0.0
    return T


def translate(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _bands(bands: list[tuple[float, float, tuple[int, int, int]]], default: tuple[int, int, int]) -> Callable:
    """Colour function of z only: (z0, z1, rgb) bands over a default colour."""

    def fn(v: np.ndarray, uv: np.ndarray) -> np.ndarray:
        out = np.tile(np.asarray(default, np.float64), (len(v), 1))
        for z0, z1, c in bands:
            sel = (v[:, 2] >= z0 - 1e-9) & (v[:, 2] <= z1 + 1e-9)
            out[sel] = c
        return out.astype(np.uint8)

    return fn


def _radial(rings: list[tuple[float, float, tuple[int, int, int]]], default: tuple[int, int, int], axes=(0, 1)) -> Callable:
    """Colour function of the distance to an axis: (r0, r1, rgb) rings over a default."""

    def fn(v: np.ndarray, uv: np.ndarray) -> np.ndarray:
        r = np.hypot(v[:, axes[0]], v[:, axes[1]])
        out = np.tile(np.asarray(default, np.float64), (len(v), 1))
        for r0, r1, c in rings:
            out[(r >= r0) & (r <= r1)] = c
        return out.astype(np.uint8)

    return fn


def _label_fn(label: Label, feature_mm: float = 1.0) -> Callable:
    return lambda v, uv: label.sample(uv, feature_mm)


def _cylinder(r: float, z0: float, z1: float, h: float, n: int, caps: tuple[bool, bool] = (True, True)) -> dict[str, Patch]:
    """Closed cylinder about z: 'wall' (uv = (angle * r, z - z0)), 'top', 'bottom'."""
    out = {"wall": revolve_patch(resample_profile(np.array([[r, z0], [r, z1]]), h), n)}
    if caps[1]:
        out["top"] = disc_patch(r, n, z1, h, up=True)
    if caps[0]:
        out["bottom"] = disc_patch(r, n, z0, h, up=False)
    return out


# ---------------------------------------------------------------------------- the objects


def _cereal_box(h: float) -> Design:
    X, Y, Z = 100.0, 40.0, 140.0
    rng = np.random.default_rng(101)
    yellow, red, white, brown, blue, green = (248, 200, 40), (200, 30, 35), (250, 250, 245), (140, 85, 40), (30, 70, 170), (40, 150, 60)
    front = Label(X, Z, yellow)
    front.rect(0, 0, X, 32, red).text("OAT", 8, 16, 11, white).text("CRUNCH", 8, 28, 8, (250, 220, 80), bold=0.25)
    front.disc(50, 82, 30, white).disc(50, 86, 24, brown)
    for _ in range(14):
        front.disc(rng.uniform(34, 66), rng.uniform(72, 98), rng.uniform(2.5, 4.5), rng.choice([(200, 20, 60), (60, 20, 120), (250, 240, 220)]))
    front.polygon(np.array([[70, 34], [98, 40], [90, 58], [72, 54]]), (240, 120, 20)).text("NEW", 74, 50, 6, white)
    front.ring(14, 44, 9, 2.5, blue).disc(14, 44, 4, blue)
    front.stripes(0, 118, X, 22, 5.5, [green, white]).text_block(6, 121, 60, 14, 4, (20, 20, 20), rng)
    back = Label(X, Z, (242, 236, 222))
    back.rect(6, 8, 52, 70, (30, 30, 30)).rect(7, 9, 50, 68, white)
    back.text_block(10, 12, 44, 62, 4.5, (30, 30, 30), rng)
    for i in range(4):
        for j in range(4):
            back.rect(64 + 8.5 * i, 10 + 8.5 * j, 7.5, 7.5, [red, blue, green, yellow][(i + 2 * j) % 4])
    back.text("PUZZLE", 62, 54, 6, red).text_block(6, 86, 88, 30, 5, (90, 60, 30), rng).barcode(62, 120, 32, 14, rng)
    right = Label(Y, Z, blue).stripes(0, 0, Y, 16, 4, [white, blue]).text_block(4, 24, 32, 100, 5, white, rng)
    left = Label(Y, Z, red).disc(20, 30, 12, yellow).text("OAT", 7, 35, 7, red).text_block(4, 52, 32, 80, 5, white, rng)
    top = Label(X, Y, yellow).text("OAT CRUNCH", 6, 16, 6, red).text_block(6, 22, 88, 14, 4, (40, 40, 40), rng)
    bottom = Label(X, Y, (200, 170, 120)).text_block(6, 6, 60, 28, 4, (60, 40, 20), rng)
    labels = {"front": front, "back": back, "right": right, "left": left, "top": top, "bottom": bottom}
    faces = box_patches((X, Y, Z), h)
    return Design([faces[k].painted(_label_fn(labels[k])) for k in faces])


def _soup_can(h: float) -> Design:
    R, H = 33.0, 98.0
    circ = 2 * np.pi * R
    rng = np.random.default_rng(102)
    red, white, gold = (190, 25, 30), (250, 248, 240), (205, 165, 60)
    lab = Label(circ, H, white)
    lab.rect(0, 0, circ, 34, red).rect(0, 34, circ, 3, gold)
    lab.text("TOMATO", 12, 26, 13, white).text("SOUP", 120, 24, 9, white)
    lab.disc(150, 62, 15, gold).ring(150, 62, 12, 1.2, red).text("1897", 141, 65, 5, red)
    lab.text("condensed", 12, 48, 6, red).text_block(12, 56, 100, 30, 4.5, (70, 40, 30), rng)
    lab.barcode(174, 66, 24, 18, rng).stripes(0, 90, circ, 8, 2, [gold, white])
    n = circle_count(R, h)
    cyl = _cylinder(R, -H / 2, H / 2, h, n)
    lid = _radial([(0, 6, (150, 150, 155)), (24, 27, (150, 150, 155))], (200, 200, 205))
    # uv of the wall is (angle * R, z + H/2): exactly label mm.
    wall = cyl["wall"]
    wall.uv[:, 1] = wall.vertices[:, 2] + H / 2
    return Design([wall.painted(_label_fn(lab)), cyl["top"].painted(lid), cyl["bottom"].painted(lid)])


def _u_channel(h: float) -> Design:
    profile = np.array([[-25, -15], [25, -15], [25, 15], [21, 15], [21, -11], [-21, -11], [-21, 15], [-25, 15]], float)
    parts = extrude_patches(profile, [], -55.0, 55.0, h)
    alu = (172, 175, 180)
    patches = [p.painted(alu) for ps in parts.values() for p in ps]
    # Turning the U over about its opening axis (y) maps it onto itself.
    return Design(patches, discrete=[rot("y", 180)])


def _bracket(h: float) -> Design:
    outline = np.array([[0, 0], [100, 0], [100, 30], [30, 30], [30, 72], [0, 72]], float)
    holes = [circle(5.0, circle_count(5.0, h), (15, 15)), circle(4.0, circle_count(4.0, h), (60, 15)),
             circle(4.0, circle_count(4.0, h), (85, 15)), circle(6.0, circle_count(6.0, h), (15, 57))]
    parts = extrude_patches(outline, holes, -6.0, 6.0, h)
    steel = (88, 98, 112)
    return Design([p.painted(steel) for ps in parts.values() for p in ps])


def _hex_nut(h: float) -> Design:
    a = 26.0  # circumradius: across flats 45 mm
    hole = circle(12.5, circle_count(12.5, h, multiple=6))
    parts = extrude_patches(circle(a, 6), [hole], -11.0, 11.0, h)
    zinc = (196, 190, 168)
    patches = [p.painted(zinc) for ps in parts.values() for p in ps]
    turns = [rot("z", 60 * k) for k in range(6)]
    discrete = turns[1:] + [rot("x", 180) @ T for T in turns]
    return Design(patches, discrete=discrete)


def _cup(h: float) -> Design:
    z0, z1, zin = -45.0, 45.0, -39.0
    r_bot, r_top, wall = 28.0, 40.0, 3.0
    r_in_top = r_top - wall
    r_in_bot = r_in_top - (r_top - r_bot) * (z1 - zin) / (z1 - z0)
    n_out, n_in = circle_count(r_top, h), circle_count(r_in_top, h)
    outer = revolve_patch(resample_profile(np.array([[r_bot, z0], [r_top, z1]]), h), n_out)
    inner = revolve_patch(resample_profile(np.array([[r_in_top, z1], [r_in_bot, zin]]), h), n_in)
    rim = disc_patch(r_top, n_out, z1, h, up=True, hole=(r_in_top, n_in))
    base_out = disc_patch(r_bot, n_out, z0, h, up=False)
    base_in = disc_patch(r_in_bot, n_in, zin, h, up=True)
    white, red, blue, green = (244, 242, 236), (200, 40, 40), (40, 70, 180), (60, 150, 80)
    outer_col = _bands([(z0, z0 + 8, green), (12, 15, blue), (22, 34, red)], white)
    patches = [outer.painted(outer_col), inner.painted((236, 230, 218)), rim.painted(red),
               base_out.painted((210, 208, 200)), base_in.painted((236, 230, 218))]
    return Design(patches, continuous=[{"axis": np.array([0.0, 0.0, 1.0]), "offset": np.zeros(3)}])


def _spool(h: float) -> Design:
    R, r_core, r_hole, zf, zc = 34.0, 15.0, 6.0, 30.0, 24.0
    n_r, n_c, n_h = circle_count(R, h), circle_count(r_core, h), circle_count(r_hole, h)
    red, wood, thread, dark = (200, 45, 45), (214, 182, 132), (40, 75, 190), (150, 115, 75)
    patches = [
        disc_patch(R, n_r, zf, h, up=True, hole=(r_hole, n_h)).painted(red),
        disc_patch(R, n_r, -zf, h, up=False, hole=(r_hole, n_h)).painted(red),
        disc_patch(R, n_r, zc, h, up=False, hole=(r_core, n_c)).painted(red),
        disc_patch(R, n_r, -zc, h, up=True, hole=(r_core, n_c)).painted(red),
        revolve_patch(resample_profile(np.array([[R, zc], [R, zf]]), h), n_r).painted(red),
        revolve_patch(resample_profile(np.array([[R, -zf], [R, -zc]]), h), n_r).painted(red),
        revolve_patch(resample_profile(np.array([[r_core, -zc], [r_core, zc]]), h), n_c).painted(_bands([(-16, 16, thread)], wood)),
        # Walked downwards so the normal points into the hole.
        revolve_patch(resample_profile(np.array([[r_hole, zf], [r_hole, -zf]]), h), n_h).painted(dark),
    ]
    return Design(
        patches,
        discrete=[rot("x", 180)],
        continuous=[{"axis": np.array([0.0, 0.0, 1.0]), "offset": np.zeros(3)}],
    )


def _part_box(extents, h, center, colors: dict[str, Callable | tuple], skip=("bottom",), top_holes=()) -> list[Patch]:
    faces = box_patches(extents, h, top_holes=top_holes, skip=skip)
    T = translate(*center)
    return [faces[k].painted(colors.get(k, colors["default"])).transformed(T) for k in faces]


def _toy_truck(h: float) -> Design:
    rng = np.random.default_rng(108)
    red, blue, yellow, glass, black, grey = (215, 40, 40), (40, 90, 200), (240, 200, 30), (170, 215, 240), (30, 30, 32), (170, 170, 170)
    CX, CY, CZ = 110.0, 50.0, 20.0
    cab = (36.0, 44.0, 30.0, 34.0)  # size x, y, z and centre x
    cargo = (62.0, 44.0, 22.0, -20.0)
    holes = []
    for sx, sy, _, cx in (cab, cargo):
        u0 = cx - sx / 2 + CX / 2
        v0 = (CY - sy) / 2
        holes.append(resample_loop(rectangle(u0, v0, u0 + sx, v0 + sy), h)[::-1])
    side = Label(CX, CZ, red).stripes(0, 13, CX, 3, 3, [(250, 250, 250)])
    patches = _part_box((CX, CY, CZ), h, (0, 0, 0), {"default": red, "right": _label_fn(side), "left": _label_fn(side)},
                        skip=(), top_holes=holes)
    sx, sy, sz, cx = cab
    win_side = Label(sy, sz, blue).rect(6, 4, sy - 12, 13, glass)
    win_front = Label(sx, sz, blue).rect(4, 4, sx - 8, 12, glass).disc(8, 25, 2.5, yellow).disc(sx - 8, 25, 2.5, yellow)
    patches += _part_box((sx, sy, sz), h, (cx, 0, CZ / 2 + sz / 2),
                         {"default": blue, "right": _label_fn(win_front), "left": _label_fn(Label(sy, sz, blue).rect(4, 4, sy - 8, 12, glass)),
                          "front": _label_fn(win_side), "back": _label_fn(win_side)})
    sx, sy, sz, cx = cargo
    crate = Label(sx, sz, yellow).rect(0, 9, sx, 4, black).text("TOY", 4, 8, 6, blue).text_block(30, 14, 28, 6, 3, black, rng)
    patches += _part_box((sx, sy, sz), h, (cx, 0, CZ / 2 + sz / 2),
                         {"default": yellow, "front": _label_fn(crate), "back": _label_fn(crate), "top": _label_fn(Label(sx, sy, yellow).stripes(0, 0, sx, sy, 5.5, [yellow, (225, 170, 20)], vertical=True))})
    # Wheels: cylinders about y, 1 mm clear of the chassis sides.
    rw, ww = 14.0, 10.0
    n = circle_count(rw, h)
    hub = _radial([(0, 6, grey)], black)
    for x in (-36.0, 36.0):
        for s in (-1.0, 1.0):
            cyl = _cylinder(rw, -ww / 2, ww / 2, h, n)
            T = translate(x, s * (CY / 2 + 1 + ww / 2), -CZ / 2 + 2) @ rot("x", 90)
            patches += [cyl["wall"].painted(black).transformed(T), cyl["top"].painted(hub).transformed(T),
                        cyl["bottom"].painted(hub).transformed(T)]
    return Design(patches)


def _toy_tower(h: float) -> Design:
    green, red, blue, yellow, white, dark = (60, 160, 80), (205, 50, 45), (45, 80, 190), (245, 205, 40), (250, 250, 250), (50, 35, 30)
    B, BZ = 70.0, 24.0
    rt, th, roof = 18.0, 50.0, 30.0
    tx, ty = -12.0, 10.0
    n = circle_count(rt, h)
    hole = circle(rt, n, (tx + B / 2, ty + B / 2))[::-1]
    dots = Label(B, BZ, green)
    for i in range(5):
        dots.disc(7 + 14 * i, BZ / 2, 4, [white, yellow][i % 2])
    base = _part_box((B, B, BZ), h, (0, 0, 0), {"default": green, "front": _label_fn(dots), "right": _label_fn(Label(B, BZ, green).stripes(0, 0, B, BZ, 6, [green, yellow])),
                     "top": _label_fn(Label(B, B, green).text("A", 48, 20, 12, white))}, skip=(), top_holes=[hole])
    circ = 2 * np.pi * rt
    tower_lab = Label(circ, th, red).rect(20, 10, 10, 14, dark).rect(60, 24, 14, 26, dark).rect(0, 0, circ, 3, white)
    wall = revolve_patch(resample_profile(np.array([[rt, 0.0], [rt, th]]), h), n)
    wall.uv[:, 1] = wall.vertices[:, 2]
    cone = revolve_patch(resample_profile(np.array([[rt, th], [0.0, th + roof]]), h), n)
    T = translate(tx, ty, BZ / 2)
    tower = [wall.painted(_label_fn(tower_lab)).transformed(T), cone.painted(blue).transformed(T)]
    ball = sphere_patch(13.0, h)
    ball.vertices[:, 2] -= ball.vertices[:, 2].min()
    ball = ball.painted(lambda v, uv: np.where((np.abs(v[:, 2] - 13.0) < 3.0)[:, None], np.array([white]), np.array([yellow])))
    ball = ball.transformed(translate(20.0, -20.0, BZ / 2))
    return Design(base + tower + [ball])


def _painted_block(h: float) -> Design:
    red, yellow, blue = (205, 55, 50), (232, 192, 45), (50, 95, 195)
    colors = {"right": red, "left": red, "front": yellow, "back": yellow, "top": blue, "bottom": blue}
    faces = box_patches((80.0, 50.0, 30.0), h)
    patches = [faces[k].painted(colors[k]) for k in faces]
    return Design(patches, discrete=[rot("x", 180), rot("y", 180), rot("z", 180)])


BUILDERS: dict[int, tuple[str, Callable[[float], Design]]] = {
    1: ("cereal_box", _cereal_box),
    2: ("soup_can", _soup_can),
    3: ("u_channel", _u_channel),
    4: ("bracket", _bracket),
    5: ("hex_nut", _hex_nut),
    6: ("cup", _cup),
    7: ("spool", _spool),
    8: ("toy_truck", _toy_truck),
    9: ("toy_tower", _toy_tower),
    10: ("painted_block", _painted_block),
}
OBJ_IDS: tuple[int, ...] = tuple(sorted(BUILDERS))


# ---------------------------------------------------------------------------- assembly


def _recentre_symmetries(design: Design, c: np.ndarray) -> tuple[list[np.ndarray], list[dict]]:
    """Express symmetries in the frame whose origin is the old point ``c``.

    p' = p - c, so p -> R p + t becomes p' -> R p' + (t + R c - c).
    """
    disc = []
    for T in design.discrete:
        T2 = np.array(T, float)
        T2[:3, 3] = T[:3, 3] + T[:3, :3] @ c - c
        T2[np.abs(T2) < 1e-12] = 0.0
        disc.append(T2)
    cont = [{"axis": np.asarray(s["axis"], float), "offset": np.asarray(s["offset"], float) - c} for s in design.continuous]
    for s in cont:
        s["offset"][np.abs(s["offset"]) < 1e-9] = 0.0
    return disc, cont


def build_object(obj_id: int, eval_spacing: float | None = None) -> SynthObject:
    """Build object ``obj_id``: coloured model, eval mesh and symmetries, origin at bbox centre.

    eval_spacing: vertex spacing of models_eval in mm; default diameter / 40 clipped
    to [2.5, 5] mm.
    """
    if obj_id not in BUILDERS:
        raise KeyError(f"unknown synthetic object id {obj_id}; known: {list(OBJ_IDS)}")
    name, builder = BUILDERS[obj_id]
    design = builder(MODEL_SPACING_MM)
    v, f, col = concatenate(design.patches)
    assert col is not None, f"{name}: a patch was left unpainted"
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    v = v - c
    disc, cont = _recentre_symmetries(design, c)
    model = trimesh.Trimesh(vertices=v, faces=f, vertex_normals=vertex_normals(v, f), process=False)
    model.visual = trimesh.visual.ColorVisuals(model, vertex_colors=np.column_stack([col, np.full(len(col), 255, np.uint8)]))
    if eval_spacing is None:
        eval_spacing = float(np.clip(point_cloud_diameter(v) / 40.0, 2.5, 5.0))
    ev, ef, _ = concatenate(builder(eval_spacing).patches)
    eval_mesh = merged_mesh(ev - c, ef)
    return SynthObject(obj_id, name, model, eval_mesh, eval_spacing, disc, cont)


def physics_mesh(obj: SynthObject) -> trimesh.Trimesh:
    """Watertight merged copy of the model, for mass properties and stable poses."""
    return merged_mesh(np.asarray(obj.model.vertices), np.asarray(obj.model.faces))
