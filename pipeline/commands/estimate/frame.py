"""One RGB-D frame of one object as a dataset the pipeline runs on (``freeze estimate``).

The frame is written as a one-image BOP dataset (:func:`pipeline.formats.bop.wrap.wrap_frame`)
with its prior, and beside it a dataset manifest, ``<bop_root>/<name>.yaml``, so that the
stages, and ``snakemake bop_all``, take it like any BOP dataset::

    snakemake --cores 2 bop_all --config bop_root=OUT/bop datasets=OUT/bop/NAME.yaml

The scene-side keys hash every byte of the frame (as for every dataset), so a new image is never answered from the cache,
while the model-side keys hash only the model's files, so the model side (templates,
symmetries, features) is reused for every frame of the same model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

OBJ_ID, SCENE_ID, IM_ID = 1, 1, 0
"""The ids of the frame's object, scene and image in the wrapped dataset."""
DETECTOR = "estimate"
"""Detector name of the prior file (``detections/estimate_<name>-test.json``)."""


@dataclass(frozen=True)
class FrameDataset:
    """The wrapped frame: the dataset folder, its manifest and its prior file."""

    root: Path
    manifest: Path
    prior: Path

    @property
    def bop_root(self) -> Path:
        return self.root.parent

    def obj_item(self) -> str:
        return f"obj_{OBJ_ID:06d}"

    def scene_item(self) -> str:
        return f"scene_{SCENE_ID:06d}"


def dataset_manifest(name: str, width: int, height: int, image_mode: str = "rgb") -> dict:
    """The manifest (as a mapping) of a wrapped frame named ``name``. A grey frame
    (``image_mode="gray"``) is declared as grey datasets are (``image_dir: gray``, as
    ITODD's manifest, its image in ``gray/``), so that its templates and SAR renders are
    grey like the image."""
    if image_mode not in ("rgb", "gray"):
        raise ValueError(f"image_mode must be 'rgb' or 'gray', got {image_mode!r}")
    return {
        "name": name,
        "kind": "bop",
        "prior": f"detections/{DETECTOR}_{name}-test.json",
        "obj_ids": [OBJ_ID],
        "image_size": [int(width), int(height)],
        **({"image_dir": "gray"} if image_mode == "gray" else {}),
    }


def pipeline_command(bop_root: Path, manifest: Path) -> str:
    """The shell command that runs the pipeline on a wrapped frame, each argument quoted
    (:func:`shlex.quote`) so that it pastes whole into a POSIX shell whatever the paths hold."""
    import shlex

    return shlex.join(["snakemake", "--cores", "2", "bop_all", "--config", f"bop_root={bop_root}",
                       f"datasets={manifest}"])


def write_frame_dataset(bop_root: Path, name: str, *, rgb: np.ndarray, depth_mm: np.ndarray, K: np.ndarray,
                        model_path: Path, model_scale: float = 1.0, mask: np.ndarray | None = None,
                        bbox: Sequence[float] | None = None, kept_mask: np.ndarray | None = None,
                        image_mode: str = "rgb", final_root: Path | None = None) -> FrameDataset:
    """Write the frame as ``<bop_root>/<name>`` (replacing a previous one of that name),
    its prior and ``<bop_root>/<name>.yaml``.

    rgb (H, W, 3) uint8; depth_mm (H, W) float32 mm; K (3, 3); model_path: PLY whose
    coordinates times ``model_scale`` are mm. The prior's mask is ``mask``, or, with only
    a box, the box's pixels in ``kept_mask`` (what :func:`pipeline.method.geometry.box_points.box_candidate_points`
    kept); its bbox is ``bbox`` when given. image_mode: ``"gray"`` for a grey image (see
    :func:`dataset_manifest`). final_root: where ``bop_root`` will be once moved into
    place (``freeze estimate`` writes to a staging folder first), named in the command
    the manifest's comment gives (default ``bop_root``). Raises ValueError on bad input.
    """
    from pipeline.formats.bop import wrap
    from pipeline.common.store import atomic_write_text

    bop_root = Path(bop_root)
    H, W = rgb.shape[:2]
    text = yaml.safe_dump(dataset_manifest(name, W, H, image_mode), sort_keys=False)
    root = wrap.wrap_frame(bop_root, name, rgb=rgb, depth_mm=depth_mm, K=K, model_path=model_path,
                           model_scale=model_scale, mask=mask, bbox=bbox, kept_mask=kept_mask, obj_id=OBJ_ID,
                           scene_id=SCENE_ID, im_id=IM_ID, detector=DETECTOR, overwrite=True,
                           grey=image_mode == "gray")
    manifest = bop_root / f"{name}.yaml"
    shown = Path(final_root) if final_root is not None else bop_root
    command = pipeline_command(shown, shown / manifest.name)
    if "\n" in command or "\r" in command:  # a path with a line break cannot sit in a YAML comment
        command = "snakemake --cores 2 bop_all --config bop_root=<this folder> datasets=<this file>"
    atomic_write_text(manifest, f"# A frame wrapped by `freeze estimate`; run it with\n#   {command}\n" + text)
    return FrameDataset(root=root, manifest=manifest, prior=wrap.detections_path(bop_root, name, DETECTOR))
