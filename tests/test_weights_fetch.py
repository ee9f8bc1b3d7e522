"""`freeze weights fetch` against a loopback HTTP server: self-made checkpoints in the
official layouts, downloaded, resumed, verified, refused, and loaded by the real loaders.

Nothing here needs the internet: the server listens on 127.0.0.1, the test manifests
point at it, and the real manifests are only read (their URLs checked as text)."""

from __future__ import annotations

import hashlib
import io
import json
import re
import socket
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import torch
import yaml
from typer.testing import CliRunner

transformers = pytest.importorskip("transformers")

from test_encoders_dinov2 import TINY, _tiny_hf, _to_official  # noqa: E402  (the tiny DINOv2 of its tests)

from pipeline.common import config as cfg  # noqa: E402
from pipeline.commands.cli import app  # noqa: E402
from pipeline.method.encoders import dinov2 as d2  # noqa: E402
from pipeline.method.encoders.gedi import STATE_KEY, GeDiNet  # noqa: E402
from pipeline.method.encoders.registry import build_encoder  # noqa: E402
from pipeline.formats.weights import (WeightsFetchError, fetch_download, part_path, read_sidecar, select,  # noqa: E402
                              sidecar_path)
from pipeline.formats.weights.fetch import part_meta_path  # noqa: E402

runner = CliRunner()
GEDI_MEMBER = "chkpts/3dmatch/chkpt.tar"


# --------------------------------------------------------------------- loopback server


class _Handler(BaseHTTPRequestHandler):
    """GET with single open-ended ranges (``bytes=N-``) and ``If-Range``, 404 for unknown
    paths, and the misbehaviours a test switches on in its :class:`Loopback`."""

    protocol_version = "HTTP/1.1"

    def log_message(self, *args) -> None:  # quiet
        pass

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        state: Loopback = self.server.state  # type: ignore[attr-defined]
        rng = self.headers.get("Range")
        state.requests.append((self.path, rng))
        state.if_ranges.append(self.headers.get("If-Range"))
        if state.hang:  # accept the connection, read the request, never answer
            state.released.wait(30)
            self.close_connection = True
            return
        if self.path in state.redirects:
            self.send_response(302)
            self.send_header("Location", state.url(state.redirects[self.path]))
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        body = state.files.get(self.path)
        if body is None:
            self.send_error(404, "Not Found")
            return
        etag = f'"{hashlib.sha256(body).hexdigest()[:16]}"'  # a strong ETag: changes with the bytes
        if_range = self.headers.get("If-Range")
        honour = rng and state.ranges and (not if_range or not state.if_range or if_range == etag)
        start = 0
        if honour:
            start = int(re.fullmatch(r"bytes=(\d+)-", rng).group(1))
            if start >= len(body):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(body)}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
        else:
            self.send_response(200)
        rest = body[start:]
        if state.validators:
            self.send_header("ETag", etag)
        self.send_header("Content-Type", state.content_type)
        if state.no_length:  # HTTP/1.1 without Content-Length: the body ends when the connection closes
            self.send_header("Connection", "close")
            self.close_connection = True
        else:
            self.send_header("Content-Length", str(len(rest)))
        self.end_headers()
        if state.cut_after is not None:  # promise the whole body, send part of it, hang up
            n, state.cut_after = state.cut_after, None
            self.wfile.write(rest[:n])
            self.wfile.flush()
            self.close_connection = True
            self.connection.shutdown(socket.SHUT_RDWR)
            return
        self.wfile.write(rest)


class Loopback:
    """An HTTP server on 127.0.0.1 (port 0) in a thread: ``files`` maps a path (with
    its query) to bytes; ``requests`` records (path, Range header) of every GET and
    ``if_ranges`` its If-Range header.

    Misbehaviours: ``cut_after`` (send that many bytes of the next body, then close),
    ``no_length`` (no Content-Length), ``content_type``, ``validators`` False (no ETag),
    ``if_range`` False (a resume gets the rest of whatever is served now), ``ranges``
    False (always 200), ``hang`` (never answer), ``redirects`` (path -> path, 302)."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.requests: list[tuple[str, str | None]] = []
        self.if_ranges: list[str | None] = []
        self.cut_after: int | None = None
        self.ranges = True
        self.if_range = True
        self.validators = True
        self.no_length = False
        self.hang = False
        self.released = threading.Event()
        self.redirects: dict[str, str] = {}
        self.content_type = "application/octet-stream"
        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
        self.httpd.state = self  # type: ignore[attr-defined]
        self.httpd.daemon_threads = True
        # a short poll interval: shutdown() waits for one poll, 0.5 s by default, per test
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
        self.thread.start()

    def serve(self, path: str, body: bytes) -> str:
        """Serve ``body`` at ``path``; returns its URL."""
        self.files[path] = body
        return self.url(path)

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}{path}"

    def close(self) -> None:
        self.released.set()
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture(autouse=True)
def _no_proxy(monkeypatch):
    """urllib honours the proxy variables: loopback requests must not go to a proxy."""
    for var in ("http_proxy", "https_proxy", "all_proxy", "HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY"):
        monkeypatch.delenv(var, raising=False)


@pytest.fixture
def server():
    srv = Loopback()
    yield srv
    srv.close()


# ---------------------------------------------------------------- checkpoints, manifests


@pytest.fixture
def tiny_arch(monkeypatch):
    """The tiny 'vitt14' architecture of tests/test_encoders_dinov2.py (32-d, 2 layers)."""
    monkeypatch.setitem(d2.MODEL_CONFIGS, "vitt14", dict(TINY))
    monkeypatch.setenv("TORCH_HOME", "/nonexistent-torch-home")  # the hub cache is never a fallback here
    return "vitt14"


def _torch_bytes(obj) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


@pytest.fixture(scope="module")
def tiny_dinov2():
    """(net, official .pth bytes) of a random tiny DINOv2."""
    net = _tiny_hf(seed=3)
    return net, _torch_bytes(_to_official(net))


@pytest.fixture(scope="module")
def gedi_zip() -> tuple[bytes, bytes]:
    """(chkpts.zip bytes, chkpt.tar bytes): a random-init GeDi network in the official
    checkpoint layout, stored as chkpts/3dmatch/chkpt.tar in a zip as GeDi publishes it."""
    torch.manual_seed(0)
    ckpt = _torch_bytes({"epoch": 1, STATE_KEY: GeDiNet().state_dict()})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("chkpts/", b"")
        zf.writestr(GEDI_MEMBER, ckpt)
        zf.writestr("chkpts/kitti/chkpt.tar", b"another checkpoint, not ours")
    return buf.getvalue(), ckpt


def _manifest(root: Path, name: str, encoder: str, params: dict, downloads: list[dict]) -> Path:
    """Write an encoder manifest ``root/encoders/<name>.yaml``; returns its path."""
    path = root / "encoders" / f"{name}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    kind = "visual" if encoder == "dinov2" else "geometric"
    path.write_text(yaml.safe_dump({"encoder": encoder, "kind": kind, "params": params, "download": downloads}))
    return path


def _fetch_all(names: list[str], manifests: Path, wdir: Path, source: str = "official", **kw):
    """Fetch every file of ``names`` (as the CLI does); returns the results."""
    planned, _ = select(names, source=source, manifest_dir=manifests)
    return [fetch_download(p.download, wdir, manifest=p.manifest, name=p.name, progress=False, **kw) for p in planned]


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _official_manifest(root: Path, server: Loopback, body: bytes, **entry) -> tuple[Path, str]:
    url = server.serve("/dinov2/dinov2_vitt14/dinov2_vitt14_pretrain.pth", body)
    path = _manifest(root, "dinov2-vitt14", "dinov2", {"model": "vitt14"},
                     [{"url": url, "file": "dinov2_vitt14_pretrain.pth", "source": "official", **entry}])
    return path, url


# --------------------------------------------------------------------------- the tests


def test_official_dinov2_downloads_and_loads_strictly(tmp_path, server, tiny_arch, tiny_dinov2):
    net, body = tiny_dinov2
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body, size=len(body))
    (result,) = _fetch_all(["dinov2-vitt14"], manifests, wdir)
    final = wdir / "dinov2_vitt14_pretrain.pth"
    assert (result.path, result.status, result.size, result.resumed_from) == (final, "downloaded", len(body), 0)
    assert final.read_bytes() == body
    assert read_sidecar(final) == _sha(body) == result.sha256
    assert sidecar_path(final).read_text() == f"{_sha(body)}  dinov2_vitt14_pretrain.pth\n"  # sha256sum format
    assert sorted(p.name for p in wdir.iterdir()) == ["dinov2_vitt14_pretrain.pth", "dinov2_vitt14_pretrain.pth.sha256"]
    enc = build_encoder({"name": "dinov2", "params": {"model": "vitt14"}}, weights_dir=wdir)
    assert enc.weights_path == final.resolve() and not enc.hf_dir
    loaded = d2.load_official(enc.weights_path, "vitt14")  # strict
    ref = net.state_dict()
    for k, v in loaded.state_dict().items():
        assert torch.equal(v, ref[k]), k


def test_hf_copy_downloads_into_the_folder_the_loader_looks_in(tmp_path, server, tiny_arch):
    net = _tiny_hf(registers=False, seed=5)
    net.save_pretrained(tmp_path / "hf", safe_serialization=True)
    folder = d2.hf_dirname("vitt14")  # dinov2-vitt14
    entries = [{"url": "https://example.invalid/never-fetched.pth", "file": "dinov2_vitt14_pretrain.pth",
                "source": "official"}]
    for name in ("config.json", "model.safetensors"):
        url = server.serve(f"/facebook/{folder}/resolve/main/{name}", (tmp_path / "hf" / name).read_bytes())
        entries.append({"url": url, "file": f"{folder}/{name}", "source": "hf"})
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _manifest(manifests, "dinov2-vitt14", "dinov2", {"model": "vitt14"}, entries)
    results = _fetch_all(["dinov2-vitt14"], manifests, wdir, source="hf")
    assert [r.path.relative_to(wdir).as_posix() for r in results] == [f"{folder}/config.json",
                                                                      f"{folder}/model.safetensors"]
    assert [p for p, _ in server.requests] == [f"/facebook/{folder}/resolve/main/config.json",
                                               f"/facebook/{folder}/resolve/main/model.safetensors"]
    enc = build_encoder({"name": "dinov2", "params": {"model": "vitt14"}}, weights_dir=wdir)
    assert enc.weights_path == (wdir / folder).resolve() and enc.hf_dir
    loaded = d2.load_hf_dir(enc.weights_path)
    ref = net.state_dict()
    assert all(torch.equal(v, ref[k]) for k, v in loaded.state_dict().items())


def test_gedi_zip_member_is_extracted_and_loads(tmp_path, server, gedi_zip):
    archive, ckpt = gedi_zip
    url = server.serve("/download?id=GEDI&export=download&confirm=t", archive)
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    entry = {"url": url, "member": GEDI_MEMBER, "file": "gedi/chkpt.tar", "sha256": _sha(ckpt)}
    for name in ("gedi", "gedi-r03"):  # two manifests share the file: it is fetched once
        _manifest(manifests, name, "gedi", {"weights": "gedi/chkpt.tar"}, [entry])
    planned, _ = select(["gedi", "gedi-r03"], manifest_dir=manifests)
    assert len(planned) == 1 and planned[0].names == ["gedi", "gedi-r03"]
    (result,) = _fetch_all(["gedi", "gedi-r03"], manifests, wdir)
    final = wdir / "gedi" / "chkpt.tar"
    assert final.read_bytes() == ckpt and result.sha256 == _sha(ckpt) == read_sidecar(final)
    assert result.received == len(archive)
    assert sorted(p.name for p in final.parent.iterdir()) == ["chkpt.tar", "chkpt.tar.sha256"]  # archive deleted
    enc = build_encoder({"name": "gedi", "params": {"weights": "gedi/chkpt.tar"}}, weights_dir=wdir)  # strict load
    assert enc.weights == final.resolve()
    ref = torch.load(io.BytesIO(ckpt), weights_only=True)[STATE_KEY]
    assert all(torch.equal(v, ref[k]) for k, v in enc.net.state_dict().items())


def test_a_cut_transfer_resumes_with_a_range_request(tmp_path, server, tiny_dinov2):
    body = tiny_dinov2[1]
    half = len(body) // 2
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body, sha256=_sha(body))
    final = wdir / "dinov2_vitt14_pretrain.pth"
    server.cut_after = half
    with pytest.raises(WeightsFetchError, match=rf"interrupted after {half} of {len(body)} bytes.*"
                                                r"run `freeze weights fetch dinov2-vitt14` again to resume"):
        _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert not final.exists() and not sidecar_path(final).exists()  # nothing under the final name
    assert part_path(final).read_bytes() == body[:half]
    (result,) = _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert server.requests[-1][1] == f"bytes={half}-"
    assert (result.resumed_from, result.received) == (half, len(body) - half)
    assert final.read_bytes() == body and read_sidecar(final) == _sha(body)
    assert not part_path(final).exists()


def test_a_server_without_ranges_restarts_from_zero(tmp_path, server, tiny_dinov2):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body)
    final = wdir / "dinov2_vitt14_pretrain.pth"
    server.cut_after = 29  # a first transfer records the server's ETag beside the .part
    with pytest.raises(WeightsFetchError, match="interrupted after 29"):
        _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert part_meta_path(final).is_file()
    server.ranges = False  # answers 200 with the whole file
    (result,) = _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert server.requests[-1][1] == "bytes=29-"
    assert (result.resumed_from, result.received) == (0, len(body))
    assert final.read_bytes() == body and read_sidecar(final) == _sha(body)
    assert not part_path(final).exists() and not part_meta_path(final).exists()


def test_a_part_without_a_record_of_the_servers_file_is_not_resumed(tmp_path, server, tiny_dinov2):
    """A .part whose server file was not recorded (no ETag or Last-Modified) and no pinned
    digest: nothing could tell old bytes from new, so the fetch starts from zero (issue 28)."""
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body)
    final = wdir / "dinov2_vitt14_pretrain.pth"
    final.parent.mkdir(parents=True)
    part_path(final).write_bytes(body[:29])
    (result,) = _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert server.requests[-1][1] is None  # no Range
    assert (result.resumed_from, result.received) == (0, len(body))
    assert final.read_bytes() == body and read_sidecar(final) == _sha(body)


def test_a_complete_part_is_published_after_416(tmp_path, server, tiny_dinov2):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _, url = _official_manifest(manifests, server, body)
    final = wdir / "dinov2_vitt14_pretrain.pth"
    final.parent.mkdir(parents=True)
    part_path(final).write_bytes(body)  # a run that ended between the transfer and the rename
    etag = f'"{_sha(body)[:16]}"'  # what that run recorded of the server's file
    part_meta_path(final).write_text(json.dumps({"url": url, "etag": etag, "last_modified": None,
                                                 "length": len(body)}))
    (result,) = _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert server.requests == [("/dinov2/dinov2_vitt14/dinov2_vitt14_pretrain.pth", f"bytes={len(body)}-")]
    assert server.if_ranges == [etag]
    assert result.received == 0 and final.read_bytes() == body and read_sidecar(final) == _sha(body)


def test_a_wrong_pinned_checksum_is_refused(tmp_path, server, tiny_dinov2):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    wrong = "ab" * 32
    manifest, url = _official_manifest(manifests, server, body, sha256=wrong)
    final = wdir / "dinov2_vitt14_pretrain.pth"
    with pytest.raises(WeightsFetchError) as err:
        _fetch_all(["dinov2-vitt14"], manifests, wdir)
    message = str(err.value)
    assert f"expected {wrong}" in message and f"got {_sha(body)}" in message
    assert str(manifest) in message and str(final) in message and "\n" not in message
    assert sorted(p.name for p in wdir.iterdir()) == []  # no final file, no sidecar, no .part


def test_a_404_names_the_url_and_the_manifest(tmp_path, server):
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    url = server.url("/dinov2/missing.pth")
    manifest = _manifest(manifests, "dinov2-vitt14", "dinov2", {"model": "vitt14"},
                         [{"url": url, "file": "dinov2_vitt14_pretrain.pth"}])
    with pytest.raises(WeightsFetchError) as err:
        _fetch_all(["dinov2-vitt14"], manifests, wdir)
    message = str(err.value)
    assert message.startswith(f"{url}: HTTP 404 Not Found") and f"manifest {manifest}" in message
    assert not part_path(wdir / "dinov2_vitt14_pretrain.pth").exists()


def test_no_network_says_how_to_place_the_file_by_hand(tmp_path):
    with socket.socket() as s:  # a port nothing listens on: connection refused
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    url = f"http://127.0.0.1:{port}/download?id=GEDI"
    manifest = _manifest(manifests, "gedi", "gedi", {"weights": "gedi/chkpt.tar"},
                         [{"url": url, "member": GEDI_MEMBER, "file": "gedi/chkpt.tar"}])
    with pytest.raises(WeightsFetchError) as err:
        _fetch_all(["gedi"], manifests, wdir, timeout=5)
    message = str(err.value)
    final = wdir / "gedi" / "chkpt.tar"
    assert message.startswith(f"cannot reach 127.0.0.1:{port} (ConnectionRefusedError")
    assert f"fetch {url} and place it at {final} (the URL is a zip archive: extract its member {GEDI_MEMBER}" in message
    assert "`freeze weights fetch gedi`" in message and str(manifest) in message
    assert not final.exists() and not part_path(final).exists()


def test_a_second_run_verifies_and_skips(tmp_path, server, tiny_dinov2):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body)
    _fetch_all(["dinov2-vitt14"], manifests, wdir)
    server.requests.clear()
    lines: list[str] = []
    (result,) = _fetch_all(["dinov2-vitt14"], manifests, wdir, log=lines.append)
    assert server.requests == [] and result.status == "verified" and result.received == 0
    assert lines == [f"{wdir / 'dinov2_vitt14_pretrain.pth'}: verified, skipped (sha256 {_sha(body)})"]
    # a file changed after it was fetched: refused, left as it is
    final = wdir / "dinov2_vitt14_pretrain.pth"
    changed = body[:-1] + bytes([body[-1] ^ 1])
    final.write_bytes(changed)
    with pytest.raises(WeightsFetchError, match="changed or is corrupt; delete"):
        _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert server.requests == [] and final.read_bytes() == changed


def test_a_file_placed_by_hand_is_checked_and_recorded(tmp_path, server, tiny_dinov2):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body, sha256=_sha(body))
    final = wdir / "dinov2_vitt14_pretrain.pth"
    final.parent.mkdir(parents=True)
    final.write_bytes(body)
    (result,) = _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert result.status == "recorded" and read_sidecar(final) == _sha(body) and server.requests == []
    final.write_bytes(b"not the weights")
    sidecar_path(final).unlink()
    with pytest.raises(WeightsFetchError, match=f"pins {_sha(body)}"):
        _fetch_all(["dinov2-vitt14"], manifests, wdir)
    assert not sidecar_path(final).exists()


def test_entries_must_stay_in_the_weights_folder(tmp_path, server):
    manifests = tmp_path / "manifests"
    _manifest(manifests, "gedi", "gedi", {}, [{"url": server.url("/x"), "file": "../outside.tar"}])
    planned, _ = select(["gedi"], manifest_dir=manifests)
    with pytest.raises(cfg.ManifestError, match="inside the weights folder"):
        fetch_download(planned[0].download, tmp_path / "weights", manifest=planned[0].manifest)


# ------------------------------------------------------------------------------ the CLI


def test_cli_list_shows_the_real_manifests_urls(tmp_path):
    result = runner.invoke(app, ["weights", "list", "--json", "--weights-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["weights_dir"] == str(tmp_path.resolve())
    rows = {(r["manifest"], r["file"]): r for r in data["downloads"]}
    vits = rows[("dinov2-vits14", "dinov2_vits14_pretrain.pth")]
    assert vits["url"] == "https://dl.fbaipublicfiles.com/dinov2/dinov2_vits14/dinov2_vits14_pretrain.pth"
    assert (vits["source"], vits["status"]) == ("official", "missing")
    reg = rows[("dinov2-vitb14-reg", "dinov2_vitb14_reg4_pretrain.pth")]
    assert reg["url"] == "https://dl.fbaipublicfiles.com/dinov2/dinov2_vitb14/dinov2_vitb14_reg4_pretrain.pth"
    hf = rows[("dinov2-vitl14", "dinov2-large/model.safetensors")]
    assert (hf["url"], hf["source"]) == ("https://huggingface.co/facebook/dinov2-large/resolve/main/model.safetensors",
                                         "hf")
    assert ("dinov2-vits14-reg", "dinov2-with-registers-small/config.json") in rows
    for name in ("gedi", "gedi-r02", "gedi-r03", "gedi-r04"):
        gedi = rows[(name, "gedi/chkpt.tar")]
        assert gedi["url"] == ("https://drive.usercontent.google.com/download?id=1Lpep5QigALjk60h8bNJAUH3DnxtnGcZX"
                               "&export=download&confirm=t")
        assert gedi["member"] == GEDI_MEMBER
    # every file a DINOv2 manifest downloads is one its loader looks up first in the weights folder
    for (name, file), row in rows.items():
        if name.startswith("dinov2"):
            model = cfg.load_encoder_manifest(name).params["model"]
            assert file in (d2.official_filename(model), f"{d2.hf_dirname(model)}/config.json",
                            f"{d2.hf_dirname(model)}/model.safetensors"), (name, file)


def test_cli_fetch_unknown_name_is_one_line():
    result = runner.invoke(app, ["weights", "fetch", "nosuch"])
    assert result.exit_code != 0
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "'nosuch'" in lines[0] and "dinov2-vits14" in lines[0] and "gedi" in lines[0]


def test_cli_fetch_then_skip(tmp_path, server, tiny_dinov2, monkeypatch):
    body = tiny_dinov2[1]
    manifests, wdir = tmp_path / "manifests", tmp_path / "weights"
    _official_manifest(manifests, server, body)
    _manifest(manifests, "gedi", "gedi", {}, [{"url": server.url("/nothing-here"), "file": "gedi/chkpt.tar"}])
    monkeypatch.setattr(cfg, "MANIFEST_DIR", manifests)
    args = ["weights", "fetch", "--weights-dir", str(wdir), "--no-progress"]
    result = runner.invoke(app, [*args, "dinov2-vitt14"])
    assert result.exit_code == 0, result.output
    assert "fetching dinov2_vitt14_pretrain.pth" in result.output and (wdir / "dinov2_vitt14_pretrain.pth").is_file()
    result = runner.invoke(app, [*args, "--all"])  # the DINOv2 file is skipped, the GeDi one fails: exit 1
    assert result.exit_code == 1
    assert "verified, skipped" in result.output and "HTTP 404" in result.output
