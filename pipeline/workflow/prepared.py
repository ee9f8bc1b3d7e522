"""The prepared objects of a scene-side job, read from the model side's artifacts.

:func:`prepared_objects` gives a stage the :class:`pipeline.method.estimator.PreparedObject`
of every object of the dataset, each field a loader that opens the artifact only when the
estimator first needs it, through the job's :class:`pipeline.workflow.plan.StageIO` (so a
field the stage did not declare it reads is refused there, naming the stage).
"""

from __future__ import annotations

from typing import Sequence

from pipeline.method.estimator import PreparedObject
from pipeline.workflow.plan import StageIO, obj_item


def prepared_objects(io: StageIO, bop, *, features: Sequence[str] | None = None,
                     symmetries: bool = False) -> dict[int, PreparedObject]:
    """obj_id -> PreparedObject of every object in the dataset's models_info: its
    diameter (mm), and as loaders: ``features`` (the model_features arrays named, None:
    not given, ``()``: every array), with ``symmetries`` the estimated and near
    symmetries of its ``symmetries.json`` and the declared ones of models_info. (The
    stages render the meshes through their :class:`pipeline.method.scene_side.SceneImages`.)"""
    from pipeline.method.geometry.symmetry import SymmetrySet
    from pipeline.method.model_side import read_near_symmetries, read_symmetries

    out = {}
    for obj_id, info in bop.models_info().items():
        fields = {}
        # the folders are looked up when read: an object no candidate needs is never asked for
        if features is not None:
            names = list(features) or None
            fields["features"] = lambda o=obj_id, names=names: io.arrays("model_features", "features", obj_item(o),
                                                                          names)
        if symmetries:
            fields["symmetries"] = lambda o=obj_id: read_symmetries(_symmetries_json(io, o))
            fields["near_symmetries"] = lambda o=obj_id: read_near_symmetries(_symmetries_json(io, o))
            fields["declared"] = lambda info=info: SymmetrySet.from_model_info(info)
        out[obj_id] = PreparedObject(obj_id, info.diameter, **fields)
    return out


def _symmetries_json(io: StageIO, obj_id: int):
    return io.path("symmetries", "symmetries", obj_item(obj_id))
