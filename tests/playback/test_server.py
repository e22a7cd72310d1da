"""Tests of lungdeform.playback.server: loopback by default, a fixed whitelist of paths, GET/HEAD only."""

from __future__ import annotations

import http.client
import json
import socket

import numpy as np
import pytest

from lungdeform.breathing.presets import PRESET_NAMES, PRESETS
from lungdeform.breathing.pv import simulate
from lungdeform.errors import InputError, ReadError
from lungdeform.playback.export import glb_bytes
from lungdeform.playback.server import (
    PRESET_RATE_HZ,
    ServerLog,
    ViewerServer,
    check_glb,
    model_glb,
    presets_json,
    viewer_dir,
)
from lungdeform.playback.tracefeed import LiveFeed
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
    assert res.status == 200 and res.getheader("Content-Type") == "application/json"
    assert body == presets_json() and len(json.loads(body)["presets"]) == len(PRESET_NAMES)
    # every asset the bundle references is served
    for asset in (viewer_dir() / "assets").iterdir():
        res, body = request(server, "GET", f"/assets/{asset.name}")
        assert res.status == 200 and body == asset.read_bytes()


def test_presets_json_is_the_pv_model_presets(server):
    # truth: lungdeform.breathing.presets simulated here, independently, by the PV model (one periodic cycle)
    res, body = request(server, "GET", "/presets.json")
    doc = json.loads(body)
    assert doc["schema"] == "lungdeform.presets" and doc["schema_version"] == 1
    assert [p["name"] for p in doc["presets"]] == list(PRESET_NAMES)
    for entry in doc["presets"]:
        preset = PRESETS[entry["name"]]
        period = preset.params.period_s
        assert entry["description"] == preset.description and entry["sources"] == list(preset.sources)
        assert entry["sources"] and all(isinstance(x, str) and x for x in entry["sources"])
        assert entry["period_s"] == period and entry["rate_bpm"] == pytest.approx(60 / period)
        assert entry["tidal_volume_ml"] == preset.tidal_volume_ml
        assert entry["params"] == json.loads(json.dumps(preset.params.as_dict()))
        # one whole cycle, [0, T], at >= 50 Hz: the grid ends exactly at the period
        t, s = np.array(entry["t_s"]), np.array(entry["s"])
        n = len(t) - 1
        assert entry["fs_hz"] >= PRESET_RATE_HZ and entry["fs_hz"] == pytest.approx(n / period)
        assert t[0] == 0 and t[-1] == pytest.approx(period, abs=1e-9)
        np.testing.assert_allclose(np.diff(t), period / n, rtol=1e-9)
        ref = simulate(preset.params, n_cycles=1, fs_hz=n / period)
        np.testing.assert_allclose(t, ref.t_s, atol=1e-12)
        v_ee, dv = ref.volume_ml.min(), np.ptp(ref.volume_ml)
        np.testing.assert_allclose(s, (ref.volume_ml - v_ee) / dv, atol=1e-12)
        assert entry["end_exhale_ml"] == pytest.approx(v_ee) and entry["curve_tidal_ml"] == pytest.approx(dv)
        # s is normalised, the sampled peak-to-peak is the preset's tidal volume (50 Hz samples),
        # and the periodic steady state closes: s(T) = s(0)
        assert s.min() == 0 and s.max() == pytest.approx(1.0)
        assert dv == pytest.approx(preset.tidal_volume_ml, rel=2e-3)
        assert s[-1] == pytest.approx(s[0], abs=1e-4)


def test_presets_bytes_can_be_replaced(glb):
    # what the viewer's fallback test uses: the route serves the given bytes, still whitelisted
    with ViewerServer(glb, presets=b"not json") as srv:
        res, body = request(srv, "GET", "/presets.json")
        assert res.status == 200 and body == b"not json"
        res, _ = request(srv, "POST", "/presets.json", body=b"{}")
        assert res.status == 405


def test_trace_json_is_null_by_default_and_served_as_given(server, glb):
    # without a trace the page must still find /trace.json (a 404 would be a console error in the
    # browser): "trace": null, so the viewer plays the presets; given bytes are served as they are
    res, body = request(server, "GET", "/trace.json")
    assert res.status == 200 and res.getheader("Content-Type") == "application/json"
    assert json.loads(body)["trace"] is None and json.loads(body)["schema"] == "lungdeform.trace-prediction"
    with ViewerServer(glb, trace=b'{"trace": 1}') as srv:
        assert request(srv, "GET", "/trace.json")[1] == b'{"trace": 1}'


def test_live_is_server_sent_events_of_the_feed(glb):
    # /live streams the feed's events (text/event-stream, no length: the connection closes at the end);
    # without a feed it is not a route (404)
    feed = LiveFeed(predict_ms=300)
    feed.push(0.0, 1.0)
    feed.push(0.1, 2.0)
    feed.end()
    with ViewerServer(glb, live=feed) as srv:
        res, body = request(srv, "GET", "/live")
        assert res.status == 200 and res.getheader("Content-Type") == "text/event-stream"
        events = [json.loads(c[6:]) for c in body.decode().split("\n\n") if c.startswith("data: {\"")]
        assert [e["t_s"] for e in events] == [0.0, 0.1] and events[0]["ahead_s"] == 0.3
        assert body.endswith(b"event: end\ndata: {}\n\n")
    with ViewerServer(glb) as srv:
        assert request(srv, "GET", "/live")[0].status == 404


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


def test_port_in_use_names_the_address_and_the_option(glb):
    # a listening socket holds the port: binding again fails with EADDRINUSE, which used to reach
    # the user as a bare "Address already in use" without saying which address or what to do
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        with pytest.raises(InputError, match=rf"cannot serve on 127\.0\.0\.1:{port}: .*--port"):
            ViewerServer(glb, port=port)


def test_a_client_that_resets_the_connection_is_one_line_not_a_traceback(glb, capfd):
    # why: socketserver printed a traceback on stderr for every connection a client reset (132 in
    # one viewer session); a failed request is now one line to the server's ``errors``
    import struct
    import time

    lines: list[str] = []
    with ViewerServer(glb, port=0, report=ServerLog(errors=lines.append)) as srv:
        for _ in range(3):
            s = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
            s.sendall(b"GET /model.glb HTTP/1.1\r\nHost: 127.0.0.1")  # the headers never end
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            s.close()  # linger 0: an RST, not a FIN
        deadline = time.monotonic() + 10
        while len(lines) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert request(srv, "GET", "/model.glb")[0].status == 200  # still serving
    err = capfd.readouterr().err
    assert "Traceback" not in err and err == "", err
    assert len(lines) == 3 and all("closed the connection" in line and "\n" not in line for line in lines), lines
