"""Encoder interfaces and the name -> factory registry.

An encoder is described in manifests by an :class:`EncoderSpec` (a name and plain JSON
parameters) and built with :func:`build_encoder`. Built-in encoders (``fpfh``,
``colortex``) need no weights and are registered on first use; other modules add
theirs with :func:`register_encoder`.

Every encoder exposes ``name``, ``kind`` (``"geometric"`` or ``"visual"``), ``version``
(bumped whenever outputs change; part of cache keys), ``dim``, ``signature()`` (short
readable name without ``_``, used in artifact directory names) and ``cache_params()``
(every parameter that changes outputs, as plain JSON).

Weights. Encoders registered with ``weights=True`` (``gedi``, ``dinov2``) take a
``weights_dir`` keyword: the folder where relative ``weights`` paths of their manifests
are resolved and where default weight files are looked up (see
:func:`resolve_weights_dir`). It is where the files live, not what they are, so it is
never part of a cache key; the encoders put a checksum of the weights in
``cache_params()`` instead.

``none-geometric`` and ``none-visual`` (:mod:`pipeline.method.encoders.none`) are the empty
encoders (``dim == 0``) of geometry-only and vision-only runs.
"""

from __future__ import annotations

import abc
import functools
import importlib
import importlib.util
import json
import os
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from pipeline.common.config import PROJECT_ROOT

EncoderKind = Literal["geometric", "visual"]

# Modules whose import registers encoders, imported on first use of the registry (so
# the registry has no import-time dependency on them, and no import cycle). Modules
# that need weights must load them lazily, in their factories, not at import.
_BUILTIN_MODULES = ("pipeline.method.encoders.fpfh", "pipeline.method.encoders.colortex", "pipeline.method.encoders.rgb",
                    "pipeline.method.encoders.none")
# Encoders whose modules import torch (about 1 s and 150 MiB per process): registered
# by name and imported only when one is built, so that jobs using the weight-free
# encoders, and the Snakefile's planning, don't pay for them.
_LAZY_MODULES: dict[str, tuple[EncoderKind, str]] = {
    "dinov2": ("visual", "pipeline.method.encoders.dinov2"),
    "gedi": ("geometric", "pipeline.method.encoders.gedi"),
}
# Encoders that load weight files and so take the ``weights_dir`` keyword.
_WEIGHTED: set[str] = {"dinov2", "gedi"}

WEIGHTS_ENV = "FREEZE_WEIGHTS"


def resolve_weights_dir(weights_dir: str | os.PathLike | None = None) -> Path:
    """The weights folder: ``weights_dir`` if given, else ``$FREEZE_WEIGHTS``, else
    ``<project>/weights``. Relative paths are taken from the current directory."""
    if weights_dir is None:
        weights_dir = os.environ.get(WEIGHTS_ENV) or PROJECT_ROOT / "weights"
    return Path(weights_dir).expanduser().resolve()


def resolve_weights_path(path: str | os.PathLike, weights_dir: str | os.PathLike | None = None) -> Path:
    """``path`` itself if absolute (or starting with ``~``), else relative to the weights
    folder (:func:`resolve_weights_dir`)."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else resolve_weights_dir(weights_dir) / p


class EncoderSpec(BaseModel):
    """Which encoder to build: registry ``name`` and its factory keyword ``params``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    params: dict[str, Any] = Field(default_factory=dict)

    @field_validator("params")
    @classmethod
    def _plain_json(cls, value: dict[str, Any]) -> dict[str, Any]:
        try:
            json.dumps(value, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"encoder params must be plain JSON values: {exc}") from exc
        return value


class _EncoderBase(abc.ABC):
    name: str
    kind: EncoderKind
    version: str
    dim: int

    def signature(self) -> str:
        """Short readable name (no ``_``), e.g. ``fpfh-ms``."""
        return self.name.replace("_", "-")

    @abc.abstractmethod
    def cache_params(self) -> dict[str, Any]:
        """Everything that changes the outputs, as plain JSON values."""

    def describe(self) -> dict[str, Any]:
        """Name, kind, version, dim and cache params in one JSON-able dict."""
        return {
            "name": self.name,
            "kind": self.kind,
            "version": self.version,
            "dim": int(self.dim),
            "params": self.cache_params(),
        }


class GeometricEncoder(_EncoderBase):
    """Per-point descriptors of a 3D point cloud."""

    kind: EncoderKind = "geometric"

    @abc.abstractmethod
    def encode(
        self,
        points: np.ndarray,
        normals: np.ndarray | None,
        diameter: float,
        *,
        viewpoint: np.ndarray | None = None,
    ) -> np.ndarray:
        """Descriptors (N, dim) float32 of ``points`` (N, 3) float32 mm.

        normals: (N, 3) outward unit normals, or None to estimate them and orient them
        towards ``viewpoint`` ((3,) mm, the camera centre for scene points).
        diameter: object diameter in mm; scales are relative to it.
        """


def with_checked_points(encode: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """Decorator of a :meth:`GeometricEncoder.encode` holding its common start: the
    wrapped method gets ``points`` as (N, 3) float64 mm, a positive ``diameter`` (else
    ``ValueError`` naming the encoder) and at least one point (no points give (0, dim)
    float32 descriptors without calling it)."""

    @functools.wraps(encode)
    def checked(self: GeometricEncoder, points: np.ndarray, normals: np.ndarray | None, diameter: float, *,
                viewpoint: np.ndarray | None = None) -> np.ndarray:
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if diameter <= 0:
            raise ValueError(f"{self.name}: diameter must be positive, got {diameter}")
        if len(pts) == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        return encode(self, pts, normals, diameter, viewpoint=viewpoint)

    return checked


class VisualEncoder(_EncoderBase):
    """Dense feature maps of square RGB crops."""

    kind: EncoderKind = "visual"
    input_size: int

    @abc.abstractmethod
    def encode(self, images: np.ndarray) -> np.ndarray:
        """Feature maps (B, dim, h, w) float32 of ``images`` (B, S, S, 3) uint8 RGB with
        ``S == input_size``; ``h, w <= S``. Cell ``j`` of the map covers crop pixels
        ``[j*S/w, (j+1)*S/w)`` (its centre is at crop coordinate ``(j+0.5)*S/w - 0.5``),
        which is the convention :mod:`pipeline.method.encoders.lifting` upsamples with."""

    def check_images(self, images: np.ndarray) -> np.ndarray:
        """``images`` as an array, after checking it is (B, S, S, 3) uint8 with S == input_size."""
        images = np.asarray(images)
        S = self.input_size
        if images.ndim != 4 or images.shape[1:] != (S, S, 3):
            raise ValueError(f"{self.name}: expected images (B, {S}, {S}, 3) uint8, got shape {images.shape}")
        if images.dtype != np.uint8:
            raise ValueError(f"{self.name}: expected uint8 images, got {images.dtype}")
        return images


Encoder = GeometricEncoder | VisualEncoder
EncoderFactory = Callable[..., Encoder]

_REGISTRY: dict[str, tuple[EncoderKind, EncoderFactory]] = {}
_builtins_loaded = False


def register_encoder(name: str, kind: EncoderKind, factory: EncoderFactory, *, weights: bool = False) -> None:
    """Register ``factory(**params) -> encoder`` under ``name``.

    Names must be non-empty and contain no ``_`` (they appear in file names and
    Snakemake wildcards). Re-registering a name replaces the previous factory.
    ``weights=True``: the factory loads weight files and takes a ``weights_dir`` keyword.
    """
    if not name or "_" in name:
        raise ValueError(f"encoder name {name!r} must be non-empty and contain no '_'")
    if kind not in ("geometric", "visual"):
        raise ValueError(f"encoder {name!r}: kind must be 'geometric' or 'visual', got {kind!r}")
    _REGISTRY[name] = (kind, factory)
    if weights:
        _WEIGHTED.add(name)


def needs_weights(name: str) -> bool:
    """Whether the registered encoder ``name`` loads weight files."""
    return name in _WEIGHTED


def _load_builtins() -> None:
    global _builtins_loaded
    if not _builtins_loaded:
        _builtins_loaded = True
        for module in _BUILTIN_MODULES:
            importlib.import_module(module)
        for name, (kind, module) in _LAZY_MODULES.items():
            if name not in _REGISTRY and importlib.util.find_spec(module) is not None:
                _REGISTRY[name] = (kind, _lazy_factory(name, module))


def _lazy_factory(name: str, module: str) -> EncoderFactory:
    """A factory that imports ``module`` (which registers the real factory under
    ``name``, replacing this one) and then builds through it."""

    def factory(**params: Any) -> Encoder:
        importlib.import_module(module)
        real = _REGISTRY[name][1]
        if real is factory:
            raise RuntimeError(f"{module} did not register encoder {name!r}")
        return real(**params)

    return factory


def known_encoders() -> dict[str, EncoderKind]:
    """Registered encoder names and their kinds."""
    _load_builtins()
    return {name: kind for name, (kind, _) in sorted(_REGISTRY.items())}


def build_encoder(spec: EncoderSpec | dict[str, Any], weights_dir: str | os.PathLike | None = None, *,
                  device: str | None = None, allow_download: bool = False) -> Encoder:
    """Build the encoder described by ``spec`` (an :class:`EncoderSpec` or its dict).

    weights_dir: passed to encoders that load weights (see :func:`resolve_weights_dir`);
    ignored by the others.
    device: the run's device (``--config device=...``): ``cpu`` or ``cuda`` replaces the
    ``device`` param of the encoders that load weights (they are the torch ones); None or
    ``auto`` leaves their manifests' value. The numpy/open3d encoders ignore it.
    allow_download: passed (when true) to the encoders that load weights: DINOv2 then
    loads missing weights from the Hugging Face hub; GeDi accepts and ignores it."""
    if not isinstance(spec, EncoderSpec):
        spec = EncoderSpec.model_validate(spec)
    _load_builtins()
    if spec.name not in _REGISTRY:
        known = ", ".join(f"{n} ({k})" for n, k in known_encoders().items())
        raise ValueError(f"unknown encoder {spec.name!r}; known encoders: {known}")
    kind, factory = _REGISTRY[spec.name]
    params = dict(spec.params)
    if weights_dir is not None and spec.name in _WEIGHTED and "weights_dir" not in params:
        params["weights_dir"] = str(weights_dir)
    if device not in (None, "auto") and spec.name in _WEIGHTED:
        params["device"] = str(device)
    if allow_download and spec.name in _WEIGHTED:
        params["allow_download"] = True
    try:
        encoder = factory(**params)
    except TypeError as exc:
        raise ValueError(f"encoder {spec.name!r}: invalid params {spec.params}: {exc}") from exc
    if encoder.kind != kind:
        raise TypeError(f"encoder {spec.name!r} registered as {kind} but built a {encoder.kind} encoder")
    return encoder
