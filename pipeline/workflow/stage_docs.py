"""Documentation generated from the stage declarations (:mod:`pipeline.workflow.stage_graph`).

A generated block of a doc file sits between two marker lines::

    <!-- stage-table:start -->
    ...
    <!-- stage-table:end -->

:data:`BLOCKS` lists each block: its file, its marker name and the function rendering
it. ``scripts/update_docs.py`` rewrites every block from the declarations, and
``tests/test_stage_docs.py`` fails when one differs from what they give. The blocks: the
stage table of ``docs/architecture.md`` and the artifact list of ``docs/artifacts.md``
(from :mod:`pipeline.workflow.artifact_schema`); another is one more render function and
one more :class:`Block`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

from pipeline.workflow.stage_graph import STAGES, StageSpec

PROJECT_ROOT = Path(__file__).resolve().parents[2]

SHOWN = {"{results_csv}": "<method>_<dataset>-<split>.csv", "{dataset}": "<dataset>/"}
"""The placeholders of :attr:`StageSpec.writes` as file names in the docs."""
WRITTEN = {"{results_csv}": f"`{SHOWN['{results_csv}']}` (the BOP results CSV)",
           "{dataset}": "the BOP dataset and its prior"}
"""How the placeholders read in the stage table's writes column."""

EXTERNAL_NOTES = {"source": "the real sample of a semi-real or real-sample dataset"}
"""A few words on the external inputs a reader may not guess (``dataset`` and ``prior``
are the docs' own words)."""


class MarkerError(ValueError):
    """A doc file lacks a block's markers, or has them twice or in the wrong order."""


@dataclass(frozen=True)
class Block:
    """One generated block: the doc file (relative to the project root), the name of its
    markers, and the function rendering its text (without the marker lines)."""

    path: str
    name: str
    render: Callable[[], str]


# ------------------------------------------------------------------ stage table

def job_per(stage: str | StageSpec, kind: str) -> str:
    """What one job of ``stage`` for items of ``kind`` covers: ``object``, ``scene``, or
    ``dataset (item `all`)``, with the declaration's note on that kind and whether the
    stage runs for the datasets it builds only (synthetic, semi-real, real samples)."""
    s = STAGES[stage] if isinstance(stage, str) else stage
    if kind in ("obj", "scene"):
        word = {"obj": "object", "scene": "scene"}[kind]
        return f"{word} ({s.notes[kind]})" if kind in s.notes else word
    note = (f": {s.notes[kind]}" if kind in s.notes else "") + (
        "; synthetic, semi-real and real-sample datasets only" if s.synthetic_only else "")
    return f"dataset (item `{kind}`{note})"


def _read(upstream: str, reader: StageSpec, specs: Mapping[str, StageSpec]) -> str:
    """An upstream in the reads column: named by itself, with the item kind read when it
    has several and the reader is another stage (``refine (`all`)``); an external input
    with its note, if it has one."""
    up = specs.get(upstream)
    if up is not None and len(up.items) > 1 and upstream != reader.name:
        return f"{upstream} (`{up.items[-1]}`)"
    if upstream in EXTERNAL_NOTES:
        return f"`{upstream}` ({EXTERNAL_NOTES[upstream]})"
    return upstream


def _algorithms(s: StageSpec, kind: str) -> str:
    """``pkg.mod.first`` (then ``second``, ``third``; role: ``pkg.other.fourth``): the
    functions after the first by their short name when they sit in its module."""
    calls: list[str | tuple[str, str]] = [s.algorithm] if kind == s.items[0] else []
    calls += list(s.more_algorithms.get(kind, ()))
    if not calls:
        return "-"
    first, rest = calls[0] if isinstance(calls[0], str) else calls[0][1], calls[1:]
    module = first.rpartition(".")[0]

    def short(name: str) -> str:
        return f"`{name.rpartition('.')[2]}`" if name.rpartition(".")[0] == module else f"`{name}`"

    then = [short(c) for c in rest if isinstance(c, str)]
    parts = ([f"then {', '.join(then)}"] if then else []) + [f"{role}: `{c}`" for role, c in
                                                             (r for r in rest if not isinstance(r, str))]
    return f"`{first}`" + (f" ({'; '.join(parts)})" if parts else "")


def stage_table(specs: Mapping[str, StageSpec] = STAGES) -> str:
    """The stage table of ``docs/architecture.md``: one row per stage and item kind."""
    rows = ["| stage | job per | reads | writes | algorithm (one hop from the stage module) |",
            "|---|---|---|---|---|"]
    for name, s in specs.items():
        for kind in s.items:
            reads = ", ".join(_read(u, s, specs) for u in s.reads_for(kind)) or "-"
            writes = ", ".join(WRITTEN.get(w, f"[`{w}`](artifacts.md#{_anchor(name, kind, w)})")
                               for w in s.writes_for(kind)) or "-"
            rows.append(f"| `{name}` | {job_per(s, kind)} | {reads} | {writes} | {_algorithms(s, kind)} |")
    return "\n".join(rows) + "\n"


# ------------------------------------------------------------------ artifact list

def _anchor(stage: str, kind: str, file: str) -> str:
    """The anchor of an artifact's heading in docs/artifacts.md (GitHub's rule: lower
    case, spaces to dashes, punctuation but dashes and underscores dropped)."""
    import re

    heading = f"{stage} {_item_words(kind)} {file}"
    return re.sub(r"[^a-z0-9 _-]", "", heading.lower()).replace(" ", "-")


def _item_words(kind: str) -> str:
    return {"obj": "obj_NNNNNN", "scene": "scene_NNNNNN", "all": "all", "dataset": "dataset"}[kind]


def artifact_list(specs: Mapping[str, StageSpec] = STAGES) -> str:
    """Every artifact of every stage, per item kind: its file, kind, what it holds, and
    its columns (tables) or arrays (dtype and shape), from the declarations
    (:mod:`pipeline.workflow.artifact_schema`)."""
    out: list[str] = []
    for name, s in specs.items():
        for kind in s.items:
            for a in s.artifacts_for(kind):
                out += [f"### {name} {_item_words(kind)} `{SHOWN.get(a.file, a.file)}`", "",
                        f"`{a.name}` ({a.kind}): {a.doc}.", ""]
                if a.kind == "table":
                    out += ["| column | dtype | meaning |", "|---|---|---|"]
                    out += [f"| `{f.name}` | {f.dtype} | {f.doc} |" for f in a.fields]
                    out.append("")
                elif a.kind == "arrays":
                    out += ["| array | dtype | shape | meaning |", "|---|---|---|---|"]
                    out += [f"| `{f.name}` | {f.dtype} | {f.shape} | {f.doc} |" for f in a.fields]
                    out.append("")
    return "\n".join(out)


BLOCKS: tuple[Block, ...] = (
    Block("docs/architecture.md", "stage-table", stage_table),
    Block("docs/artifacts.md", "artifact-list", artifact_list),
)
"""Every generated block of the docs."""


# ------------------------------------------------------------- blocks in files

def markers(name: str) -> tuple[str, str]:
    """The start and end marker lines of block ``name``."""
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def _span(text: str, name: str, where: str) -> tuple[int, int]:
    """(index just after the start marker's line, index of the end marker's line) in ``text``."""
    start, end = markers(name)
    lines = text.splitlines(keepends=True)
    starts = [i for i, line in enumerate(lines) if line.strip() == start]
    ends = [i for i, line in enumerate(lines) if line.strip() == end]
    if len(starts) != 1 or len(ends) != 1 or ends[0] < starts[0]:
        found = f"{len(starts)} '{start}' and {len(ends)} '{end}' line(s)" + (
            ", the end first" if len(starts) == len(ends) == 1 else "")
        raise MarkerError(f"{where}: the generated block '{name}' needs one line '{start}' and, after it, one line "
                          f"'{end}'; found {found}")
    offsets = [0]
    for line in lines:
        offsets.append(offsets[-1] + len(line))
    return offsets[starts[0] + 1], offsets[ends[0]]


def between(text: str, name: str, where: str = "text") -> str:
    """The text between the marker lines of block ``name``."""
    a, b = _span(text, name, where)
    return text[a:b]


def replace_between(text: str, name: str, body: str, where: str = "text") -> str:
    """``text`` with the lines between the markers of block ``name`` replaced by ``body``
    (a blank line before and after it, so that Markdown sees a block of its own)."""
    a, b = _span(text, name, where)
    return text[:a] + "\n" + body.rstrip("\n") + "\n\n" + text[b:]


def rendered(block: Block, root: Path = PROJECT_ROOT) -> tuple[str, str]:
    """(the file's text now, the file's text with ``block`` regenerated)."""
    path = Path(root) / block.path
    text = path.read_text(encoding="utf-8")
    return text, replace_between(text, block.name, block.render(), where=block.path)


def outdated(root: Path = PROJECT_ROOT, blocks: tuple[Block, ...] = BLOCKS) -> list[Block]:
    """The blocks whose text in their file differs from what the declarations give."""
    out = []
    for block in blocks:
        now, want = rendered(block, root)
        if now != want:
            out.append(block)
    return out


def update(root: Path = PROJECT_ROOT, blocks: tuple[Block, ...] = BLOCKS) -> list[str]:
    """Rewrite every outdated block in its file; returns the files changed."""
    changed = []
    for block in blocks:
        now, want = rendered(block, root)
        if now != want:
            (Path(root) / block.path).write_text(want, encoding="utf-8")
            changed.append(block.path)
    return changed
