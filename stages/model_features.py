"""Stage model_features: fused-feature ingredients of one object -> ``features.zarr``.

Arrays: points (N, 3) float32 mm and normals (N, 3) in the model frame; geometric
(N, G) float32 (multi-scale, concatenated); visual (N, C) float32 (template features
lifted onto the points and averaged over the views that see them); view_count (N,)
int32 (how many templates saw each point; 0 means the feature was copied from the
nearest seen point).
"""

from __future__ import annotations

import numpy as np

from pipeline.plan import DatasetPlan, build_encoders, item_id
from pipeline.store import item_seed, load_arrays, publish, save_arrays

CODE_VERSION = 1


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.encoders.lifting import lift_model_visual_features
    from pipeline.geometry.sampling import sample_surface

    obj_id = item_id(item, "obj", "model_features")
    sp = plan["model_features"]
    p = plan.run.stages.model_features
    bop = plan.bop()
    diameter = plan.model_info(bop, obj_id).diameter
    mesh = bop.load_model(obj_id)
    tpl = load_arrays(plan["render_templates"].item_dir(item) / "templates.zarr")
    geo_enc, vis_enc = build_encoders(plan.run)

    points, normals = sample_surface(mesh, p.n_points, seed=item_seed(sp.key, item, p.seed))
    geometric = geo_enc.encode(points, normals, diameter)
    views = [(tpl["rgb"][i], tpl["depth"][i], tpl["K"][i], tpl["R"][i], tpl["t"][i]) for i in range(len(tpl["rgb"]))]
    visual, view_count = lift_model_visual_features(points, views, vis_enc, batch_size=p.batch_size, diameter=diameter)

    with publish(sp.item_dir(item), **sp.publish_kwargs(item)) as w:
        save_arrays(
            w.dir / "features.zarr",
            {
                "points": points.astype(np.float32),
                "normals": normals.astype(np.float32),
                "geometric": geometric.astype(np.float32),
                "visual": visual.astype(np.float32),
                "view_count": view_count.astype(np.int32),
            },
            chunks={"points": (p.n_points, 3), "normals": (p.n_points, 3),
                    "geometric": (p.n_points, geometric.shape[1]), "visual": (p.n_points, visual.shape[1]),
                    "view_count": (p.n_points,)},
            attrs={"key": sp.key, "obj_id": obj_id, "diameter": diameter,
                   "geometric_encoder": geo_enc.signature(), "visual_encoder": vis_enc.signature()},
        )
        w.summary.update({
            "obj_id": obj_id, "n_points": int(len(points)), "geometric_dim": int(geometric.shape[1]),
            "visual_dim": int(visual.shape[1]), "points_unseen": int((view_count == 0).sum()),
            "mean_views_per_point": float(view_count.mean()),
        })
