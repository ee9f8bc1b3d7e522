"""Stage model_features: fused-feature ingredients of one object -> ``features.zarr``.

Arrays: points (N, 3) float32 mm and normals (N, 3) in the model frame; geometric
(N, G) float32 (multi-scale, concatenated); visual (N, C) float32 (template features
lifted onto the points and averaged over the views that see them); view_count (N,)
int32 (how many templates saw each point; 0 means the feature was copied from the
nearest seen point). Algorithm: :func:`pipeline.method.model_side.model_features`.
"""

from __future__ import annotations

from pipeline.workflow.plan import DatasetPlan, build_encoders, encoder_runtime


def run(plan: DatasetPlan, item: str, progress: bool = True) -> None:
    from pipeline.method.model_side import model_features

    io = plan.io("model_features", item)
    obj_id, p = io.item_id(), io.params
    bop = io.bop()
    diameter = plan.model_info(bop, obj_id).diameter
    mesh = bop.load_model(obj_id)  # first: a model the reader refuses is named before anything else is read
    tpl = io.arrays("render_templates", "templates")
    geo_enc, vis_enc = build_encoders(plan.run)
    f = model_features(mesh, tpl, geo_enc, vis_enc, diameter, n_points=p.n_points,
                       seed=io.seed(item, p.seed), batch_size=p.batch_size)
    with io.publish() as w:
        # where the encoders ran and in what precision: recorded, not keyed
        w.manifest["runtime"] = {"geometric": encoder_runtime(geo_enc), "visual": encoder_runtime(vis_enc)}
        w.write("features", f, chunks={name: a.shape for name, a in f.items()},  # each array one chunk
                attrs={"obj_id": obj_id, "diameter": diameter, "geometric_encoder": geo_enc.signature(),
                       "visual_encoder": vis_enc.signature()})
        w.summary.update({
            "obj_id": obj_id, "n_points": int(len(f["points"])), "geometric_dim": int(f["geometric"].shape[1]),
            "visual_dim": int(f["visual"].shape[1]), "points_unseen": int((f["view_count"] == 0).sum()),
            "mean_views_per_point": float(f["view_count"].mean()),
        })
