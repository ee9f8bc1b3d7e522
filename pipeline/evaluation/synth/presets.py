"""Named sizes of the synthetic dataset.

``tiny`` is for unit tests (seconds), ``mini`` for an end-to-end run of the whole
pipeline in a few minutes on two cores (every object at least once, ~20-40 targets),
``bench`` for measurements (several hundred targets), ``hard`` for measurements on
scenes that depart from the templates the way camera images do (colour drift, white
balance, exposure, gamma, blur, noise, highlights, a noisier and holier depth:
:mod:`pipeline.evaluation.synth.camera_gap`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .objects import OBJ_IDS
from .camera_gap import CameraGap
from .priors import PriorFaults
from .sensor import DepthSensor


@dataclass(frozen=True)
class SynthPreset:
    """Every parameter of one generation run (lengths in mm, angles in degrees).

    objects_per_scene: (min, max) number of distinct objects in a scene.
    duplicate_prob: chance that a scene holds a second instance of one of its objects.
    distractors_per_scene: (min, max) clutter objects that are not in the dataset
    (not annotated, like the unannotated objects of LM or T-LESS scenes).
    camera: fx, fy, cx, cy (px) of a Primesense-like 640x480 camera.
    camera_gap: how the scene images depart from renders (None: the plain camera model
    of :func:`pipeline.evaluation.synth.sensor.simulate_rgb`).
    """

    name: str
    obj_ids: tuple[int, ...]
    n_scenes: int
    images_per_scene: int
    objects_per_scene: tuple[int, int]
    duplicate_prob: float = 0.35
    distractors_per_scene: tuple[int, int] = (1, 3)
    elevation_deg: tuple[float, float] = (30.0, 70.0)
    distance_mm: tuple[float, float] = (600.0, 1100.0)
    width: int = 640
    height: int = 480
    camera: tuple[float, float, float, float] = (572.4114, 573.57043, 325.2611, 242.04899)
    depth_scale: float = 0.1
    sensor: DepthSensor = field(default_factory=DepthSensor)
    faults: PriorFaults = field(default_factory=PriorFaults)
    camera_gap: CameraGap | None = None

    @property
    def K(self) -> np.ndarray:
        fx, fy, cx, cy = self.camera
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def __post_init__(self) -> None:
        lo, hi = self.objects_per_scene
        if not 1 <= lo <= hi <= len(self.obj_ids):
            raise ValueError(f"preset {self.name!r}: objects_per_scene {self.objects_per_scene} must lie in [1, {len(self.obj_ids)}]")
        if self.n_scenes * lo < len(self.obj_ids):
            raise ValueError(f"preset {self.name!r}: {self.n_scenes} scenes x {lo} objects cannot show all {len(self.obj_ids)} objects")
        unknown = set(self.obj_ids) - set(OBJ_IDS)
        if unknown:
            raise ValueError(f"preset {self.name!r}: unknown object ids {sorted(unknown)}")


PRESETS: dict[str, SynthPreset] = {
    "tiny": SynthPreset("tiny", obj_ids=(2, 5, 6), n_scenes=1, images_per_scene=2, objects_per_scene=(3, 3), duplicate_prob=1.0,
                        distractors_per_scene=(1, 1)),
    "mini": SynthPreset("mini", obj_ids=OBJ_IDS, n_scenes=3, images_per_scene=2, objects_per_scene=(4, 5)),
    "bench": SynthPreset("bench", obj_ids=OBJ_IDS, n_scenes=12, images_per_scene=7, objects_per_scene=(5, 8)),
    # Kinect-like depth: twice the axial noise, 1/8 px disparity steps, more dropped edges and blobs
    "hard": SynthPreset("hard", obj_ids=OBJ_IDS, n_scenes=6, images_per_scene=4, objects_per_scene=(4, 6),
                        sensor=DepthSensor(noise_k=3.0e-6, disparity_step_px=0.125, edge_drop_prob=0.8,
                                           dropout_fraction=0.01),
                        camera_gap=CameraGap()),
}


def preset_layout(preset: str | SynthPreset, seed: int = 0) -> tuple[list[int], list[int]]:
    """(obj_ids, scene_ids) that ``generate`` will write for a preset, without generating.

    Every object of the preset is in the dataset (models/ and at least one scene);
    scenes are numbered 1..n_scenes. The seed does not change either list.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise KeyError(f"unknown synth preset {preset!r}; choose one of {sorted(PRESETS)}")
        preset = PRESETS[preset]
    return sorted(preset.obj_ids), list(range(1, preset.n_scenes + 1))
