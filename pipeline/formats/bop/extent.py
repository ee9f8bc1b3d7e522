"""Extent of point sets: the model diameter of ``models_info.json``, which BOP uses for its
thresholds (in formats: the wrapper writes it, and the method and the scorer read it)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.distance import pdist


def point_cloud_diameter(points: np.ndarray) -> float:
    """Largest distance (mm) between two points of (N, 3): exact, over the convex hull's
    vertices where it is attained (all points when the hull is degenerate: flat or
    collinear). 0 for fewer than two points."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 2:
        return 0.0
    try:
        pts = pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):
        pass
    return float(pdist(pts).max())
