"""BOP 2019 pose-estimation metrics: VSD, MSSD, MSPD, greedy matching, recall and AR."""

from .evaluate import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    ROTATION_TOLERANCE,
    VSD_THETAS,
    NotARotationError,
    Scores,
    bop_vsd_delta,
    check_rotations,
    evaluate,
    load_scores,
    score_results_file,
    vsd_column,
)
from .matching import greedy_match, valid_gt_mask
from .pose_errors import mspd, mssd, project
from .bop_symmetries import model_symmetries, symmetry_transformations
from .vsd import VSD_TAUS, Crop, depth_to_distance, sphere_projections_overlap, vsd, vsd_crops, vsd_from_distances

__all__ = [
    "Crop",
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "NotARotationError",
    "ROTATION_TOLERANCE",
    "VSD_TAUS",
    "VSD_THETAS",
    "Scores",
    "bop_vsd_delta",
    "check_rotations",
    "depth_to_distance",
    "evaluate",
    "greedy_match",
    "load_scores",
    "model_symmetries",
    "mspd",
    "mssd",
    "project",
    "score_results_file",
    "sphere_projections_overlap",
    "symmetry_transformations",
    "valid_gt_mask",
    "vsd",
    "vsd_column",
    "vsd_crops",
    "vsd_from_distances",
]
