"""Template viewpoints and template rendering (stage render_templates).

Templates are object-centred square renders: the camera sits on a sphere around the
model's bounding-box centre (the origin of BOP models and of the synthetic ones, but
not of every model a user brings) and looks at it, with a focal length chosen so that
the object's diameter spans ``fill`` of the image side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.method.geometry.transforms import look_at_rotation
from pipeline.method.render.renderer import Light, Lighting, Renderer

IMAGE_MODES = ("rgb", "gray")
# ITU-R BT.601 luma, the weights OpenCV's RGB2GRAY uses: a grey camera sees roughly this.
_LUMA = np.array([0.299, 0.587, 0.114])


def match_image_mode(rgb: np.ndarray, mode: str) -> np.ndarray:
    """Renders (..., 3) uint8 RGB made to look like the dataset's images: unchanged for
    ``"rgb"``; for ``"gray"`` (ITODD) the luma replicated to 3 channels, as the reader
    replicates a grey image, so templates and scene crops meet the visual encoder alike."""
    if mode not in IMAGE_MODES:
        raise ValueError(f"image mode must be one of {IMAGE_MODES}, got {mode!r}")
    rgb = np.asarray(rgb)
    if mode == "rgb":
        return rgb
    if rgb.shape[-1:] != (3,) or rgb.dtype != np.uint8:
        raise ValueError(f"match_image_mode: expected (..., 3) uint8, got {rgb.shape} {rgb.dtype}")
    luma = np.clip(np.rint(rgb.astype(np.float32) @ _LUMA.astype(np.float32)), 0, 255).astype(np.uint8)
    return np.repeat(luma[..., None], 3, axis=-1)


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) float64 unit vectors spread evenly over the sphere (golden-angle spiral)."""
    i = np.arange(n, dtype=float) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@dataclass(frozen=True)
class TemplateViews:
    """Camera set of the templates: R_m2c (R, 3, 3), t_m2c (R, 3) mm, K (3, 3), size px."""

    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    size: int


def template_views(n_views: int, diameter: float, size: int, fill: float = 0.85, distance_factor: float = 3.0) -> TemplateViews:
    """Viewpoints on a Fibonacci sphere at ``distance_factor * diameter`` mm."""
    dist = distance_factor * diameter
    focal = fill * size * dist / diameter
    K = np.array([[focal, 0.0, (size - 1) / 2.0], [0.0, focal, (size - 1) / 2.0], [0.0, 0.0, 1.0]])
    dirs = fibonacci_sphere(n_views)
    Rs = np.stack([look_at_rotation(d) for d in dirs])
    ts = np.tile(np.array([0.0, 0.0, dist]), (n_views, 1))
    return TemplateViews(R=Rs, t=ts, K=K, size=size)


TEMPLATE_LIGHTING = Lighting(
    ambient=(0.45, 0.45, 0.45),
    lights=[Light(kind="directional", direction=(0.0, 0.0, 1.0), intensity=2.5)],
)


def render_templates(renderer: Renderer, key, views: TemplateViews) -> dict[str, np.ndarray]:
    """Render every view of mesh ``key``.

    Returns rgb (R, S, S, 3) uint8, depth (R, S, S) float32 mm, mask (R, S, S) bool,
    K (R, 3, 3), R (R, 3, 3), t (R, 3) float64.
    """
    n = len(views.R)
    rgb = np.zeros((n, views.size, views.size, 3), np.uint8)
    depth = np.zeros((n, views.size, views.size), np.float32)
    for i in range(n):
        c, d = renderer.render([(key, views.R[i], views.t[i])], views.K, rgb=True, lighting=TEMPLATE_LIGHTING)
        rgb[i], depth[i] = c, d
    return {
        "rgb": rgb,
        "depth": depth,
        "mask": depth > 0,
        "K": np.tile(views.K, (n, 1, 1)),
        "R": views.R.astype(np.float64),
        "t": views.t.astype(np.float64),
    }


def bbox_centre(mesh) -> np.ndarray:
    """(3,) float64 mm: the centre of the axis-aligned bounding box of a mesh's vertices."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    return 0.5 * (v.min(axis=0) + v.max(axis=0))


def render_object_templates(mesh, diameter: float, params, image_mode: str = "rgb") -> dict[str, np.ndarray]:
    """The templates of one object (stage render_templates): :func:`render_templates` of
    ``params.n_views`` :func:`template_views` looking at the mesh's :func:`bbox_centre`
    (``t_m2c = t - R c`` puts the centre ``c`` on the optical axis at the same distance),
    coloured like the dataset's images (:func:`match_image_mode`).

    mesh: trimesh in mm; diameter mm; params: the run's
    :class:`pipeline.common.config.RenderTemplatesParams`. Returns the arrays of
    :func:`render_templates`.
    """
    views = template_views(params.n_views, diameter, params.image_size, fill=params.fill,
                           distance_factor=params.distance_factor)
    c = bbox_centre(mesh)
    views = TemplateViews(R=views.R, t=views.t - views.R @ c, K=views.K, size=views.size)
    zfar = 10 * params.distance_factor * diameter + float(np.linalg.norm(c))
    with Renderer(params.image_size, params.image_size, znear=1.0, zfar=zfar) as r:
        r.add_mesh("object", mesh)
        arrays = render_templates(r, "object", views)
    arrays["rgb"] = match_image_mode(arrays["rgb"], image_mode)
    return arrays
