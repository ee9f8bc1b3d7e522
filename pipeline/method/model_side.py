"""The per-object (onboarding) computations shared by the stages and ``freeze estimate``:
the model's symmetry record and its fused-feature ingredients."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np


def symmetry_record(mesh, diameter: float, *, n_points: int, sample_seed: int, threshold: float, seed: int,
                    declared, obj_id: int):
    """Estimate the shape symmetries of ``mesh`` (mm) from ``n_points`` surface samples
    (drawn with ``sample_seed``). Returns ``(SymmetrySet, record)`` where ``record`` is
    the ``symmetries.json`` content: ``obj_id``, ``estimated`` and ``declared`` (BOP
    models_info form; ``declared`` a :class:`SymmetrySet`), ``n_discrete``,
    ``n_continuous``, ``threshold_mm``, ``rejected_best_mm``, ``near_symmetries``
    (``[{"T": 16 floats row-major, "score_mm"}]``, the turns refinement tries, see
    :mod:`pipeline.method.refinement.turns`) and ``seconds``."""
    from pipeline.method.geometry.sampling import sample_surface
    from pipeline.method.geometry.symmetry import SymmetryParams, estimate_symmetries

    points, normals = sample_surface(mesh, n_points, seed=sample_seed)
    details: dict = {}
    sym = estimate_symmetries(points, diameter, normals, SymmetryParams(threshold=threshold, seed=seed), details=details)
    record = {
        "obj_id": obj_id,
        "estimated": sym.to_dict(),
        "declared": declared.to_dict(),
        "n_discrete": len(sym.discrete),
        "n_continuous": len(sym.continuous),
        "threshold_mm": float(details.get("threshold_mm", threshold * diameter)),
        "rejected_best_mm": details.get("rejected_best"),
        "near_symmetries": [{"T": np.asarray(T, float).reshape(16).tolist(), "score_mm": float(s)}
                            for T, s in details.get("near", [])],
        "seconds": details.get("seconds"),
    }
    return sym, record


def model_features(mesh, templates: Mapping[str, np.ndarray], geo, vis, diameter: float, *, n_points: int,
                   seed: int, batch_size: int) -> dict[str, np.ndarray]:
    """The ``features.zarr`` arrays of one model: points (N, 3) float32 mm and normals
    sampled on ``mesh`` (seed ``seed``), geometric (N, G) float32 from ``geo``, visual
    (N, C) float32 lifted from ``templates`` (rgb, depth, K, R, t arrays as
    render_templates writes them) through ``vis``, view_count (N,) int32."""
    from pipeline.method.encoders.lifting import lift_model_visual_features
    from pipeline.method.geometry.sampling import sample_surface

    points, normals = sample_surface(mesh, n_points, seed=seed)
    geometric = geo.encode(points, normals, diameter)
    views = [(templates["rgb"][i], templates["depth"][i], templates["K"][i], templates["R"][i], templates["t"][i])
             for i in range(len(templates["rgb"]))]
    visual, view_count = lift_model_visual_features(points, views, vis, batch_size=batch_size, diameter=diameter)
    return {"points": points.astype(np.float32), "normals": normals.astype(np.float32),
            "geometric": geometric.astype(np.float32), "visual": visual.astype(np.float32),
            "view_count": view_count.astype(np.int32)}


def read_symmetries(path: Path):
    """The estimated :class:`~pipeline.method.geometry.symmetry.SymmetrySet` in a ``symmetries.json``
    written by :func:`symmetry_record`."""
    import json

    from pipeline.method.geometry.symmetry import SymmetrySet

    return SymmetrySet.from_dict(json.loads(Path(path).read_text())["estimated"])


def read_near_symmetries(path: Path) -> list[np.ndarray]:
    """The near-symmetries ((4, 4) float64 each, best first) in a ``symmetries.json``
    written by :func:`symmetry_record`."""
    import json

    from pipeline.formats.bop.errors import BopFormatError

    record = json.loads(Path(path).read_text())
    if "near_symmetries" not in record:
        raise BopFormatError(f"{path}: field 'near_symmetries' is missing (written by an older version; "
                             "run freeze verify --repair or delete the folder to rebuild it)")
    return [np.asarray(n["T"], dtype=np.float64).reshape(4, 4) for n in record["near_symmetries"]]
