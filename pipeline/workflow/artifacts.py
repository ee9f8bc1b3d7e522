"""Looking inside the artifact store: one artifact in detail, every artifact in a list,
and garbage collection of the ones no current plan points to.

An artifact is an item folder ``cache/<dataset>/<stage>/<signature>/<item>/`` holding a
``_manifest.json`` (see :mod:`pipeline.common.store`). :func:`inspect_artifact` describes one:
its manifest, its Zarr arrays (shape, dtype, chunking, compression, summary statistics,
and for feature arrays the distribution of row L2 norms), its Parquet tables (schema,
rows, key metadata) and the chain of upstream artifacts it was built from, found by key
in the same cache (:class:`ArtifactIndex`). Everything is returned as plain JSON-able
dicts; :mod:`pipeline.commands.inspect` prints them.

:func:`list_artifacts` walks the cache and marks each stage signature folder ``current``
(the plan of the given run configuration points to it), ``stale`` (it does not) or
``unknown`` (no plan could be built for its dataset, or the stage is not a known
stage); :func:`collect_garbage` removes the stale ones and the leftovers of interrupted
publishes, and nothing else.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from pipeline.common.store import MANIFEST_NAME, table_metadata

# Arrays whose rows are feature vectors whatever their width (see is_feature_array).
FEATURE_NAMES = frozenset({"geometric", "visual", "fused", "features"})
# Image stacks have a last dimension > 3 too, but their rows are not feature vectors.
IMAGE_NAMES = frozenset({"rgb", "depth", "mask", "pixels"})
# Statistics are accumulated over blocks of the first axis of about this many bytes, so
# that a large scene feature array (C, M, D) never has to be in memory whole.
_BLOCK_BYTES = 32 << 20
# Prefixes of the hidden folders store.publish() leaves behind when it is interrupted:
# the temporary copy being written, and the old copy being replaced.
LEFTOVER_PREFIXES = (".tmp-", ".old-")


class NotAnArtifact(ValueError):
    """The path given is not (inside) an artifact item folder."""


# ------------------------------------------------------------------------ locating


@dataclass(frozen=True)
class ArtifactPath:
    """Where a path lies in the store.

    item_dir: the artifact's item folder (holds ``_manifest.json``); target: the path
    asked about (the item folder itself, a Zarr store, a Parquet file, ...); cache: the
    store's root (``item_dir`` is ``cache/<dataset>/<stage>/<signature>/<item>``).
    """

    item_dir: Path
    target: Path
    cache: Path

    @property
    def dataset(self) -> str:
        return self.item_dir.parents[2].name

    @property
    def stage(self) -> str:
        return self.item_dir.parents[1].name

    @property
    def signature(self) -> str:
        return self.item_dir.parent.name

    @property
    def item(self) -> str:
        return self.item_dir.name


def locate(path: Path | str) -> ArtifactPath:
    """Find the artifact item folder that is ``path`` or contains it.

    Raises :class:`NotAnArtifact` naming ``path`` when it does not exist or no folder at
    or above it holds a ``_manifest.json`` (e.g. a stage or signature folder).
    """
    given = Path(path).expanduser()
    p = given.resolve()
    if not p.exists():
        raise NotAnArtifact(f"{given}: no such file or folder")
    if p.name == MANIFEST_NAME:
        p = p.parent
    for d in [p, *p.parents] if p.is_dir() else list(p.parents):
        if (d / MANIFEST_NAME).is_file():
            if len(d.parents) < 4:
                raise NotAnArtifact(f"{given}: {d} holds a {MANIFEST_NAME} but is not at "
                                    "<cache>/<dataset>/<stage>/<signature>/<item>")
            return ArtifactPath(item_dir=d, target=p, cache=d.parents[3])
    hint = ""
    if p.is_dir():
        items = sorted(c.name for c in p.iterdir() if (c / MANIFEST_NAME).is_file())
        if items:
            shown = ", ".join(items[:6]) + (", ..." if len(items) > 6 else "")
            hint = f"; it is a stage signature folder holding {len(items)} artifacts ({shown}): inspect one of them"
    raise NotAnArtifact(f"{given}: not an artifact (no {MANIFEST_NAME} in it or in a folder above it; an artifact is "
                        f"<cache>/<dataset>/<stage>/<signature>/<item>/){hint}")


# --------------------------------------------------------------------- key index


class ArtifactIndex:
    """Every artifact of a cache by key, read once (``cache/*/*/*/*/_manifest.json``).

    A stage key names a signature folder; its items (one per object, scene, ...) share
    the key and the upstream keys.
    """

    def __init__(self, cache: Path):
        self.cache = Path(cache)
        self._by_key: dict[str, list[Path]] | None = None
        self._manifests: dict[Path, dict[str, Any]] = {}

    def _build(self) -> dict[str, list[Path]]:
        if self._by_key is None:
            self._by_key = {}
            for path in sorted(self.cache.glob(f"*/*/*/*/{MANIFEST_NAME}")):
                if any(part.startswith(".") for part in path.relative_to(self.cache).parts[:-1]):
                    continue  # a publish in progress or interrupted
                try:
                    man = json.loads(path.read_text())
                except (OSError, json.JSONDecodeError):
                    continue
                self._manifests[path.parent] = man
                if isinstance(man, dict) and "key" in man:
                    self._by_key.setdefault(man["key"], []).append(path.parent)
        return self._by_key

    def items(self, key: str) -> list[Path]:
        """Item folders of the artifact with ``key`` (empty if none in this cache)."""
        return list(self._build().get(key, []))

    def manifest(self, item_dir: Path) -> dict[str, Any]:
        self._build()
        if item_dir not in self._manifests:
            self._manifests[item_dir] = json.loads((item_dir / MANIFEST_NAME).read_text())
        return self._manifests[item_dir]


def upstream_tree(manifest: Mapping[str, Any], index: ArtifactIndex, item: str | None = None,
                  _seen: set[str] | None = None) -> list[dict[str, Any]]:
    """The chain of upstream artifacts of ``manifest``, as nested nodes.

    Each node: ``name`` (the upstream's role, e.g. ``model_features``), ``key``,
    ``found``; when found: ``dataset``, ``stage``, ``signature``, ``path`` (the signature
    folder), ``items`` (item names), ``item_path`` (the item of the same name as
    ``item``, if any), ``upstream`` (its own nodes) or ``repeated`` (True when it already
    appears earlier in the tree and is not expanded again).
    A key not found is a dataset fingerprint or a file hash (BOP data on disk, a prior
    file), or an artifact deleted since.
    """
    seen = set() if _seen is None else _seen
    nodes = []
    for name, key in sorted(dict(manifest.get("upstream") or {}).items()):
        node: dict[str, Any] = {"name": name, "key": key}
        dirs = index.items(key)
        if not dirs:
            node["found"] = False
            nodes.append(node)
            continue
        sig_dir = dirs[0].parent
        up = index.manifest(dirs[0])
        same = [d for d in dirs if d.name == item]
        node.update(found=True, dataset=up.get("dataset", sig_dir.parents[1].name), stage=up.get("stage", sig_dir.parent.name),
                    signature=sig_dir.name, path=str(sig_dir), items=sorted(d.name for d in dirs),
                    item_path=str(same[0]) if same else None)
        if key in seen:
            node["repeated"] = True
        else:
            seen.add(key)
            node["upstream"] = upstream_tree(up, index, item, seen)
        nodes.append(node)
    return nodes


def _walk_nodes(nodes: list[dict[str, Any]]) -> Iterable[dict[str, Any]]:
    """Breadth-first over an upstream tree."""
    queue = list(nodes)
    while queue:
        node = queue.pop(0)
        yield node
        queue.extend(node.get("upstream", []))


def _encoders(manifest: Mapping[str, Any], tree: list[dict[str, Any]], index: ArtifactIndex) -> dict[str, Any] | None:
    """Encoder names, versions and parameters: from the artifact's own parameters, else
    from the nearest upstream artifact that records them (register, refine and score
    inherit them through their upstream keys)."""
    enc = (manifest.get("params") or {}).get("encoders")
    if enc:
        return {**enc, "recorded_by": "this artifact"}
    for node in _walk_nodes(tree):
        if node.get("found"):
            up = index.manifest(index.items(node["key"])[0])
            enc = (up.get("params") or {}).get("encoders")
            if enc:
                return {**enc, "recorded_by": f"{node['stage']}/{node['signature']}"}
    return None


# ------------------------------------------------------------------ zarr arrays


def is_feature_array(name: str, shape: tuple[int, ...], dtype: np.dtype) -> bool:
    """Rows are feature vectors: a 2D/3D float array named geometric/visual/fused/features,
    or any other 2D/3D float array with a last dimension > 3 that is not an image stack."""
    if np.dtype(dtype).kind != "f" or len(shape) not in (2, 3):
        return False
    leaf = name.rsplit("/", 1)[-1]
    return leaf in FEATURE_NAMES or (shape[-1] > 3 and leaf not in IMAGE_NAMES)


def _codecs(arr) -> str:
    """Short description of an array's compressors, e.g. ``blosc(zstd, 3)``."""
    out = []
    for codec in tuple(getattr(arr, "compressors", ()) or ()):
        try:
            d = codec.to_dict()
            name, conf = d.get("name", type(codec).__name__), d.get("configuration", {})
        except Exception:  # zarr v2 numcodecs objects
            name, conf = getattr(codec, "codec_id", type(codec).__name__), getattr(codec, "get_config", dict)()
        args = [str(conf[k].value if hasattr(conf[k], "value") else conf[k]) for k in ("cname", "clevel", "level") if k in conf]
        out.append(f"{name}({', '.join(args)})" if args else str(name))
    return "+".join(out) or "none"


def _norm_stats(norms: np.ndarray) -> dict[str, Any]:
    if not len(norms):
        return {}
    q = np.percentile(norms, [5, 25, 50, 75, 95])
    return {"min": float(norms.min()), "p05": float(q[0]), "p25": float(q[1]), "median": float(q[2]),
            "p75": float(q[3]), "p95": float(q[4]), "max": float(norms.max()), "mean": float(norms.mean())}


def array_info(arr, name: str) -> dict[str, Any]:
    """Description of one Zarr array: shape, dtype, chunks, compressors, ``nbytes``
    (uncompressed), ``stored_bytes`` (what the store holds for it: chunks plus its
    metadata document, zarr's ``nbytes_stored()``), ``ratio`` (nbytes / stored_bytes), and
    ``stats``: ``nan`` (count of NaN values), ``min``/``max``/``mean`` over the finite
    values (None if there are none). Feature arrays (:func:`is_feature_array`) also get
    ``norms``: rows (vectors along the last axis), ``nan_rows`` (rows with a NaN, e.g.
    the padding of scene features), ``zero_rows`` (norm < 1e-12) and the distribution
    of the L2 norms of the other rows."""
    shape = tuple(int(s) for s in arr.shape)
    dtype = np.dtype(arr.dtype)
    nbytes = int(arr.nbytes)
    try:
        stored = int(arr.nbytes_stored())
    except Exception:
        stored = None
    info: dict[str, Any] = {
        "name": name, "shape": list(shape), "dtype": str(dtype), "chunks": list(arr.chunks), "compressors": _codecs(arr),
        "nbytes": nbytes, "stored_bytes": stored,
        "ratio": round(nbytes / stored, 3) if stored else None,
    }
    if dtype.kind not in "biuf":
        return info
    n = int(np.prod(shape)) if shape else 1
    nan = 0
    count = 0
    total = 0.0
    lo, hi = np.inf, -np.inf
    feature = is_feature_array(name, shape, dtype)
    norms, nan_rows = [], 0
    if n:
        row_bytes = max(1, dtype.itemsize * (int(np.prod(shape[1:])) if len(shape) > 1 else 1))
        step = max(1, _BLOCK_BYTES // row_bytes)
        blocks = [slice(None)] if not shape else [slice(s, s + step) for s in range(0, shape[0], step)]
        for sl in blocks:
            block = np.asarray(arr[sl] if shape else arr[...])
            if dtype.kind == "b":
                block = block.astype(np.int8)
            if dtype.kind == "f":
                finite = np.isfinite(block)
                nan += int(np.isnan(block).sum())
                vals = block[finite]
            else:
                vals = block.reshape(-1)
            if vals.size:
                count += int(vals.size)
                total += float(vals.sum(dtype=np.float64))
                lo, hi = min(lo, float(vals.min())), max(hi, float(vals.max()))
            if feature and shape[-1] > 0:
                rows = block.reshape(-1, shape[-1]).astype(np.float64)
                bad = np.isnan(rows).any(axis=1)
                nan_rows += int(bad.sum())
                norms.append(np.linalg.norm(rows[~bad], axis=1))
    info["stats"] = {"nan": nan, "min": lo if count else None, "max": hi if count else None,
                     "mean": total / count if count else None}
    if feature:
        rows_total = int(np.prod(shape[:-1]))
        all_norms = np.concatenate(norms) if norms else np.zeros(0)
        info["norms"] = {"channels": shape[-1], "rows": rows_total, "nan_rows": nan_rows if shape[-1] else 0,
                         "zero_rows": int((all_norms < 1e-12).sum()) if shape[-1] else rows_total,
                         **_norm_stats(all_norms)}
    return info


def zarr_info(path: Path, only: str | None = None, manifest_key: str | None = None) -> dict[str, Any]:
    """A Zarr group: its attributes, whether their ``key`` matches the manifest's, and
    :func:`array_info` of every array in it (nested groups included, as ``group/name``),
    or only of the array ``only``."""
    import zarr

    group = zarr.open_group(str(path), mode="r")
    attrs = dict(group.attrs)
    arrays = []

    def walk(g, prefix: str) -> None:
        for name in sorted(g.array_keys()):
            full = f"{prefix}{name}"
            if only is None or full == only:
                arrays.append(array_info(g[name], full))
        for name in sorted(g.group_keys()):
            walk(g[name], f"{prefix}{name}/")

    walk(group, "")
    key = attrs.get("key")
    return {"path": str(path), "zarr_format": int(getattr(group.metadata, "zarr_format", 0) or 0), "attrs": attrs,
            "key_matches": None if key is None or manifest_key is None else key == manifest_key, "arrays": arrays}


# ---------------------------------------------------------------- parquet tables


def parquet_info(path: Path, manifest_key: str | None = None) -> dict[str, Any]:
    """A Parquet file: row count, row groups, file size, schema (column name, Arrow type,
    null count) and the ``freeze`` metadata
    (:func:`pipeline.common.store.write_table`), with whether its ``key`` matches the manifest's."""
    import pyarrow.parquet as pq

    pf = pq.ParquetFile(str(path))
    meta = pf.metadata
    # Null counts come from the row-group statistics of flat columns (one leaf column
    # each); a nested column's leaf statistics count null elements, not null rows.
    leaf = {meta.schema.column(i).path: i for i in range(meta.num_columns)}
    columns = []
    for fld in pf.schema_arrow:
        nulls: int | None = None
        if fld.name in leaf:
            nulls = 0
            for g in range(meta.num_row_groups):
                st = meta.row_group(g).column(leaf[fld.name]).statistics
                if st is None or not st.has_null_count:
                    nulls = None
                    break
                nulls += int(st.null_count)
        if nulls is None:  # nested (e.g. a list of floats per row): read that column alone
            nulls = int(pf.read(columns=[fld.name]).column(0).null_count)
        columns.append({"name": fld.name, "type": str(fld.type), "null_count": nulls})
    freeze = table_metadata(path)
    key = freeze.get("key")
    return {"path": str(path), "rows": int(meta.num_rows), "row_groups": int(meta.num_row_groups),
            "size_bytes": Path(path).stat().st_size, "columns": columns, "metadata": freeze,
            "key_matches": None if key is None or manifest_key is None else key == manifest_key}


# ------------------------------------------------------------------- other files


def tree_size(path: Path) -> tuple[int, int]:
    """(bytes, files) of a file or of everything under a folder (symlinks not followed)."""
    path = Path(path)
    if path.is_symlink() or path.is_file():
        return (path.lstat().st_size, 1)
    total = n = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
                n += 1
            except OSError:
                continue
    return total, n


def _is_zarr(path: Path) -> bool:
    return path.is_dir() and (path.suffix == ".zarr" or (path / "zarr.json").exists() or (path / ".zgroup").exists())


def file_info(path: Path) -> dict[str, Any]:
    """A file or folder that is neither Zarr nor Parquet: its size and file count, and for
    a JSON file its top-level keys (or length), for a CSV its number of data lines."""
    size, n = tree_size(path)
    out: dict[str, Any] = {"path": str(path), "kind": "dir" if path.is_dir() else path.suffix.lstrip(".") or "file",
                           "size_bytes": size, "files": n}
    if path.suffix == ".json" and path.is_file():
        try:
            data = json.loads(path.read_text())
            out["keys"] = sorted(data)[:40] if isinstance(data, dict) else None
            out["length"] = len(data) if isinstance(data, (list, dict)) else None
        except (OSError, json.JSONDecodeError) as e:
            out["error"] = f"unreadable JSON: {e}"
    elif path.suffix == ".csv" and path.is_file():
        with open(path) as f:
            out["rows"] = max(0, sum(1 for _ in f) - 1)
    return out


# ---------------------------------------------------------------------- inspect


def _manifest_view(man: Mapping[str, Any]) -> dict[str, Any]:
    keys = ("dataset", "stage", "item", "signature", "key", "code_version", "created", "wall_time_s", "peak_rss_mb",
            "host", "params", "upstream", "summary", "libraries")
    return {k: man.get(k) for k in keys}


def inspect_artifact(path: Path | str, index: ArtifactIndex | None = None) -> dict[str, Any]:
    """Everything about the artifact at or around ``path`` as a JSON-able dict.

    Keys: ``path`` (as asked), ``artifact`` (item folder, cache, dataset, stage,
    signature, item), ``manifest`` (key, upstream keys, parameters, code version,
    timing, summary, libraries), ``encoders`` (names, versions, parameters, and which
    artifact recorded them), ``zarr`` (list of :func:`zarr_info`), ``parquet`` (list of
    :func:`parquet_info`), ``files`` (list of :func:`file_info`), ``upstream``
    (:func:`upstream_tree`). When ``path`` is a Zarr store, an array in one, or a
    Parquet file, only that part of the item is described (manifest and upstream
    always are).
    """
    loc = locate(path)
    index = index or ArtifactIndex(loc.cache)
    man = json.loads((loc.item_dir / MANIFEST_NAME).read_text())
    key = man.get("key")
    zarrs, tables, files = [], [], []
    target = loc.target
    if target == loc.item_dir:
        for child in sorted(loc.item_dir.iterdir()):
            if child.name == MANIFEST_NAME or child.name.startswith("."):
                continue
            if _is_zarr(child):
                zarrs.append(zarr_info(child, manifest_key=key))
            elif child.suffix == ".parquet":
                tables.append(parquet_info(child, manifest_key=key))
            else:
                files.append(file_info(child))
    else:
        # the outermost Zarr node below the item folder is the store (array folders hold a zarr.json too)
        store = next((d for d in reversed([target, *target.parents]) if loc.item_dir in d.parents and _is_zarr(d)), None)
        if store is not None:
            only = None if store == target else str(target.relative_to(store))
            info = zarr_info(store, only=only, manifest_key=key)
            if only is not None and not info["arrays"]:
                raise NotAnArtifact(f"{path}: not an array of the Zarr store {store}")
            zarrs.append(info)
        elif target.suffix == ".parquet":
            tables.append(parquet_info(target, manifest_key=key))
        else:
            files.append(file_info(target))
    tree = upstream_tree(man, index, loc.item)
    return {
        "path": str(path),
        "artifact": {"item_dir": str(loc.item_dir), "cache": str(loc.cache), "dataset": loc.dataset, "stage": loc.stage,
                     "signature": loc.signature, "item": loc.item},
        "manifest": _manifest_view(man),
        "encoders": _encoders(man, tree, index),
        "zarr": zarrs,
        "parquet": tables,
        "files": files,
        "upstream": tree,
    }


# ------------------------------------------------------------------ ls and gc


@dataclass
class SignatureEntry:
    """One stage signature folder ``cache/<dataset>/<stage>/<signature>``.

    items: item folders with a manifest; incomplete: item folders without one;
    size_bytes: everything under the folder; created: the newest item manifest's
    ``created`` time; status: ``current`` | ``stale`` | ``unknown``; note: why unknown.
    """

    dataset: str
    stage: str
    signature: str
    path: str
    items: list[str]
    incomplete: list[str]
    size_bytes: int
    created: str | None
    status: str
    note: str = ""


@dataclass
class Leftover:
    """A hidden folder of an interrupted publish (``.tmp-*`` or ``.old-*``)."""

    path: str
    size_bytes: int
    age_s: float


@dataclass
class CacheListing:
    cache: str
    entries: list[SignatureEntry] = field(default_factory=list)
    leftovers: list[Leftover] = field(default_factory=list)
    notes: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def leftover_age_s(path: Path, now: float) -> float:
    """Seconds since anything in the leftover ``path`` (a folder or file) last changed:
    a publish still running keeps writing into its ``.tmp-*`` folder."""
    newest = max((os.lstat(os.path.join(r, f)).st_mtime for r, _, fs in os.walk(path) for f in fs),
                 default=path.lstat().st_mtime)
    return now - max(newest, path.lstat().st_mtime)


def current_signatures(run_plan, dataset: str) -> dict[str, str]:
    """stage -> signature of ``dataset`` in ``run_plan`` (a :class:`pipeline.workflow.plan.RunPlan`);
    raises when no plan can be built (no dataset manifest, BOP data not found...)."""
    return {name: sp.signature for name, sp in run_plan[dataset].stages.items()}


def _newest(item_dirs: list[Path]) -> str | None:
    stamps = []
    for d in item_dirs:
        try:
            stamps.append(json.loads((d / MANIFEST_NAME).read_text()).get("created") or "")
        except (OSError, json.JSONDecodeError):
            continue
    stamps = [s for s in stamps if s]
    return max(stamps) if stamps else None


def list_artifacts(cache: Path, run, datasets: list[str] | None = None) -> CacheListing:
    """Every signature folder of the cache (or of ``datasets``), marked against the plan
    of ``run`` (a RunManifest): ``current`` when the plan's signature for that stage is
    this folder, ``stale`` when not, ``unknown`` when the dataset has no plan here or the
    stage is not one the plan knows (those are never garbage-collected)."""
    from pipeline.workflow.plan import STAGES, RunPlan

    cache = Path(cache)
    run_plan = RunPlan(run, cache=cache)
    listing = CacheListing(cache=str(cache))
    if not cache.is_dir():
        listing.notes["*"] = f"{cache}: no cache folder"
        return listing
    names = sorted(d.name for d in cache.iterdir() if d.is_dir() and not d.name.startswith("."))
    if datasets:
        missing = [d for d in datasets if d not in names]
        for d in missing:
            listing.notes[d] = f"{cache / d}: no artifacts of dataset '{d}' in this cache"
        names = [d for d in names if d in datasets]
    now = time.time()
    for ds in names:
        try:
            current = current_signatures(run_plan, ds)
        except Exception as e:  # no manifest for it, BOP data missing, ...: we cannot tell
            current = None
            listing.notes[ds] = f"no plan for dataset '{ds}' ({type(e).__name__}: {e}); its artifacts are left alone"
        stage_dirs = [p for p in (cache / ds).iterdir() if p.is_dir() and not p.name.startswith(".")]
        order = {name: i for i, name in enumerate(STAGES)}
        for stage_dir in sorted(stage_dirs, key=lambda p: (order.get(p.name, len(order)), p.name)):
            for sig_dir in sorted(p for p in stage_dir.iterdir() if p.is_dir() and not p.name.startswith(".")):
                children = [c for c in sorted(sig_dir.iterdir()) if c.is_dir()]
                items = [c for c in children if not c.name.startswith(".") and (c / MANIFEST_NAME).is_file()]
                incomplete = [c.name for c in children if not c.name.startswith(".") and not (c / MANIFEST_NAME).is_file()]
                for c in children:
                    if c.name.startswith(LEFTOVER_PREFIXES):
                        listing.leftovers.append(Leftover(str(c), tree_size(c)[0], leftover_age_s(c, now)))
                note = ""
                if current is None:
                    status = "unknown"
                elif stage_dir.name not in STAGES or stage_dir.name not in current:
                    status, note = "unknown", f"'{stage_dir.name}' is not a stage of the plan"
                else:
                    status = "current" if current[stage_dir.name] == sig_dir.name else "stale"
                listing.entries.append(SignatureEntry(
                    dataset=ds, stage=stage_dir.name, signature=sig_dir.name, path=str(sig_dir),
                    items=[c.name for c in items], incomplete=incomplete, size_bytes=tree_size(sig_dir)[0],
                    created=_newest(items), status=status, note=note))
    return listing


@dataclass
class Removal:
    path: str
    size_bytes: int
    reason: str


def garbage(listing: CacheListing, tmp_min_age_s: float = 3600.0) -> list[Removal]:
    """What :func:`collect_garbage` would remove: the stale signature folders, and the
    leftover ``.tmp-*``/``.old-*`` folders older than ``tmp_min_age_s`` (a younger one may
    belong to a publish running right now) that are not inside a stale folder already."""
    out = [Removal(e.path, e.size_bytes, "stale") for e in listing.entries if e.status == "stale"]
    stale = {e.path for e in listing.entries if e.status == "stale"}
    for lo in listing.leftovers:
        if lo.age_s >= tmp_min_age_s and str(Path(lo.path).parent) not in stale:
            out.append(Removal(lo.path, lo.size_bytes, "leftover of an interrupted publish"))
    return out


def _check_removable(path: Path, cache: Path, current: set[str]) -> None:
    """Refuse anything but a signature folder or a leftover folder under ``cache``."""
    if path.is_symlink():
        raise ValueError(f"{path}: a symbolic link, not removed")
    real = path.resolve()
    root = cache.resolve()
    try:
        parts = real.relative_to(root).parts
    except ValueError:
        raise ValueError(f"{path}: outside the cache root {root}, not removed") from None
    if any(p.startswith(".") for p in parts[:3]):
        raise ValueError(f"{path}: not a signature folder of the cache, not removed")
    if len(parts) == 4 and parts[3].startswith(LEFTOVER_PREFIXES):
        return
    if len(parts) != 3:
        raise ValueError(f"{path}: not <cache>/<dataset>/<stage>/<signature>, not removed")
    if str(real) in current:
        raise ValueError(f"{path}: an artifact of the current plan, not removed")


def collect_garbage(listing: CacheListing, removals: list[Removal]) -> int:
    """Remove ``removals`` (from :func:`garbage` on ``listing``); returns the bytes freed.

    Every path is checked first: it must be a signature folder
    (``<cache>/<dataset>/<stage>/<signature>``) or a leftover folder in one, under the
    cache root, not a symlink and not a folder of the current plan; otherwise nothing
    is removed and ValueError names the path.
    """
    cache = Path(listing.cache)
    current = {str(Path(e.path).resolve()) for e in listing.entries if e.status != "stale"}
    for r in removals:
        _check_removable(Path(r.path), cache, current)
    freed = 0
    for r in removals:
        if Path(r.path).exists():
            shutil.rmtree(r.path)
            freed += r.size_bytes
    return freed


def human_bytes(n: int | float | None) -> str:
    """1536 -> '1.5 KiB'."""
    if n is None:
        return "-"
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"
