"""Layer 0: what every layer uses — the manifests' schemas (:mod:`.config`), the cache's storage
(:mod:`.store`, :mod:`.published_files`, :mod:`.file_hashes`), progress bars (:mod:`.progress`),
thread counts and work mappers (:mod:`.threads`, :mod:`.parallel`), and which encoders stand in for
the paper's (:mod:`.stand_in`). Imports nothing else of ``pipeline``.
"""
