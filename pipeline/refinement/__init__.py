"""Pose refinement after ICP: symmetry-aware refinement (SAR, :mod:`.sar`)."""

from pipeline.refinement.sar import (
    SarResult,
    cell_cover,
    crop_intrinsics,
    render_in_crop,
    sar_similarity,
    symmetry_aware_refinement,
    unique_symmetries,
    variant_poses,
)

__all__ = [
    "SarResult",
    "cell_cover",
    "crop_intrinsics",
    "render_in_crop",
    "sar_similarity",
    "symmetry_aware_refinement",
    "unique_symmetries",
    "variant_poses",
]
