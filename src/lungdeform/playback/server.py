"""A small local web server for the browser viewer (stdlib :mod:`http.server`).

What it serves, and nothing else:

- the built viewer bundle shipped in ``lungdeform/data/viewer`` (``/``, ``/index.html`` and the
  files directly under ``/assets/``), read once at start;
- the model it was given, as ``/model.glb``;
- ``/presets.json``: the breathing presets of :mod:`lungdeform.breathing.presets`, simulated once by the PV
  model (:func:`lungdeform.breathing.pv.simulate`) at start: per preset its name, description, period,
  tidal volume, sources and one cycle of the normalised curve ``s(t) = (V(t) − V_EE)/ΔV``
  (:func:`presets_payload`). The viewer's preset menu is built from it;
- ``/trace.json``: a recorded trace with its measured and predicted volume per sample
  (:mod:`lungdeform.playback.tracefeed`; ``"trace": null`` when none was given), played in trace time;
- ``/live`` (only with a :class:`~lungdeform.playback.tracefeed.LiveFeed`): its samples as
  Server-Sent Events, as they arrive.

Security: binds to 127.0.0.1 by default; every path is looked up in a fixed table built at start
(no file-system path is ever formed from a request, so no traversal and no directory listing);
only GET and HEAD are allowed (405 otherwise); on a loopback address, requests whose ``Host``
header is not this loopback address and port are refused (403, against DNS rebinding); responses
carry ``Content-Security-Policy``, ``X-Content-Type-Options: nosniff`` and ``Cache-Control: no-store``.
"""

from __future__ import annotations

import functools
import ipaddress
import json
import struct
import sys
import threading
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Callable

import numpy as np

from lungdeform.breathing.presets import PRESETS
from lungdeform.errors import InputError, ReadError
from lungdeform.io.modelfile import load_model

from .export import glb_bytes
from .markers import marker_anchors
from .schedule import check_reachable, preset_trace, read_volume_csv
from .tracefeed import LiveFeed, trace_json
from .trajectory import read_markers_csv

DEFAULT_HOST = "127.0.0.1"
CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8", ".json": "application/json", ".glb": "model/gltf-binary",
    ".svg": "image/svg+xml", ".png": "image/png", ".ico": "image/x-icon", ".wasm": "application/wasm",
    ".txt": "text/plain; charset=utf-8",
}
CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
       "img-src 'self' data: blob:; connect-src 'self'; worker-src 'self' blob:; object-src 'none'; "
       "base-uri 'none'; frame-ancestors 'none'; form-action 'none'")
ALLOWED = ("GET", "HEAD")


def viewer_dir() -> Path:
    """The built viewer bundle inside the package."""
    return Path(__file__).parent.parent / "data" / "viewer"


@dataclass(frozen=True)
class Resource:
    body: bytes
    content_type: str


def bundle_routes(bundle: Path | None = None) -> dict[str, Resource]:
    """``{url path: Resource}`` for the viewer bundle (index and the files directly in assets/)."""
    root = Path(bundle) if bundle is not None else viewer_dir()
    index = root / "index.html"
    if not index.is_file():
        raise ReadError(f"{root}: the viewer bundle is missing (no index.html); build it with "
                        "'npm run build' in viewer/")
    routes = {"/": Resource(index.read_bytes(), CONTENT_TYPES[".html"])}
    routes["/index.html"] = routes["/"]
    assets = root / "assets"
    for f in sorted(assets.iterdir()) if assets.is_dir() else []:
        if f.is_file() and not f.is_symlink() and f.suffix in CONTENT_TYPES:
            routes[f"/assets/{f.name}"] = Resource(f.read_bytes(), CONTENT_TYPES[f.suffix])
    return routes


def check_glb(data: bytes, source: str = "model") -> bytes:
    """Refuse bytes that are not a glTF 2.0 binary (magic ``glTF``, version 2, consistent length)."""

    if len(data) < 20 or data[:4] != b"glTF":
        raise ReadError(f"{source}: not a glTF binary (.glb) file")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2 or length != len(data):
        raise ReadError(f"{source}: glTF binary version {version}, length {length} "
                        f"(expected version 2 and {len(data)} bytes)")
    return data


class _Handler(BaseHTTPRequestHandler):
    server_version = "lungdeform"
    sys_version = ""
    protocol_version = "HTTP/1.1"

    def __getattr__(self, name: str):
        # every method other than GET and HEAD, known to http.server or not, is answered 405
        if name.startswith("do_"):
            return self._not_allowed
        raise AttributeError(name)

    def _not_allowed(self) -> None:
        self._send_plain(HTTPStatus.METHOD_NOT_ALLOWED, {"Allow": ", ".join(ALLOWED)})

    def do_GET(self) -> None:  # noqa: N802
        self._serve(head=False)

    def do_HEAD(self) -> None:  # noqa: N802
        self._serve(head=True)

    def _serve(self, head: bool) -> None:
        srv: ViewerServer = self.server.owner  # type: ignore[attr-defined]
        if not srv.host_allowed(self.headers.get("Host", "")):
            self._send_plain(HTTPStatus.FORBIDDEN, head=head)
            return
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        if path == "/live" and srv.live is not None:
            self._stream(srv.live, head)
            return
        res = srv.routes.get(path)
        if res is None:
            self._send_plain(HTTPStatus.NOT_FOUND, head=head)
            return
        self.send_response(HTTPStatus.OK)
        self._common_headers(res.content_type, len(res.body))
        self.end_headers()
        if not head:
            self.wfile.write(res.body)

    def _stream(self, feed: LiveFeed, head: bool) -> None:
        """Server-Sent Events until the feed ends or the page goes (no length: the connection closes)."""
        self.send_response(HTTPStatus.OK)
        self._common_headers("text/event-stream", None)
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        if head:
            return
        try:
            for chunk in feed.events():
                self.wfile.write(chunk)
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            pass

    def _common_headers(self, content_type: str, length: int | None) -> None:
        self.send_header("Content-Type", content_type)
        if length is not None:
            self.send_header("Content-Length", str(length))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", CSP)
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Cross-Origin-Opener-Policy", "same-origin")
        self.send_header("Cross-Origin-Resource-Policy", "same-origin")

    def _send_plain(self, status: HTTPStatus, extra: dict | None = None, head: bool = False) -> None:
        body = f"{status.value} {status.phrase}\n".encode()
        self.send_response(status)
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self._common_headers(CONTENT_TYPES[".txt"], len(body))
        self.end_headers()
        if not head and self.command != "HEAD":
            self.wfile.write(body)

    def log_message(self, fmt: str, *args) -> None:
        log = self.server.owner.log  # type: ignore[attr-defined]
        if log is not None:
            log(f"{self.address_string()} {fmt % args}")


class _Server(ThreadingHTTPServer):
    """The HTTP server: a request that fails is one line to the owner's ``errors`` (a client that
    went away mid-request, reset or broken pipe, is routine: a closed tab, a reload), never
    socketserver's traceback on stderr."""

    def handle_error(self, request, client_address) -> None:
        exc = sys.exc_info()[1]
        where = f"{client_address[0]}:{client_address[1]}" if isinstance(client_address, tuple) else str(client_address)
        if isinstance(exc, (ConnectionError, TimeoutError)):
            line = f"viewer: {where}: the client closed the connection ({exc.strerror or type(exc).__name__})"
        else:
            line = f"viewer: {where}: the request failed: {type(exc).__name__}: {exc}"
        errors = self.owner.errors  # type: ignore[attr-defined]
        if errors is not None:
            errors(line)


@dataclass(frozen=True)
class ServerLog:
    """Where a :class:`ViewerServer` reports: ``requests`` is called with a line per request;
    ``errors`` with a line per request that failed (a client that reset the connection, …); None:
    not reported."""

    requests: Callable[[str], None] | None = None
    errors: Callable[[str], None] | None = None


class ViewerServer:
    """Serve the viewer and one model. ``port=0`` picks a free port; :attr:`url` says where.
    ``presets``: the bytes of ``/presets.json`` (default :func:`presets_json`); ``trace``: the bytes of
    ``/trace.json`` (default: no trace, :func:`lungdeform.playback.tracefeed.trace_json`); ``live``: a
    :class:`~lungdeform.playback.tracefeed.LiveFeed` served as ``/live``. ``report``: where requests
    and failed requests are reported (:class:`ServerLog`; default: nowhere).

    Use as a context manager (serves from a background thread) or call :meth:`serve_forever`.
    """

    def __init__(self, glb: bytes, *, host: str = DEFAULT_HOST, port: int = 0,
                 presets: bytes | None = None, bundle: Path | None = None, trace: bytes | None = None,
                 live: LiveFeed | None = None, report: ServerLog = ServerLog()):
        if not 0 <= int(port) <= 65535:
            raise InputError(f"port must be 0..65535, got {port}")
        self.routes = bundle_routes(bundle)
        self.routes["/model.glb"] = Resource(check_glb(glb), CONTENT_TYPES[".glb"])
        # presets=None: lungdeform.breathing.presets, simulated once per process (presets_json); other bytes are
        # served as given (tests use them to exercise the viewer's fallback)
        body = presets_json() if presets is None else bytes(presets)
        self.routes["/presets.json"] = Resource(body, CONTENT_TYPES[".json"])
        self.routes["/trace.json"] = Resource(trace_json() if trace is None else bytes(trace), CONTENT_TYPES[".json"])
        self.live = live
        self.log = report.requests
        self.errors = report.errors
        try:
            self._httpd = _Server((host, int(port)), _Handler)
        except OSError as exc:  # port in use, address not on this machine, …: name the address
            where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
            raise InputError(f"cannot serve on {where}: {exc.strerror or exc}; pass another --port "
                             "(0 picks a free one)") from exc
        self._httpd.daemon_threads = True
        self._httpd.owner = self  # type: ignore[attr-defined]
        self.host = host
        self.port = self._httpd.server_address[1]
        self._thread: threading.Thread | None = None

    @property
    def loopback(self) -> bool:
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return self.host == "localhost"

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def host_allowed(self, header: str) -> bool:
        """On loopback, only ``Host: <loopback name>:<port>`` is accepted (DNS-rebinding guard)."""
        if not self.loopback:
            return True
        names = {"127.0.0.1", "localhost", "[::1]", f"[{self.host}]" if ":" in self.host else self.host}
        return header.strip().lower() in {f"{n}:{self.port}" for n in names}

    def serve_forever(self) -> None:
        self._httpd.serve_forever(poll_interval=0.2)

    def join(self) -> None:
        """Wait for the background server (started by :meth:`start`) until it is closed or interrupted."""
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(0.5)

    def start(self) -> "ViewerServer":
        self._thread = threading.Thread(target=self.serve_forever, name="lungdeform-viewer", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()
        if self._thread is not None:
            self._httpd.shutdown()
            self._thread.join()
            self._thread = None
        self._httpd.server_close()

    def __enter__(self) -> "ViewerServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def model_glb(path, curve=None, markers=None) -> bytes:
    """The ``.glb`` bytes for ``path``: a glTF binary as given, or a model file exported on the fly
    (with an optional curve CSV and markers CSV)."""
    p = Path(path)
    if not p.is_file():
        raise ReadError(f"{p}: no such file")
    if p.suffix.lower() == ".glb":
        if curve is not None or markers is not None:
            raise InputError(f"{p}: a curve and markers apply to a model file, not to a .glb")
        return check_glb(p.read_bytes(), str(p))

    model = load_model(p)
    trace = read_volume_csv(curve) if curve is not None else None
    if trace is not None:
        check_reachable(trace, model)
    anchors = None
    if markers is not None:
        pts, labels = read_markers_csv(markers)
        anchors = marker_anchors(model, pts, labels, source=str(markers))
    return glb_bytes(model, trace, anchors)


#: Sample rate (Hz, at least) of the preset curves served as /presets.json.
PRESET_RATE_HZ = 50.0
PRESETS_SCHEMA = "lungdeform.presets"
PRESETS_SCHEMA_VERSION = 1


def presets_payload(rate_hz: float = PRESET_RATE_HZ) -> dict:
    """What ``/presets.json`` holds: every preset of :mod:`lungdeform.breathing.presets`, one cycle each.

    Per preset: ``name``, ``description``, ``period_s``, ``rate_bpm``, ``tidal_volume_ml`` (the
    preset's target), ``curve_tidal_ml`` and ``end_exhale_ml`` (peak-to-peak and minimum of the
    samples, mL), ``fs_hz``, ``t_s`` : (n + 1,) s over [0, period] and ``s`` : (n + 1,) the normalised
    curve ``s(t) = (V(t) − V_EE)/ΔV`` in [0, 1] (V_EE and ΔV: the samples' minimum and peak-to-peak;
    the viewer multiplies ``s`` by its tidal-volume control), ``sources`` and the PV ``params``.
    """

    out = []
    for name, preset in PRESETS.items():
        # one cycle of the periodic steady state, n = ceil(T·rate_hz) intervals ending exactly at T
        _params, _curve, trace = preset_trace(preset, 1, rate_hz=rate_hz)
        fs = (len(trace.t_s) - 1) / float(preset.params.period_s)
        span = float(np.ptp(trace.volume_ml))
        out.append({
            "name": name, "description": preset.description,
            "period_s": float(preset.params.period_s), "rate_bpm": 60.0 / float(preset.params.period_s),
            "tidal_volume_ml": float(preset.tidal_volume_ml), "curve_tidal_ml": span,
            "end_exhale_ml": trace.shifted_ml, "fs_hz": fs,
            "t_s": trace.t_s.tolist(), "s": (trace.volume_ml / span).tolist(),
            "sources": list(preset.sources), "params": preset.params.as_dict(),
        })
    return {
        "schema": PRESETS_SCHEMA, "schema_version": PRESETS_SCHEMA_VERSION,
        "meaning": "one cycle of the periodic steady state of the PV breathing model per preset; "
                   "t = 0 is the onset of inspiration; s(t) = (V(t) - V_EE)/dV, V_EE and dV the "
                   "minimum and peak-to-peak of the samples",
        "presets": out,
    }


@functools.lru_cache(maxsize=1)
def presets_json() -> bytes:
    """:func:`presets_payload` as UTF-8 JSON (computed once per process: about 0.3 s)."""
    return json.dumps(presets_payload(), ensure_ascii=False).encode("utf-8")
