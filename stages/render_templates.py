"""Stage render_templates: R object-centred views of one object -> ``templates.zarr``.

Arrays (chunked one view per chunk): rgb (R, S, S, 3) uint8 (grey replicated to 3
channels for grey datasets), depth (R, S, S) float32 mm, mask (R, S, S) bool, K (R, 3, 3),
R (R, 3, 3), t (R, 3) mm (model-to-camera). Algorithm:
:func:`pipeline.method.render.templates.render_object_templates`.
"""

from __future__ import annotations

from pipeline.workflow.plan import DatasetPlan


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.method.render.templates import render_object_templates

    io = plan.io("render_templates", item)
    obj_id, p = io.item_id(), io.params
    bop = io.bop()
    info = plan.model_info(bop, obj_id)
    arrays = render_object_templates(bop.load_model(obj_id), info.diameter, p, image_mode=plan.dataset.image_mode)
    with io.publish() as w:
        w.write("templates", arrays, attrs={"obj_id": obj_id, "diameter": info.diameter})
        w.summary.update({"obj_id": obj_id, "n_views": p.n_views, "image_size": p.image_size,
                          "diameter_mm": info.diameter, "image_mode": plan.dataset.image_mode,
                          "mean_mask_fraction": float(arrays["mask"].mean())})
