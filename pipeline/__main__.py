"""``python -m pipeline``: the ``freeze`` command line (what the Snakefile's rules run)."""

from pipeline.commands.cli import main

main()
