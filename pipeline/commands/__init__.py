"""Layer 6: the ``freeze`` command line (:mod:`.cli` builds the app), one module per command group.
"""
