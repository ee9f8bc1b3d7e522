"""The library side of ``freeze estimate`` (the method on one RGB-D image of one object).

- :mod:`.inputs`: camera JSON, images, masks, boxes and the model, read and checked;
- :mod:`.frame`: the frame written as a one-image BOP dataset with its manifest;
- :mod:`.record`: ``pose.json``, read back from the stages' artifacts;
- :mod:`.output`: the ``--out`` folder, which the estimate marks and writes only what it owns in.

The box rule lives in :mod:`pipeline.method.geometry.box_points`, the pictures in
:mod:`pipeline.views.overlay`, and the command that runs the stages on the frame in
:mod:`pipeline.commands.estimate.command`.
"""

from .inputs import (METRE_DIAMETER_LIMIT, Camera, EstimateError, check_intrinsics, check_prior_size, load_camera,
                     load_depth, load_mask, load_model, load_rgb, load_rgb_and_mode, parse_bbox, scale_warning)

__all__ = ["METRE_DIAMETER_LIMIT", "Camera", "EstimateError", "check_intrinsics", "check_prior_size", "load_camera",
           "load_depth", "load_mask", "load_model", "load_rgb", "load_rgb_and_mode", "parse_bbox", "scale_warning"]
