"""Issue 28, weights: no bad download is trusted, and a present file that is not a
checkpoint is said in one line.

Each test makes the loopback server of tests/test_weights_fetch.py misbehave (a body cut
short, no Content-Length, a web page as the weights, a file that changes between an
interrupted and a resumed transfer, no answer, a redirect loop), or breaks the weights
folder, runs the real command (`freeze weights fetch`, `freeze encoders`, the loaders),
and checks the exit code, the one line, and that nothing was published: no final file,
no recorded digest."""

from __future__ import annotations

import errno
import io
import json
import os
import pickle
import subprocess
import zipfile
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from test_weights_fetch import (GEDI_MEMBER, Loopback, _manifest, _no_proxy, _official_manifest,  # noqa: F401
                                _sha, _torch_bytes, gedi_zip, server, tiny_arch, tiny_dinov2)

from pipeline.common import config as cfg
from pipeline.commands.cli import app
from pipeline.common.config import WeightDownload
from pipeline.method.encoders import dinov2 as d2
from pipeline.method.encoders.gedi import load_gedi_net
from pipeline.method.encoders.registry import build_encoder
from pipeline.formats.weights import NotAWeightsFile, WeightsFetchError, fetch_download, part_path, sidecar_path
from pipeline.formats.weights import fetch as fetch_mod
from pipeline.formats.weights.fetch import part_meta_path

runner = CliRunner()
HTML = b"<!DOCTYPE html><html><head><title>Sign in</title></head><body>no</body></html>"
FINAL = "dinov2_vitt14_pretrain.pth"


def _fetch(monkeypatch, manifests: Path, wdir: Path, *args: str):
    """`freeze weights fetch ARGS` with the test manifests; returns the result."""
    monkeypatch.setattr(cfg, "MANIFEST_DIR", manifests)
    return runner.invoke(app, ["weights", "fetch", "--weights-dir", str(wdir), "--no-progress", *args])


def _one_error(result) -> str:
    """The one `error:` line of a failed fetch (exit 1, no traceback)."""
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, result.output
    return errors[0]


def _nothing_published(final: Path, *, part: bool = False) -> None:
    """No final file, no recorded digest; a .part only where the transfer can resume."""
    assert not final.exists() and not sidecar_path(final).exists()
    assert part_path(final).exists() == part
    if not part:
        assert not part_meta_path(final).exists()


# ------------------------------------------------------------ truncated transfers


def test_a_body_shorter_than_its_content_length_is_kept_to_resume_not_published(tmp_path, server, tiny_dinov2,
                                                                                monkeypatch):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body)
    server.cut_after = len(body) // 3
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    assert f"interrupted after {len(body) // 3} of {len(body)} bytes" in line and "to resume" in line
    _nothing_published(wdir / FINAL, part=True)
    result = _fetch(monkeypatch, manifests, wdir, "dinov2-vitt14")  # the resume completes it
    assert result.exit_code == 0, result.output
    assert (wdir / FINAL).read_bytes() == body and not part_path(wdir / FINAL).exists()


def test_a_dropped_connection_without_content_length_is_refused(tmp_path, server, tiny_dinov2, monkeypatch):
    """No Content-Length: the cut looks like the end of the body. The zip's missing
    central directory tells it; nothing is published or recorded, the .part deleted."""
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _, url = _official_manifest(manifests, server, body)
    server.no_length = True
    server.cut_after = len(body) // 2
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    assert line.startswith(f"error: dinov2-vitt14: {url}: received a truncated or damaged zip archive "
                           f"({len(body) // 2} bytes")
    assert f"not a torch checkpoint for {FINAL}; the download was deleted and nothing was installed" in line
    _nothing_published(wdir / FINAL)
    result = _fetch(monkeypatch, manifests, wdir, "dinov2-vitt14")  # the whole body, still without a length
    assert result.exit_code == 0, result.output
    assert (wdir / FINAL).read_bytes() == body


@pytest.mark.parametrize("no_length", [False, True], ids=["content-length", "no-length"])
def test_a_size_other_than_the_manifests_exact_size_is_refused(tmp_path, server, tiny_dinov2, monkeypatch,
                                                               no_length):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body, exact_size=len(body) + 7)
    server.no_length = no_length
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    said = f"received {len(body)} bytes" if no_length else f"the server announces {len(body)} bytes"
    assert said in line and f"exact_size {len(body) + 7} for {FINAL}" in line
    _nothing_published(wdir / FINAL)


def test_a_truncated_safetensors_and_a_web_page_as_config_are_refused(tmp_path, server, tiny_arch, monkeypatch):
    from test_encoders_dinov2 import _tiny_hf

    _tiny_hf(seed=5).save_pretrained(tmp_path / "hf", safe_serialization=True)
    folder = d2.hf_dirname("vitt14")
    weights = (tmp_path / "hf" / "model.safetensors").read_bytes()
    entries = [{"url": server.serve(f"/{folder}/config.json", HTML), "file": f"{folder}/config.json", "source": "hf"},
               {"url": server.serve(f"/{folder}/model.safetensors", weights[:-100]),
                "file": f"{folder}/model.safetensors", "source": "hf"}]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _manifest(manifests, "dinov2-vitt14", "dinov2", {"model": "vitt14"}, entries)
    result = _fetch(monkeypatch, manifests, wdir, "--source", "hf", "dinov2-vitt14")
    assert result.exit_code == 1 and "Traceback" not in result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 2
    assert "received an HTML page (title 'Sign in'), not a JSON file for dinov2-vitt14/config.json" in errors[0]
    assert "received a truncated safetensors file" in errors[1] and "model.safetensors" in errors[1]
    for name in ("config.json", "model.safetensors"):
        _nothing_published(wdir / folder / name)


# -------------------------------------------------------------- a web page as the weights


def test_a_web_page_served_as_octet_stream_is_not_published(tmp_path, server, monkeypatch):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _, url = _official_manifest(manifests, server, HTML[:60])
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    assert line.startswith(f"error: dinov2-vitt14: {url}: received an HTML page (title 'Sign in'), not a torch "
                           f"checkpoint for {FINAL}; the download was deleted and nothing was installed")
    assert f"place it at {wdir / FINAL}" in line
    _nothing_published(wdir / FINAL)


def test_a_web_page_instead_of_the_gedi_zip_or_its_member_is_refused(tmp_path, server, monkeypatch):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    url = server.serve("/download?id=GEDI", HTML)
    _manifest(manifests, "gedi", "gedi", {}, [{"url": url, "member": GEDI_MEMBER, "file": "gedi/chkpt.tar"}])
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "gedi"))
    assert f"{url}: received an HTML page (title 'Sign in'), not a zip archive for gedi/chkpt.tar" in line
    _nothing_published(wdir / "gedi" / "chkpt.tar")
    buf = io.BytesIO()  # a real zip whose member is a web page
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(GEDI_MEMBER, HTML)
    server.files["/download?id=GEDI"] = buf.getvalue()
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "gedi"))
    assert f"member {GEDI_MEMBER} of {url}: received an HTML page (title 'Sign in'), not a torch checkpoint" in line
    _nothing_published(wdir / "gedi" / "chkpt.tar")
    assert sorted(p.name for p in (wdir / "gedi").iterdir()) == []  # no hidden temporary left either


# --------------------------------------------------- a file that changed between transfers


@pytest.mark.parametrize("server_mode", ["honours-if-range", "ignores-if-range", "no-validators"])
def test_a_file_changed_on_the_server_is_never_spliced(tmp_path, server, monkeypatch, server_mode):
    """v1 is cut half-way; the server then serves v2. The resume sends If-Range with v1's
    ETag: the server answers 200 with v2 (or, ignoring If-Range, a 206 of v2 whose ETag
    differs; or, with no ETag recorded, nothing is resumed): the file is v2, whole."""
    v1 = _torch_bytes({"w": torch.zeros(4000)})
    v2 = _torch_bytes({"w": torch.ones(4000)})
    assert len(v1) == len(v2) and v1 != v2
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _, url = _official_manifest(manifests, server, v1)
    server.validators = server_mode != "no-validators"
    server.if_range = server_mode == "honours-if-range"
    server.cut_after = len(v1) // 2
    _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    final = wdir / FINAL
    assert part_path(final).read_bytes() == v1[: len(v1) // 2]
    recorded = json.loads(part_meta_path(final).read_text())
    assert recorded["url"] == url and recorded["length"] == len(v1)
    server.files["/dinov2/dinov2_vitt14/dinov2_vitt14_pretrain.pth"] = v2  # the upstream file changes
    result = _fetch(monkeypatch, manifests, wdir, "dinov2-vitt14")
    assert result.exit_code == 0, result.output
    assert final.read_bytes() == v2 and sidecar_path(final).read_text().split()[0] == _sha(v2)
    assert not part_path(final).exists() and not part_meta_path(final).exists()
    if server_mode == "no-validators":
        assert server.requests[-1][1] is None and "starting again from zero" in result.output
    else:
        assert server.if_ranges[1] == f'"{_sha(v1)[:16]}"'  # the resume named the file it continues
        assert "starting again from zero" in result.output


# ------------------------------------------------------------- a bad file already present


def test_freeze_encoders_says_a_present_web_page_is_not_a_checkpoint(tmp_path):
    wdir = tmp_path / "weights"
    wdir.mkdir()
    bad = wdir / "dinov2_vits14_pretrain.pth"
    bad.write_bytes(HTML)
    (wdir / "gedi").mkdir()
    (wdir / "gedi" / "chkpt.tar").write_bytes(HTML[:30])
    result = runner.invoke(app, ["encoders", "--weights-dir", str(wdir)])
    assert result.exit_code == 0 and "Traceback" not in result.output
    lines = [line for line in result.output.splitlines() if line.startswith("dinov2-vits14: ")]
    assert lines == [f"dinov2-vits14: dinov2: {bad} is an HTML page (title 'Sign in'), not a torch checkpoint: a "
                     "download that went wrong (a web page instead of the file, or a transfer cut short)? Delete it "
                     "(and dinov2_vits14_pretrain.pth.sha256 if present) and fetch it again with `freeze weights "
                     "fetch dinov2-vits14`"]
    gedi = [line for line in result.output.splitlines() if line.startswith("gedi: ")]
    assert gedi and "chkpt.tar is an HTML page, not a torch checkpoint" in gedi[0]
    data = json.loads(runner.invoke(app, ["encoders", "--json", "--weights-dir", str(wdir)]).stdout)
    row = next(r for r in data["manifests"] if r["manifest"] == "dinov2-vits14")
    assert row["ok"] is False and row["weights"] == f"NOT A CHECKPOINT: {bad}"


def test_fetch_and_list_refuse_a_present_web_page_and_record_nothing(tmp_path, server, monkeypatch):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, b"never fetched")
    wdir.mkdir()
    (wdir / FINAL).write_bytes(HTML)
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    assert f"{wdir / FINAL} is an HTML page (title 'Sign in'), not a torch checkpoint" in line
    assert "its digest is not recorded" in line
    assert not sidecar_path(wdir / FINAL).exists() and server.requests == []
    listed = runner.invoke(app, ["weights", "list", "--json", "--weights-dir", str(wdir)])
    row = next(r for r in json.loads(listed.stdout)["downloads"] if r["file"] == FINAL)
    assert row["status"] == "invalid" and row["note"].startswith("an HTML page")


def test_the_loaders_refuse_a_bad_file_in_one_line_without_torchs_advice(tmp_path, tiny_arch, tiny_dinov2):
    """DINOv2 (official file, Hugging Face folder) and GeDi: a web page, a truncated zip,
    a truncated legacy pickle and a pickle of an object torch will not load are each a
    NotAWeightsFile (a WeightsNotFound: one line in every command) naming the file,
    raised when the encoder is built (before any stage work), never advising
    weights_only=False."""
    body = tiny_dinov2[1]
    legacy = io.BytesIO()
    torch.save({"w": torch.zeros(1000)}, legacy, _use_new_zipfile_serialization=False)
    cases = {"html": HTML, "truncated-zip": body[: len(body) // 2], "truncated-pickle": legacy.getvalue()[:300],
             "code": pickle.dumps(subprocess.Popen, protocol=2)}
    for case, data in cases.items():
        path = tmp_path / case / FINAL
        path.parent.mkdir()
        path.write_bytes(data)
        builds = {"dinov2 build": lambda: build_encoder({"name": "dinov2", "params": {"model": "vitt14"}},
                                                        weights_dir=path.parent),
                  "dinov2 load": lambda: d2.load_official(path, "vitt14"),
                  "gedi load": lambda: load_gedi_net(path),
                  "gedi build": lambda: build_encoder({"name": "gedi", "params": {"weights": str(path)}})}
        if data[:1] == b"\x80":
            # A pickle's damage shows only when it is read: DINOv2 reads it at the first
            # encode (one line then), not when built (ViT-g's 4.4 GB would cost a minute).
            assert build_encoder({"name": "dinov2", "params": {"model": "vitt14"}}, weights_dir=path.parent)
            del builds["dinov2 build"]
        for what, build in builds.items():
            with pytest.raises(NotAWeightsFile) as err:
                build()
            message = str(err.value)
            assert str(path) in message and "\n" not in message and "weights_only" not in message, (case, what)
            assert "freeze weights fetch" in message
        if case == "code":
            assert "objects other than tensors" in message
    hf = tmp_path / "hf" / d2.hf_dirname("vitt14")
    hf.mkdir(parents=True)
    (hf / "config.json").write_bytes(HTML)
    (hf / "model.safetensors").write_bytes(b"\x08" + b"\x00" * 7 + b"{}")
    with pytest.raises(NotAWeightsFile, match=r"config.json is an HTML page .*`freeze weights fetch dinov2-vitt14`"):
        build_encoder({"name": "dinov2", "params": {"model": "vitt14"}}, weights_dir=tmp_path / "hf")


# ------------------------------------------------------------------- the weights folder


def test_a_weights_folder_that_is_a_file_is_one_line(tmp_path, server, tiny_dinov2, monkeypatch):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, tiny_dinov2[1])
    wdir.write_text("not a folder")
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    assert f"{wdir} is not a folder, so {wdir / FINAL} cannot be written there" in line
    assert wdir.read_text() == "not a folder" and server.requests == []


class _FullDisk:
    """A file object whose writes fail with ENOSPC once ``room`` bytes are written."""

    def __init__(self, f, room: int) -> None:
        self._f, self._room = f, room

    def write(self, data) -> int:
        if len(data) > self._room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self._room -= len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._f.close()


def test_a_full_disk_keeps_the_part_and_says_where(tmp_path, server, tiny_dinov2, monkeypatch):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body)
    monkeypatch.setattr(fetch_mod, "CHUNK", 4096)
    monkeypatch.setattr(fetch_mod, "open", lambda *a, **k: _FullDisk(open(*a, **k), 8192), raising=False)
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    part = part_path(wdir / FINAL)
    assert line == (f"error: dinov2-vitt14: {part}: cannot write the weights (no space left on the device); nothing "
                    f"was installed, the 8192 bytes received are kept in {part}: free space (or fix the folder) and "
                    f"run `freeze weights fetch dinov2-vitt14` again to resume, or delete it (manifest "
                    f"{manifests / 'encoders' / 'dinov2-vitt14.yaml'})")
    _nothing_published(wdir / FINAL, part=True)
    monkeypatch.undo()  # space freed: the same command resumes and completes
    result = _fetch(monkeypatch, manifests, wdir, "dinov2-vitt14")
    assert result.exit_code == 0, result.output
    assert (wdir / FINAL).read_bytes() == body and server.requests[-1][1] == "bytes=8192-"


def test_a_read_only_weights_folder_is_one_line(tmp_path, server, tiny_dinov2, monkeypatch):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, tiny_dinov2[1])
    wdir.mkdir()

    def read_only(path, *args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(fetch_mod, "open", read_only, raising=False)
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
    assert f"{part_path(wdir / FINAL)}: cannot write the weights (read-only file system); nothing was installed, " \
           "nothing was left behind" in line
    assert list(wdir.iterdir()) == []


def _mount(target: Path, options: str) -> bool:
    """Mount a tmpfs at ``target`` (root with CAP_SYS_ADMIN only); whether it worked."""
    target.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(target)], capture_output=True)
    return done.returncode == 0


@pytest.mark.parametrize("options", ["size=64k", "ro"], ids=["full", "read-only"])
def test_a_real_full_or_read_only_mount(tmp_path, server, monkeypatch, options):
    """The same on a real tmpfs, where the machine allows mounting (root in CI may not)."""
    body = os.urandom(300_000)
    body = _torch_bytes({"w": torch.frombuffer(bytearray(body), dtype=torch.uint8)})
    manifests, wdir = tmp_path / "manifests", tmp_path / "mnt"
    _official_manifest(manifests, server, body)
    if not _mount(wdir, options):
        pytest.skip("cannot mount a tmpfs here")
    try:
        line = _one_error(_fetch(monkeypatch, manifests, wdir, "dinov2-vitt14"))
        if options == "ro":
            assert "(read-only file system); nothing was installed, nothing was left behind" in line
            assert list(wdir.iterdir()) == []
        else:
            part = part_path(wdir / FINAL)
            assert f"{part}: cannot write the weights (no space left on the device)" in line
            assert f"bytes received are kept in {part}" in line
            _nothing_published(wdir / FINAL, part=True)
    finally:
        subprocess.run(["umount", str(wdir)], check=False)


# ------------------------------------------------------------------- misleading messages


def test_a_server_that_never_answers_is_not_called_no_network(tmp_path, server, monkeypatch):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, b"unused")
    server.hang = True
    line = _one_error(_fetch(monkeypatch, manifests, wdir, "--timeout", "0.5", "dinov2-vitt14"))
    assert "127.0.0.1" in line and "did not answer within 0.5 s" in line and "--timeout" in line
    assert "no network access" not in line
    _nothing_published(wdir / FINAL)


def test_a_redirect_loop_is_one_line(tmp_path, server, monkeypatch):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    url = server.url("/loop")
    server.redirects["/loop"] = "/loop"
    _manifest(manifests, "dinov2-vitt14", "dinov2", {"model": "vitt14"}, [{"url": url, "file": FINAL}])
    result = _fetch(monkeypatch, manifests, wdir, "dinov2-vitt14")
    line = _one_error(result)
    assert line.startswith(f"error: dinov2-vitt14: {url}: the server's redirects loop or go on (HTTP 302")
    assert len(result.output.strip().splitlines()) == 3  # "fetching ...", the error, the count of failures
    _nothing_published(wdir / FINAL)


def test_file_urls_are_refused_by_the_manifest_and_the_fetch(tmp_path, monkeypatch):
    secret = tmp_path / "secret.pth"
    secret.write_bytes(b"PK\x05\x06" + b"\x00" * 18)
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _manifest(manifests, "dinov2-vitt14", "dinov2", {"model": "vitt14"}, [{"url": secret.as_uri(), "file": FINAL}])
    result = _fetch(monkeypatch, manifests, wdir, "dinov2-vitt14")
    line = _one_error(result)
    assert len(result.output.strip().splitlines()) == 1
    assert str(manifests / "encoders" / "dinov2-vitt14.yaml") in line and "field 'download.0.url'" in line
    assert "must be an http(s) URL with a host" in line and "got 'file://" in line
    assert not wdir.exists()
    download = WeightDownload.model_construct(url=secret.as_uri(), file=FINAL, member=None, sha256=None,
                                              source="official", size=None, exact_size=None)
    with pytest.raises(WeightsFetchError, match=r"is not an http\(s\) URL with a host") as err:
        fetch_download(download, wdir, manifest="m.yaml")
    assert "\n" not in str(err.value) and not wdir.exists()


def test_freeze_estimate_stops_at_once_on_a_web_page_as_the_dinov2_weights(tmp_path, monkeypatch):
    """The encoders are built with the inputs' checks, before any stage: a web page as
    dinov2_vits14_pretrain.pth is one line naming it, exit 1, no cache written."""
    from test_estimate import _cli_args

    wdir = tmp_path / "weights"
    wdir.mkdir()
    (wdir / "dinov2_vits14_pretrain.pth").write_bytes(HTML)
    monkeypatch.setenv("FREEZE_CACHE", str(tmp_path / "cache"))
    frame = _estimate_frame(tmp_path / "frame")
    result = runner.invoke(app, _cli_args(frame, tmp_path / "out", "--visual", "dinov2-vits14", "-c",
                                          f"weights_dir={wdir}"))
    assert result.exit_code == 1 and "Traceback" not in result.output, result.output
    [line] = [ln for ln in result.output.splitlines() if ln.startswith("error:")]
    assert f"{wdir / 'dinov2_vits14_pretrain.pth'} is an HTML page (title 'Sign in'), not a torch checkpoint" in line
    assert "weights_only" not in result.output
    assert not (tmp_path / "cache").exists() and not (tmp_path / "out").exists()


def _estimate_frame(d: Path) -> dict:
    """A minimal frame for `freeze estimate`'s input checks: a cube model, a flat depth,
    a mask (the command stops at the encoders, before any pose work)."""
    import numpy as np
    import trimesh

    from pipeline.formats.bop.dataset import save_depth_png, save_mask_png, save_rgb
    from pipeline.formats.bop.ply import write_ply

    d.mkdir(parents=True)
    cube = trimesh.creation.box(extents=[50, 50, 50])
    write_ply(d / "model.ply", np.asarray(cube.vertices), np.asarray(cube.faces),
              normals=np.asarray(cube.vertex_normals))
    save_rgb(d / "rgb.png", np.full((48, 64, 3), 128, np.uint8))
    save_depth_png(d / "depth.png", np.full((48, 64), 600.0), 0.1)
    mask = np.zeros((48, 64), bool)
    mask[10:30, 20:40] = True
    save_mask_png(d / "mask.png", mask)
    (d / "camera.json").write_text(json.dumps({"cam_K": [60.0, 0, 32, 0, 60.0, 24, 0, 0, 1], "depth_scale": 0.1}))
    return {"model": d / "model.ply", "rgb": d / "rgb.png", "depth": d / "depth.png", "camera": d / "camera.json",
            "mask": d / "mask.png"}
