"""The encoders' weight files: where they come from and fetching them (``freeze weights``).

Runs never download anything: the encoders load local files only
(:mod:`pipeline.encoders.registry`, ``resolve_weights_dir``). This package is the
explicit, separate step that puts those files in the weights folder, from the URLs of
the encoder manifests' ``download:`` entries:

- :mod:`pipeline.weights.catalog`: the manifests' entries, the selection of the files
  to fetch, and the state of each in the weights folder;
- :mod:`pipeline.weights.fetch`: one file's download (resumable, SHA-256 checked,
  published atomically) and its errors (:class:`WeightsFetchError`).

``docs/weights.md`` describes the commands and the folder's layout.
"""

from pipeline.weights.catalog import (SOURCES, Listed, Planned, UnknownWeights, entry_status, manifests_with_downloads,
                                      select)
from pipeline.weights.fetch import (FetchResult, WeightsFetchError, fetch_download, human_size, part_path,
                                    read_sidecar, sidecar_path, target_path)

__all__ = ["SOURCES", "FetchResult", "Listed", "Planned", "UnknownWeights", "WeightsFetchError", "entry_status",
           "fetch_download", "human_size", "manifests_with_downloads", "part_path", "read_sidecar", "select",
           "sidecar_path", "target_path"]
