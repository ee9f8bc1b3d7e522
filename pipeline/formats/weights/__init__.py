"""The encoders' weight files: where they come from and fetching them (``freeze weights``).

Runs never download anything: the encoders load local files only
(:mod:`pipeline.method.encoders.registry`, ``resolve_weights_dir``). This package is the
explicit, separate step that puts those files in the weights folder, from the URLs of
the encoder manifests' ``download:`` entries:

- :mod:`pipeline.formats.weights.catalog`: the manifests' entries, the selection of the files
  to fetch, and the state of each in the weights folder;
- :mod:`pipeline.formats.weights.fetch`: one file's download (resumable, SHA-256 checked,
  published atomically) and its errors (:class:`WeightsFetchError`);
- :mod:`pipeline.formats.weights.formats`: whether a file's first bytes are of the format its
  name says (a web page or a truncated zip is not a checkpoint), for the fetch, for
  ``freeze encoders`` and for the loaders (:class:`NotAWeightsFile`).

``docs/weights.md`` describes the commands and the folder's layout.
"""

from pipeline.formats.weights.catalog import (SOURCES, Listed, Planned, UnknownWeights, entry_status, manifests_with_downloads,
                                      select)
from pipeline.formats.weights.fetch import (TIMEOUT_S, FetchResult, WeightsFetchError, fetch_download, human_size,
                                    part_meta_path, part_path, read_sidecar, sidecar_path, target_path)
from pipeline.formats.weights.formats import NotAWeightsFile, check_weights_file, expected_format, sniff

__all__ = ["SOURCES", "TIMEOUT_S", "FetchResult", "Listed", "NotAWeightsFile", "Planned", "UnknownWeights",
           "WeightsFetchError", "check_weights_file", "entry_status", "expected_format", "fetch_download",
           "human_size", "manifests_with_downloads", "part_meta_path", "part_path", "read_sidecar", "select",
           "sidecar_path", "sniff", "target_path"]
