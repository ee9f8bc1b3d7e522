"""Datasets the pipeline builds itself: the synthetic BOP-format generator (procedural
objects, cluttered tabletop scenes, a Primesense-like sensor model and a faulty
CNOS-style localisation prior), semi-real datasets made from real samples
(:mod:`.semireal`) and real datasets copied from real samples with an exact and a
derived faulty prior (:mod:`.real_sample`).

Entry points: ``generate(out_dir, name, preset="mini", seed=0)`` (sizes in ``PRESETS``),
``build_semireal(source, out_dir, name)``, ``build_real(source, out_dir, ds)``, and
``build_dataset`` for a dataset manifest
(the ``synth`` stage).
"""

from pathlib import Path

from .objects import OBJ_IDS, SynthObject, build_object
from .presets import PRESETS, SynthPreset, preset_layout
from .real_sample import build_real
from .semireal import build_semireal
from .writer import compose_scenes, generate


def build_dataset(ds, out_dir: Path, source: Path | None = None, progress: bool = True) -> dict:
    """Build the dataset of manifest ``ds`` (:class:`pipeline.common.config.DatasetManifest`,
    kind ``synthetic``, ``semireal`` or ``real``) in ``out_dir``; ``source``: the real
    sample of a semi-real or real one. Returns the builder's summary."""
    if ds.kind == "synthetic":
        return generate(out_dir, ds.name, preset=ds.preset, seed=ds.seed, progress=progress)
    if ds.kind == "semireal":
        return build_semireal(source, out_dir, ds.name, depth=ds.depth, prior=ds.gt_prior, seed=ds.seed,
                              progress=progress)
    if ds.kind == "real":
        return build_real(source, out_dir, ds, progress=progress)
    raise ValueError(f"dataset '{ds.name}' is a {ds.kind} dataset: the pipeline does not build it")


__all__ = ["OBJ_IDS", "PRESETS", "SynthObject", "SynthPreset", "build_dataset", "build_object", "build_real", "build_semireal",
           "compose_scenes", "generate", "preset_layout"]
