"""Stage render_templates: R object-centred views of one object -> ``templates.zarr``.

Arrays (chunked one view per chunk): rgb (R, S, S, 3) uint8 (grey replicated to 3
channels for grey datasets), depth (R, S, S) float32 mm,
mask (R, S, S) bool, K (R, 3, 3), R (R, 3, 3), t (R, 3) mm (model-to-camera).
"""

from __future__ import annotations

from pipeline.plan import DatasetPlan, item_id
from pipeline.store import publish, save_arrays

CODE_VERSION = 1


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.render import Renderer
    from pipeline.render.templates import match_image_mode, render_templates, template_views

    obj_id = item_id(item, "obj", "render_templates")
    sp = plan["render_templates"]
    p = plan.run.stages.render_templates
    bop = plan.bop()
    info = plan.model_info(bop, obj_id)
    mesh = bop.load_model(obj_id)
    views = template_views(p.n_views, info.diameter, p.image_size, fill=p.fill, distance_factor=p.distance_factor)
    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        with Renderer(p.image_size, p.image_size, znear=1.0, zfar=10 * p.distance_factor * info.diameter) as r:
            r.add_mesh(obj_id, mesh)
            arrays = render_templates(r, obj_id, views)
        # grey datasets (ITODD) get grey templates, so that both sides of the matching look alike
        arrays["rgb"] = match_image_mode(arrays["rgb"], plan.dataset.image_mode)
        save_arrays(w.dir / "templates.zarr", arrays, attrs={"key": sp.key, "obj_id": obj_id, "diameter": info.diameter})
        w.summary.update({"obj_id": obj_id, "n_views": p.n_views, "image_size": p.image_size,
                          "diameter_mm": info.diameter, "image_mode": plan.dataset.image_mode,
                          "mean_mask_fraction": float(arrays["mask"].mean())})
