"""Geometry of points, depth images, crops, transforms and symmetries (mm, OpenCV camera)."""
