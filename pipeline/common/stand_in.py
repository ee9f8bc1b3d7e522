"""Which encoders of a run stand in for the paper's, said in one sentence.

The default encoders (``fpfh``, ``colortex``) need no weights: they stand in for the
paper's GeDi + DINOv2 ViT-g/14. The encoder manifests say so (``stand_in: true``; the
paper's own carry ``paper: true``), and this module turns those flags into the one line
that a run prints at its start (the Snakefile's ``onstart``, ``freeze run``, ``freeze
estimate``), that the HTML report shows and that ``pose.json`` records. The names come
from the manifests, never from strings spread over the commands.

Foundation layer: it reads manifests only (:mod:`pipeline.common.config`).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from pipeline.common import config as cfg

KINDS = ("geometric", "visual")
FETCH = "freeze weights fetch"
"""The command that fetches weights (``pipeline/commands/weights.py``)."""

Form = Literal["config", "freeze", "estimate"]
"""How a notice says to switch encoders: ``config`` as Snakemake's ``--config geometric=..
visual=..``; ``freeze`` as ``freeze run``'s repeated ``-c key=value``;
``estimate`` as ``freeze estimate``'s ``--geometric .. --visual ..``."""

# Readable names of the registry's encoder families (a manifest's `encoder` field).
_FAMILY = {"gedi": "GeDi", "dinov2": "DINOv2", "fpfh": "FPFH"}


def _manifest(name: str, kind: str, manifest_dir: Path) -> cfg.EncoderManifest | None:
    """The manifest a run's encoder ``name`` refers to; None when there is none (the
    plan reports that error itself)."""
    try:
        return cfg.load_encoder_manifest(cfg.encoder_manifest_name(name, kind), manifest_dir)
    except (cfg.ManifestError, OSError):
        return None


def display_name(man: cfg.EncoderManifest) -> str:
    """``GeDi``, ``DINOv2 ViT-g/14``: the family, and the ViT size when the manifest names
    one, spelled as DINOv2 spells it (ViT-S, -B, -L, and a lower-case g for giant)."""
    family = _FAMILY.get(man.encoder, man.encoder)
    m = re.fullmatch(r"vit([a-z])(\d+)", str(man.params.get("model") or ""))
    if not m:
        return family
    size = m.group(1) if m.group(1) == "g" else m.group(1).upper()
    return f"{family} ViT-{size}/{m.group(2)}"


def paper_configuration(manifest_dir: Path = cfg.MANIFEST_DIR) -> dict[str, tuple[str, str]]:
    """kind -> (manifest name, readable name) of the encoder manifests with ``paper: true``
    (the first by name when several of a kind are; a kind with none is left out)."""
    out: dict[str, tuple[str, str]] = {}
    for name in cfg.encoder_manifest_names(manifest_dir):
        try:
            man = cfg.load_encoder_manifest(name, manifest_dir)
        except cfg.ManifestError:
            continue
        if man.paper and man.kind not in out:
            out[man.kind] = (name, display_name(man))
    return {k: out[k] for k in KINDS if k in out}


def paper_fetch(manifest_dir: Path = cfg.MANIFEST_DIR) -> str | None:
    """``freeze weights fetch gedi dinov2-vitg14``: the command that fetches the paper's
    encoders' weights; None when no manifest is marked ``paper``."""
    paper = paper_configuration(manifest_dir)
    return f"{FETCH} {' '.join(paper[k][0] for k in KINDS if k in paper)}" if paper else None


def switch_text(names: dict[str, str], form: Form = "config") -> str:
    """The options that select the encoders ``names`` (kind -> manifest name)."""
    order = [k for k in KINDS if k in names]
    if form == "estimate":
        return " ".join(f"--{k} {names[k]}" for k in order)
    if form == "freeze":
        return " ".join(f"-c {k}={names[k]}" for k in order)
    return "--config " + " ".join(f"{k}={names[k]}" for k in order)


def paper_line(form: Form = "config", manifest_dir: Path = cfg.MANIFEST_DIR) -> str | None:
    """``the paper's configuration is gedi + dinov2-vitg14 (GeDi + DINOv2 ViT-g/14): ...``
    with the fetch command and the options; None when no manifest is marked ``paper``."""
    paper = paper_configuration(manifest_dir)
    if not paper:
        return None
    names = {k: paper[k][0] for k in KINDS if k in paper}
    return (f"the paper's configuration is {' + '.join(names.values())} "
            f"({' + '.join(paper[k][1] for k in names)}): fetch it with `{FETCH} {' '.join(names.values())}` and "
            f"run with {switch_text(names, form)}")


def _stand_in_clause(geometric: str, visual: str, form: Form, manifest_dir: Path,
                     subject: bool = True) -> str | None:
    """The heart of the notice, without its ``note:`` prefix; None when no encoder of the
    run is a stand-in. subject=False leaves out the stand-ins' names when both encoders
    are stand-ins (the caller has just named them)."""
    used = {"geometric": geometric, "visual": visual}
    mans = {k: _manifest(used[k], k, manifest_dir) for k in KINDS}
    stand_ins = [k for k in KINDS if mans[k] is not None and mans[k].stand_in]
    if not stand_ins:
        return None
    paper = paper_configuration(manifest_dir)
    one = len(stand_ins) == 1
    if subject or one:
        text = (f"{' + '.join(used[k] for k in stand_ins)} "
                f"{'is a weight-free stand-in' if one else 'are weight-free stand-ins'}")
    else:
        text = "weight-free stand-ins"
    replacing = {k: paper[k] for k in stand_ins if k in paper}
    if not replacing:
        return text + " for the paper's encoders"
    text += f" for the paper's {' + '.join(v[1] for v in replacing.values())}"
    names = {k: v[0] for k, v in replacing.items()}
    return (text + f"; fetch {'it' if len(names) == 1 else 'those'} with `{FETCH} {' '.join(names.values())}` "
            f"and run with {switch_text(names, form)}")


def stand_in_notice(geometric: str, visual: str, form: Form = "config",
                    manifest_dir: Path = cfg.MANIFEST_DIR) -> str | None:
    """The one line a run prints at its start when its geometric or visual encoder is a
    stand-in (``stand_in: true``) for the paper's, e.g. ``note: fpfh + colortex are
    weight-free stand-ins for the paper's GeDi + DINOv2 ViT-g/14; fetch those with
    `freeze weights fetch gedi dinov2-vitg14` and run with --config geometric=gedi
    visual=dinov2-vitg14``. None when neither is a stand-in (nothing is said then)."""
    clause = _stand_in_clause(geometric, visual, form, manifest_dir)
    return None if clause is None else f"note: {clause}"


def encoders_sentence(geometric: str, visual: str, form: Form = "config",
                      manifest_dir: Path = cfg.MANIFEST_DIR) -> str:
    """Which encoders ran, in one sentence (``pose.json``'s ``note``): ``fpfh + colortex:
    weight-free stand-ins for ...`` (the notice of :func:`stand_in_notice`), ``gedi +
    dinov2-vitg14: the paper's configuration``, or the names and the paper's
    configuration for any other pair."""
    used = f"{geometric} + {visual}"
    clause = _stand_in_clause(geometric, visual, form, manifest_dir, subject=False)
    if clause is not None:
        return f"{used}: {clause}"
    paper = paper_configuration(manifest_dir)
    names = {k: cfg.encoder_manifest_name(n, k) for k, n in (("geometric", geometric), ("visual", visual))}
    if paper and all(k in paper and paper[k][0] == names[k] for k in KINDS):
        return f"{used}: the paper's configuration ({' + '.join(paper[k][1] for k in KINDS)})"
    if paper:
        return f"{used}; the paper's configuration is {' + '.join(paper[k][1] for k in KINDS if k in paper)}"
    return used
