"""The feature figure: what the model's and a scene candidate's features look like, and
which of their matches RANSAC kept (like the supplementary feature figure of FreeZe).

Each kind of feature (geometric, visual, and the fused features exactly as the register
stage builds them: visual part reduced by PCA to ``register.pca_dim``, each part
L2-normalised, concatenated) is reduced to 3 components by one PCA fitted on the model's
features and applied to both the model and the scene, and the components are mapped to
RGB with the same robust range (1st-99th percentile of the model's projections, per
component). A model point and a scene point with the same colour therefore have similar
features, and identical features get identical colours.

Points are drawn in the camera frame of the candidate's image, orthographically (x to
the right, y down, as in the image), the model placed by the pose the register stage
found, nearest points drawn last. The last panel draws the two clouds side by side with
lines between scene points and their nearest model point in fused-feature space (the
matches RANSAC samples from) that are inliers under the registered pose.

Points or features with NaN or inf are not drawn (features: grey, outside the PCA), and
a panel whose cloud has no finite point says "no data"; an empty cloud is not an error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

PARTS = ("geometric", "visual", "fused")


@dataclass
class FeatureCase:
    """One object and one of its scene candidates.

    model_points (N, 3) float mm, model frame; scene_points (M, 3) float mm, camera frame;
    parts: name -> (model features (N, D), scene features (M, D)), D may be 0 (a part
    switched off in this run); R (3, 3), t (3,) mm: the registered model-to-camera pose;
    inlier_threshold mm (register's inlier_frac x diameter); n_inliers: as the register
    stage stored it; model_normals (N, 3) model frame, optional: when given, only the model
    points facing the camera are drawn (the others would show through the surface);
    notes: what was skipped and why.
    """

    dataset: str
    obj_id: int
    scene_id: int
    im_id: int
    cand_id: int
    model_points: np.ndarray
    scene_points: np.ndarray
    parts: dict[str, tuple[np.ndarray, np.ndarray]]
    R: np.ndarray
    t: np.ndarray
    diameter: float
    inlier_threshold: float
    n_inliers: int | None = None
    model_normals: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)


# ------------------------------------------------------------------------- colours


def _project(X: np.ndarray, mean: np.ndarray, comps: np.ndarray) -> np.ndarray:
    """(X - mean) @ comps.T in float64, row by row the same arithmetic wherever a row sits
    (einsum's own loop, not a blocked BLAS product), so equal rows project equally."""
    return np.einsum("nd,kd->nk", np.asarray(X, np.float64) - mean, comps)


def pca_colours(model: np.ndarray, scene: np.ndarray, q: tuple[float, float] = (1.0, 99.0)
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Colours of (N, D) model and (M, D) scene features by a shared PCA.

    Returns model RGB (N, 3) and scene RGB (M, 3), float in [0, 1], and the fraction of
    the model features' total variance the (up to) 3 components explain. The PCA is
    fitted on the model only; each component is mapped to [0, 1] between its ``q``
    percentiles over the model (clipped outside); a component without spread (or missing,
    when D < 3) is a constant 0.5. Rows holding NaN or inf are left out of the fit and
    coloured 0.5 (grey); with no finite model row every colour is 0.5 and the explained
    fraction 0.
    """
    from pipeline.method.registration.fusion import fit_pca

    model = np.asarray(model, np.float64)
    if model.ndim != 2 or model.shape[1] == 0:
        raise ValueError(f"pca_colours: expected (N, D) model features with D > 0, got shape {model.shape}")
    scene = np.asarray(scene, np.float64).reshape(-1, model.shape[1])
    ok_m, ok_s = np.isfinite(model).all(axis=1), np.isfinite(scene).all(axis=1)
    cm, cs = np.full((len(model), 3), 0.5), np.full((len(scene), 3), 0.5)
    if not ok_m.any():
        return cm, cs, 0.0
    fit = model[ok_m]
    basis = fit_pca(fit, n_components=3, min_variance=0.0)
    mean, comps = basis.mean.astype(np.float64), basis.components.astype(np.float64)
    # Row by row projections (see _project), so leaving rows out changes no other row.
    pm, ps = _project(fit, mean, comps), _project(scene[ok_s], mean, comps)
    lo, hi = np.percentile(pm, q, axis=0)
    span = hi - lo
    flat = span <= 1e-9 * max(1.0, float(np.abs(pm).max(initial=0.0)))
    span = np.where(flat, 1.0, span)

    def rgb(p: np.ndarray) -> np.ndarray:
        out = np.full((len(p), 3), 0.5)
        out[:, : p.shape[1]] = np.where(flat, 0.5, np.clip((p - lo) / span, 0.0, 1.0))
        return out

    cm[ok_m], cs[ok_s] = rgb(pm), rgb(ps)
    total = float(fit.var(axis=0, ddof=1).sum()) if len(fit) > 1 else 0.0
    explained = float(basis.explained_variance.sum()) / total if total > 0 else 0.0
    return cm, cs, min(1.0, explained)


def fused_features(model_geo: np.ndarray, model_vis: np.ndarray, scene_geo: np.ndarray, scene_vis: np.ndarray,
                   pca_dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Model (N, G+V) and scene (M, G+V) fused features, as the register stage computes
    them (PCA of the model's visual features to ``pca_dim``, applied to both; fuse())."""
    from pipeline.method.registration.fusion import apply_pca, fit_pca, fuse

    basis = fit_pca(model_vis, n_components=pca_dim) if model_vis.shape[1] else None
    return (fuse(model_geo, apply_pca(basis, model_vis) if basis is not None else None),
            fuse(scene_geo, apply_pca(basis, scene_vis) if basis is not None else None))


def inlier_matches(case: FeatureCase) -> tuple[np.ndarray, np.ndarray]:
    """For every scene point, its nearest model point in fused-feature space (M,) and
    whether that match is an inlier under the registered pose (M,) bool: the model point
    moved by (R, t) lies within ``inlier_threshold`` of the scene point. Their count is
    what the register stage stores as ``n_inliers``. Without model points every match
    is model point 0 and none is an inlier."""
    from pipeline.method.registration.ransac import feature_neighbours

    mf, sf = case.parts["fused"]
    if len(mf) == 0 or len(sf) == 0:
        return np.zeros(len(sf), np.int64), np.zeros(len(sf), bool)
    nn = feature_neighbours(sf, mf, k=1)[:, 0]
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite points: NaN distance, not an inlier
        moved = case.model_points[nn] @ np.asarray(case.R, float).T + np.asarray(case.t, float)
        return nn, np.linalg.norm(moved - case.scene_points, axis=1) < case.inlier_threshold


# ------------------------------------------------------------------------- loading


def feature_case(plan, obj_id: int, scene_id: int | None = None, cand_id: int | None = None) -> FeatureCase:
    """The case of ``obj_id`` from a dataset plan's model_features, scene_features and
    register artifacts: candidate ``cand_id`` (searched in ``scene_id``, or in every scene),
    or else the object's first registered candidate (lowest scene id, then candidate id)."""
    from pipeline.workflow.plan import obj_item
    from pipeline.common.store import load_arrays, load_attrs, read_table

    mf_path = plan["model_features"].path(obj_item(obj_id), "features")
    if not mf_path.exists():
        known = ", ".join(map(str, plan.obj_ids))
        raise FileNotFoundError(f"{mf_path} missing: object {obj_id} has no model features in this run "
                                f"(objects of {plan.name}: {known}; run the pipeline first)")
    if scene_id is not None and scene_id not in plan.scene_ids:
        raise LookupError(f"{plan.name}: no scene {scene_id} (scenes: {', '.join(map(str, plan.scene_ids))})")
    scenes = [scene_id] if scene_id is not None else list(plan.scene_ids)
    chosen = None
    for item in [i for sc in scenes for i in plan.items_of_scene(sc)]:
        path = plan["register"].path(item, "coarse_hypotheses")
        if not path.exists():
            raise FileNotFoundError(f"{path} missing: run the register stage first (snakemake --cores 2 bop_all)")
        table = read_table(path)
        if cand_id is not None:
            rows = table[table.cand_id == cand_id]
            if len(rows) and int(rows.obj_id.iloc[0]) != obj_id:
                raise ValueError(f"{path}: candidate {cand_id} is of object {int(rows.obj_id.iloc[0])}, not {obj_id}")
            if len(rows) and rows.status.iloc[0] != "ok":
                raise ValueError(f"{path}: candidate {cand_id} was not registered ({rows.reason.iloc[0]})")
        else:
            rows = table[(table.obj_id == obj_id) & (table.status == "ok")].sort_values("cand_id")
        if len(rows):
            # the paper's fused hypothesis, whose matches the figure draws (register keeps
            # several hypotheses per candidate); hyp 0 when the run had one modality
            first = rows[rows.cand_id == rows.cand_id.iloc[0]]
            fused = first[first.source == "fused"] if "source" in first else first.iloc[:0]
            chosen = (item, (fused if len(fused) else first).iloc[0])
            break
    if chosen is None:
        what = f"candidate {cand_id}" if cand_id is not None else f"no registered candidate of object {obj_id}"
        where = f"scene {scene_id}" if scene_id is not None else f"scenes {', '.join(map(str, scenes))}"
        raise LookupError(f"{plan.name}: {what} in {where}" + (" not found" if cand_id is not None else ""))
    item, row = chosen
    model = load_arrays(mf_path)
    diameter = load_attrs(mf_path).get("diameter")
    if diameter is None:
        diameter = plan.model_info(plan.bop(), obj_id).diameter
    sf_path = plan["scene_features"].path(item, "features")
    scene = load_arrays(sf_path)
    i = int(np.flatnonzero(scene["cand_id"] == int(row.cand_id))[0])
    k = int(scene["n_points"][i])
    sgeo, svis = scene["geometric"][i, :k], scene["visual"][i, :k]
    p = plan.run.stages.register
    parts = {"geometric": (model["geometric"], sgeo), "visual": (model["visual"], svis),
             "fused": fused_features(model["geometric"], model["visual"], sgeo, svis, p.pca_dim)}
    notes = [f"no {name} features in this run ({name} encoder 'none'): its row is left empty"
             for name in ("geometric", "visual") if parts[name][0].shape[1] == 0]
    return FeatureCase(dataset=plan.name, obj_id=obj_id, scene_id=int(row.scene_id), im_id=int(row.im_id), cand_id=int(row.cand_id),
                       model_points=model["points"].astype(np.float64), scene_points=scene["points"][i, :k].astype(np.float64),
                       parts=parts, R=np.asarray(row.R, float).reshape(3, 3), t=np.asarray(row.t, float).reshape(3),
                       diameter=float(diameter), inlier_threshold=float(p.inlier_frac * diameter),
                       n_inliers=int(row.n_inliers), model_normals=model.get("normals"), notes=notes)


# ------------------------------------------------------------------------- drawing

FIGSIZE = (8.6, 16.0)  # inches
DPI = 90


def _scatter(ax, pts_cam: np.ndarray, colours: np.ndarray | None, centre: np.ndarray, half: float, size: float,
             alpha: float = 1.0) -> None:
    """Camera-frame points (P, 3) mm drawn orthographically (x right, y down), far ones
    first; points with a NaN or inf coordinate are not drawn."""
    keep = np.isfinite(pts_cam).all(axis=1)
    if not keep.all():
        pts_cam, colours = pts_cam[keep], (None if colours is None else colours[keep])
    order = np.argsort(-pts_cam[:, 2])
    c = "0.6" if colours is None else colours[order]
    edges = "none"
    if alpha == 1.0 and colours is not None:
        # a grey rim around near-white points only, so that they show on the white background
        light = colours[order] @ np.array([0.299, 0.587, 0.114]) > 0.85
        edges = np.where(light[:, None], 0.55, colours[order])  # others: rim in their own colour
    ax.scatter(pts_cam[order, 0], pts_cam[order, 1], c=c, s=size, linewidths=0.4, edgecolors=edges, alpha=alpha)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] + half, centre[1] - half)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def _centre(pts: np.ndarray) -> np.ndarray:
    """(2,) mean x, y (mm) of the finite rows of ``pts`` (P, 3); NaN when there is none."""
    ok = np.isfinite(pts).all(axis=1)
    return pts[ok, :2].mean(axis=0) if ok.any() else np.full(2, np.nan)


def _frame_size(case: FeatureCase, *clouds: np.ndarray) -> float:
    """The object's diameter (mm), or when it is not a positive finite number, the
    largest x/y extent of the clouds' finite points (1 mm when they have none)."""
    if np.isfinite(case.diameter) and case.diameter > 0:
        return float(case.diameter)
    pts = np.concatenate([c[np.isfinite(c).all(axis=1), :2] for c in clouds])
    return float(max(1.0, np.ptp(pts, axis=0).max())) if len(pts) else 1.0


def draw_features_figure(case: FeatureCase, out: Path, max_lines: int = 50, seed: int = 0) -> Path:
    """Write the figure of ``case`` to the PNG ``out`` (FIGSIZE x DPI pixels): rows
    geometric / visual / fused (model left, scene right), then the inlier matches.
    Points with NaN or inf are not drawn; a panel with no point left says "no data"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.views.plots import NO_DATA, no_data, save_figure

    R = np.asarray(case.R, float).reshape(3, 3)
    with np.errstate(invalid="ignore", over="ignore"):  # inf x 0 in a pose or point: NaN, left out below
        model_cam = np.asarray(case.model_points, float).reshape(-1, 3) @ R.T + np.asarray(case.t, float).reshape(3)
    scene_cam = np.asarray(case.scene_points, float).reshape(-1, 3)
    ok_m, ok_s = np.isfinite(model_cam).all(axis=1), np.isfinite(scene_cam).all(axis=1)
    if case.model_normals is not None and len(case.model_normals) == len(model_cam):
        # the side of the surface the camera sees: normal against the viewing ray
        front = np.einsum("nd,nd->n", np.asarray(case.model_normals, float) @ R.T, model_cam) < 0
    else:
        front = np.ones(len(model_cam), bool)
    front &= ok_m
    view = f"{int(front.sum())} of {len(front)} points, those facing the camera" if not front.all() else f"{len(front)} points"
    diameter = _frame_size(case, model_cam, scene_cam)
    c_model, c_scene = _centre(model_cam), _centre(scene_cam)
    if not np.isfinite(c_model).all() or not np.isfinite(c_scene).all():
        # one cloud (or both) without a finite point: frame the other one (or the origin)
        c_model = c_scene = c_model if np.isfinite(c_model).all() else c_scene if np.isfinite(c_scene).all() else np.zeros(2)
    dist = float(np.linalg.norm(c_model - c_scene))
    if dist < diameter:
        # one frame for both: where the model's surface falls on the scene's shows the pose
        centre_m = centre_s = (c_model + c_scene) / 2
        half = 0.6 * diameter + dist / 2
    else:  # a pose far off: centre each cloud on its own
        centre_m, centre_s, half = c_model, c_scene, 0.6 * diameter

    fig = plt.figure(figsize=FIGSIZE, dpi=DPI)
    grid = fig.add_gridspec(4, 2, height_ratios=[1, 1, 1, 1.05], hspace=0.22, wspace=0.04,
                            left=0.02, right=0.98, top=0.92, bottom=0.01)
    fused_colours = None
    for r, name in enumerate(PARTS):
        ax_m, ax_s = fig.add_subplot(grid[r, 0]), fig.add_subplot(grid[r, 1])
        mf, sf = case.parts[name]
        if mf.shape[1] == 0:
            for ax in (ax_m, ax_s):
                ax.axis("off")
            ax_m.text(1.0, 0.5, f"no {name} features in this run\n({name} encoder 'none')", transform=ax_m.transAxes,
                      ha="center", va="center", fontsize=12, color="0.4")
            continue
        cm, cs, explained = pca_colours(mf, sf)
        if name == "fused":
            fused_colours = (cm, cs)
        _scatter(ax_m, model_cam[front], cm[front], centre_m, half, size=9)
        _scatter(ax_s, scene_cam, cs, centre_s, half, size=9)
        for ax, shown in ((ax_m, front.any()), (ax_s, ok_s.any())):
            if not shown:
                no_data(ax, f"{NO_DATA}: no finite point")
        ax_m.set_title(f"model: {name} ({mf.shape[1]} ch)", fontsize=11)
        ax_s.set_title(f"scene candidate: {name}", fontsize=11)
        def clipped(c: np.ndarray) -> float:  # share of points with a component outside the model's range
            return 100 * float(np.mean(((c <= 0) | (c >= 1)).any(axis=1))) if len(c) else 0.0

        ax_s.text(0.01, 0.01, f"{len(cs)} points; {clipped(cs):.0f}% clipped in a component (model: {clipped(cm):.0f}%)",
                  transform=ax_s.transAxes, fontsize=8, color="0.3")
        spread = (f"3-component PCA: {100 * explained:.0f}% of the model's variance" if explained > 0 else
                  "no variance on the model: a single colour")
        ax_m.text(0.01, 0.01, f"{view}\n{spread}",
                  transform=ax_m.transAxes, fontsize=8, color="0.3")

    ax = fig.add_subplot(grid[3, :])
    nn, inl = inlier_matches(case)
    inl = inl & ok_s & ok_m[nn] if len(ok_m) else inl
    gap = 0.65 * diameter
    shift_m, shift_s = np.array([-gap, 0.0]) - c_model, np.array([gap, 0.0]) - c_scene
    m2, s2 = model_cam.copy(), scene_cam.copy()
    m2[:, :2] += shift_m
    s2[:, :2] += shift_s
    cm, cs = fused_colours if fused_colours is not None else (None, None)
    _scatter(ax, m2[front], None if cm is None else cm[front], np.zeros(2), gap + 0.7 * diameter, size=4, alpha=0.35)
    _scatter(ax, s2, cs, np.zeros(2), gap + 0.7 * diameter, size=6, alpha=0.35)
    ax.set_ylim(0.6 * diameter, -0.6 * diameter)
    if not front.any() and not ok_s.any():
        no_data(ax, f"{NO_DATA}: no finite point")
    rng = np.random.default_rng(seed)
    # outliers only among matches with both ends drawn: a line to a NaN point is no line
    inliers = np.flatnonzero(inl)
    outliers = np.flatnonzero(~inl & ok_s & (ok_m[nn] if len(ok_m) else False))
    drawn_in = rng.choice(inliers, min(max_lines, len(inliers)), replace=False) if len(inliers) else inliers
    drawn_out = rng.choice(outliers, min(max_lines // 3, len(outliers)), replace=False) if len(outliers) else outliers
    for idx, colour, lw, alpha in ((drawn_out, "tab:red", 0.6, 0.45), (drawn_in, "tab:green", 0.9, 0.9)):
        for j in idx:
            a, b = m2[nn[j], :2], s2[j, :2]
            ax.plot([a[0], b[0]], [a[1], b[1]], color=colour, lw=lw, alpha=alpha)
    stored = f", register stored {case.n_inliers}" if case.n_inliers is not None else ""
    ax.set_title(f"fused-feature nearest neighbours (scene → model): {int(inl.sum())} of {len(inl)} are inliers\n"
                 f"under the registered pose (< {case.inlier_threshold:.1f} mm){stored}; model left, scene right;\n"
                 f"{len(drawn_in)} inliers drawn in green, {len(drawn_out)} outliers in red", fontsize=10)
    fig.suptitle(f"{case.dataset}: object {case.obj_id}, scene {case.scene_id}, image {case.im_id}, candidate {case.cand_id}\n"
                 "colours: per feature, a 3-component PCA fitted on the model and applied to both;\n"
                 "camera view, model at the registered pose", fontsize=11)
    # the figure's own layout (its grid's margins), written atomically with the umask's mode
    return save_figure(fig, out, dpi=DPI, tight=False)
