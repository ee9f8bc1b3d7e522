"""Headless rendering (pyrender over EGL) in BOP conventions."""

from pipeline.method.render.renderer import Light, Lighting, Renderer, pose_matrix

__all__ = ["Light", "Lighting", "Renderer", "pose_matrix"]
