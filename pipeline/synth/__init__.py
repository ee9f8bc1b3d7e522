"""Synthetic BOP-format dataset generator: procedural objects, cluttered tabletop
scenes, a Primesense-like sensor model and a faulty CNOS-style localisation prior.

Entry point: ``generate(out_dir, name, preset="mini", seed=0)``; sizes in ``PRESETS``.
"""

from .writer import compose_scenes, generate
from .objects import OBJ_IDS, SynthObject, build_object
from .presets import PRESETS, SynthPreset, preset_layout

__all__ = ["OBJ_IDS", "PRESETS", "SynthObject", "SynthPreset", "build_object", "compose_scenes", "generate", "preset_layout"]
