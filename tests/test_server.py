"""Tests of lungdeform.server: loopback by default, a fixed whitelist of paths, GET/HEAD only."""

from __future__ import annotations

import http.client
import json

import pytest

from lungdeform.errors import InputError, ReadError
from lungdeform.export import glb_bytes
from lungdeform.server import ViewerServer, check_glb, model_glb, viewer_dir
from tests.browser.support import two_lungs


@pytest.fixture(scope="module")
def glb():
    return glb_bytes(two_lungs(2))


@pytest.fixture(scope="module")
def server(glb):
    with ViewerServer(glb, port=0) as srv:
        yield srv


def request(srv, method, path, host=None, body=None):
    conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=10)
    conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
    conn.putheader("Host", host if host is not None else f"127.0.0.1:{srv.port}")
    if body is not None:
        conn.putheader("Content-Length", str(len(body)))
    conn.endheaders(body)
    res = conn.getresponse()
    data = res.read()
    conn.close()
    return res, data


def test_binds_loopback_by_default(server):
    assert server.host == "127.0.0.1" and server.url == f"http://127.0.0.1:{server.port}/"
    assert server._httpd.server_address[0] == "127.0.0.1"


def test_serves_viewer_model_and_presets(server, glb):
    res, body = request(server, "GET", "/")
    assert res.status == 200 and res.getheader("Content-Type").startswith("text/html")
    assert body == (viewer_dir() / "index.html").read_bytes()
    assert res.getheader("X-Content-Type-Options") == "nosniff"
    assert "default-src 'self'" in res.getheader("Content-Security-Policy")
    res, body = request(server, "GET", "/model.glb?cache=1")
    assert res.status == 200 and body == glb and res.getheader("Content-Type") == "model/gltf-binary"
    res, body = request(server, "GET", "/presets.json")
    assert res.status == 200 and isinstance(json.loads(body)["presets"], list)
    # every asset the bundle references is served
    for asset in (viewer_dir() / "assets").iterdir():
        res, body = request(server, "GET", f"/assets/{asset.name}")
        assert res.status == 200 and body == asset.read_bytes()


def test_head_sends_headers_only(server, glb):
    res, body = request(server, "HEAD", "/model.glb")
    assert res.status == 200 and body == b"" and int(res.getheader("Content-Length")) == len(glb)


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE", "CONNECT", "PROPFIND"])
def test_other_methods_are_refused(server, method):
    res, _ = request(server, method, "/model.glb", body=b"x")
    assert res.status == 405 and res.getheader("Allow") == "GET, HEAD"


@pytest.mark.parametrize("path", [
    "/../../../../etc/passwd", "/assets/../../pyproject.toml", "/%2e%2e/%2e%2e/etc/passwd",
    "/assets/", "/assets", "/src/main.ts", "/data/viewer/index.html", "//etc/passwd",
    "/assets/..%2f..%2fserver.py", "/model.npz", "/.git/config", "/index.html/..",
    "/ASSETS/viewer.js", "/favicon.ico",
])
def test_no_traversal_and_no_listing(server, path):
    res, body = request(server, "GET", path)
    assert res.status == 404, (path, body[:80])
    assert b"root:" not in body and b"<a href" not in body


def test_foreign_host_header_is_refused(server):
    # a DNS-rebinding page would send its own host name
    res, _ = request(server, "GET", "/model.glb", host=f"evil.example:{server.port}")
    assert res.status == 403
    res, _ = request(server, "GET", "/model.glb", host=f"localhost:{server.port}")
    assert res.status == 200


def test_check_glb_and_model_glb(tmp_path, glb):
    with pytest.raises(ReadError, match="not a glTF binary"):
        check_glb(b"PK\x03\x04" + b"\0" * 40, "x.glb")
    with pytest.raises(ReadError, match="length"):
        check_glb(glb[:-4], "cut.glb")
    f = tmp_path / "m.glb"
    f.write_bytes(glb)
    assert model_glb(f) == glb
    with pytest.raises(InputError, match="apply to a model file"):
        model_glb(f, curve=tmp_path / "c.csv")
    with pytest.raises(ReadError, match="no such file"):
        model_glb(tmp_path / "missing.npz")


def test_missing_bundle_and_bad_port(glb, tmp_path):
    with pytest.raises(ReadError, match="viewer bundle is missing"):
        ViewerServer(glb, bundle=tmp_path)
    with pytest.raises(InputError, match="port"):
        ViewerServer(glb, port=70000)
