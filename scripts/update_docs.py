#!/usr/bin/env python3
"""Rewrite the generated blocks of the docs from the stage declarations
(pipeline/workflow/stage_docs.py: the stage table of docs/architecture.md, between its
`<!-- stage-table:start -->` and `<!-- stage-table:end -->` lines, and the artifact list
of docs/artifacts.md, between `<!-- artifact-list:start -->` and `<!-- artifact-list:end -->`).

    .venv/bin/python scripts/update_docs.py            # rewrite what is out of date
    .venv/bin/python scripts/update_docs.py --check    # exit 1 if something is

--root DIR works on another copy of the project's docs (DIR/docs/...).
tests/test_stage_docs.py fails when a block is out of date.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.workflow.stage_docs import PROJECT_ROOT, MarkerError, outdated, update  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 when a block is out of date")
    ap.add_argument("--root", type=Path, default=PROJECT_ROOT, help="the folder holding docs/ (default: this project)")
    args = ap.parse_args(argv)
    try:
        if args.check:
            stale = outdated(args.root)
            for block in stale:
                print(f"{block.path}: block '{block.name}' is out of date; run .venv/bin/python scripts/update_docs.py")
            return 1 if stale else 0
        changed = update(args.root)
    except (MarkerError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print("\n".join(f"rewrote {p}" for p in changed) or "the generated blocks are up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
