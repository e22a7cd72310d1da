"""``lungdeform view``: serve the browser viewer for a model or a .glb on a loopback address; with
``--trace TRACE [--predict-ms H]`` the viewer plays a recorded breathing trace in trace time, showing
the volume the streaming estimator predicts H ms ahead (docs/PREDICTION.md); ``--trace -`` reads
``t_s,amplitude`` lines from stdin and pushes each estimate to the page as it arrives. With
``--predict-ms`` the page also shows the beam gate for that latency (``lungdeform stream --gate``:
the window, the prediction's interval band, BEAM ON/OFF; docs/VIEWER.md), set by ``--window``,
``--confident`` and ``--coverage``."""

from __future__ import annotations

import ipaddress
import sys
import webbrowser
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.breathing.gating import GateRule, parse_window
from lungdeform.breathing.predict_interval import IntervalConfig
from lungdeform.breathing.stream import MAX_PREDICT_MS
from lungdeform.errors import InputError
from lungdeform.playback.server import ServerLog, ViewerServer, model_glb
from lungdeform.playback.tracefeed import LiveFeed, check_view_options, live_json, view_trace_json

from .common import bounded, takes


def _port_option(value: int) -> int:
    """``--port`` within 0…65535, refused as the command line is parsed."""
    if not 0 <= value <= 65535:
        raise InputError(f"--port must be 0..65535 (0 picks a free one), got {value}")
    return value


@dataclass(frozen=True, kw_only=True)
class ViewOptions:
    """The options of ``lungdeform view`` (:func:`register`)."""

    model: Annotated[Path, typer.Argument(help="Model file (.npz) or an exported .glb.")]
    host: Annotated[str, typer.Option("--host", help="Address to bind (loopback by default).")] = "127.0.0.1"
    port: Annotated[int, typer.Option("--port", callback=_port_option, help="Port (0 picks a free one).")] = 8765
    curve: Annotated[Path | None, typer.Option("--curve", help="Breathing curve CSV for a model file.")] = None
    markers: Annotated[Path | None, typer.Option("--markers", help="Markers CSV (x_mm,y_mm,z_mm[,label]) for a model file.")] = None
    trace: Annotated[Path | None, typer.Option("--trace", help="Breathing trace to play (.vxp or marker .csv) "
        "through the streaming volume estimator, or - for live 't_s,amplitude' lines on stdin.")] = None
    predict_ms: Annotated[float, typer.Option("--predict-ms", callback=bounded(0, MAX_PREDICT_MS, "ms"), help="With --trace: show the volume predicted this many ms ahead "
        f"(0-{MAX_PREDICT_MS:g}), compensating that display latency.")] = 0.0
    window: Annotated[str | None, typer.Option("--window", help="With --predict-ms: the gating window KIND:PERCENT "
        "(default end-exhale:30).")] = None
    confident: Annotated[bool, typer.Option("--confident", help="With --predict-ms: beam on only when the whole "
        "interval is inside the window.")] = False
    coverage: Annotated[float | None, typer.Option("--coverage", callback=bounded(0, 1, low_open=True, high_open=True), help="With --predict-ms: the interval's coverage "
        "(0-1, default 0.9).")] = None
    open_browser: Annotated[bool, typer.Option("--open", help="Open the default web browser.")] = False


def register(apps) -> None:
    @apps.root.command("view")
    @takes(ViewOptions)
    def view_command(opts: ViewOptions) -> None:
        """Show both lungs breathing in the browser (three.js, deformation on the GPU, WebXR)."""


        rule = None
        if opts.window is not None or opts.confident or opts.coverage is not None:
            try:
                interval = IntervalConfig(coverage=0.9 if opts.coverage is None else opts.coverage)
            except InputError as exc:
                raise InputError(f"--coverage: {exc}") from None
            rule = GateRule(parse_window(opts.window or "end-exhale:30"), opts.confident, interval=interval)
        check_view_options(opts.model, opts.trace, opts.curve, opts.predict_ms, rule)  # before the model is exported
        live = LiveFeed(opts.predict_ms, rule) if str(opts.trace) == "-" else None
        feed = live_json(live) if live is not None else view_trace_json(opts.model, opts.trace, opts.curve, opts.predict_ms, rule)
        glb = model_glb(opts.model, opts.curve, opts.markers)
        # /presets.json: lungdeform.breathing.presets; /trace.json: the trace; /live: the live feed
        server = ViewerServer(glb, host=opts.host, port=opts.port, trace=feed, live=live,
                              report=ServerLog(errors=lambda line: typer.echo(line, err=True)))
        try:
            exposed = not ipaddress.ip_address(opts.host).is_loopback
        except ValueError:
            exposed = opts.host != "localhost"
        if exposed:
            typer.echo(f"warning: serving on {opts.host}, reachable from other machines", err=True)
        typer.echo(f"viewer for {opts.model} at {server.url}  (Ctrl-C to stop)")
        if opts.open_browser:
            webbrowser.open(server.url)
        try:
            if live is None:
                server.serve_forever()
            else:
                server.start()
                live.push_lines(sys.stdin)  # a bad line: InputError naming it (exit 2)
                typer.echo("stdin ended: the page keeps the last sample  (Ctrl-C to stop)")
                server.join()
        finally:
            server.close()
