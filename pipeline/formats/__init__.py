"""Layer 1: files whose format others define — BOP datasets, results and meshes (:mod:`.bop`) and
pretrained weight files, their catalogue and download (:mod:`.weights`). Imports only
:mod:`pipeline.common`.
"""
