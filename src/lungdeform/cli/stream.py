"""``lungdeform stream [TRACE | -] [--predict-ms H]``: the streaming volume estimate, one line per sample.

Reads samples ``t_s,amplitude`` from standard input as they arrive (``-``, the default) or replays a
recorded trace (any file ``lungdeform breathe`` reads), and writes ``t_s,volume_ml,ahead_s`` per sample
to standard output at once, for a renderer or a beam controller downstream. With ``--predict-ms H`` each
volume is the one predicted for ``t_s + H`` ms (:mod:`lungdeform.breathing.predict`), cancelling that
much display or beam latency (docs/PREDICTION.md). With ``--gate`` each line also carries the predicted
signal at ``t_s + H`` with its interval, the gating window known at ``t_s`` and the beam decision
(``on``/``off``; :class:`lungdeform.breathing.gating.BeamGate`), in the signal's own units.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.breathing.gating import GateRule, parse_window
from lungdeform.breathing.predict_interval import IntervalConfig
from lungdeform.breathing.stream import MAX_PREDICT_MS, StreamingVolumeEstimator, stream_lines
from lungdeform.breathing.trace import read_trace
from lungdeform.errors import InputError

from .common import MAX_LUNGS_ML, bounded, renamed_tidal_ml, takes, tidal_option


@dataclass(frozen=True, kw_only=True)
class StreamOptions:
    """The options of ``lungdeform stream`` (:func:`register`)."""

    source: Annotated[str, typer.Argument(help="A trace file to replay, or - to read 't_s,amplitude' lines from stdin.")] = "-"
    predict_ms: Annotated[float, typer.Option("--predict-ms", callback=bounded(0, MAX_PREDICT_MS, "ms"), help=f"Play the volume predicted this many ms ahead (0-{MAX_PREDICT_MS:g}).")] = 0.0
    tidal_ml: Annotated[float | None, typer.Option("--tidal-ml", callback=tidal_option, help="Volume of one breath (mL; default 500).")] = None
    tidal_volume_ml: Annotated[float | None, typer.Option("--tidal-volume-ml", hidden=True, callback=tidal_option)] = None
    v_ee_ml: Annotated[float, typer.Option("--v-ee-ml", callback=bounded(0, MAX_LUNGS_ML, "mL"), help="End-exhale lung volume (mL); 0: volumes above end-exhale.")] = 2400.0
    window_s: Annotated[float, typer.Option("--window-s", callback=bounded(0, 3600, "s", low_open=True), help="Calibration window (s): two or more breaths.")] = 10.0
    gate: Annotated[bool, typer.Option("--gate", help="Add the beam decision for t_s + H (needs --predict-ms H) "
        "with the prediction's interval.")] = False
    window: Annotated[str, typer.Option("--window", help="With --gate: the gating window KIND:PERCENT.")] = "end-exhale:30"
    confident: Annotated[bool, typer.Option("--confident", help="With --gate: the whole interval must be inside.")] = False
    coverage: Annotated[float, typer.Option("--coverage", callback=bounded(0, 1, low_open=True, high_open=True), help="With --gate: the interval's coverage (0-1).")] = 0.9


def register(apps) -> None:
    @apps.root.command("stream")
    @takes(StreamOptions)
    def stream(opts: StreamOptions) -> None:
        """Volume per sample from a live breathing signal (stdin) or a recorded trace, optionally predicted ahead."""

        rule = GateRule(parse_window(opts.window), opts.confident, interval=IntervalConfig(coverage=opts.coverage)) if opts.gate else None
        if opts.gate and opts.predict_ms <= 0:
            raise InputError("--gate needs --predict-ms H > 0: the beam's latency, the time its decision is for")
        est = StreamingVolumeEstimator(tidal_volume_ml=renamed_tidal_ml(opts.tidal_ml, opts.tidal_volume_ml), v_ee_ml=opts.v_ee_ml, window_s=opts.window_s,
                                       predict_ms=opts.predict_ms, gate=rule)
        if opts.source == "-":
            samples = stream_lines(sys.stdin, est)
        else:
            samples = _replay(Path(opts.source), est)
        typer.echo("t_s,volume_ml,ahead_s" + (",predicted,lo,hi,window_low,window_high,beam" if opts.gate else ""))
        for s in samples:
            typer.echo(f"{s.t_s:.6g},{s.volume_ml:.3f},{s.ahead_s:g}" + (_gate_cells(s.gate) if opts.gate else ""))
            sys.stdout.flush()


def _gate_cells(g) -> str:
    """The gate columns: prediction and interval of the signal at t_s + H, the window, beam on/off."""
    return (f",{g.predicted:.6g},{g.lo:.6g},{g.hi:.6g},{g.window[0]:.6g},{g.window[1]:.6g},"
            f"{'on' if g.beam_on else 'off'}")


def _replay(path: Path, est: StreamingVolumeEstimator):
    """The estimates of a recorded trace, one per sample (the file is read at once, before any line
    is printed); a sample the estimator refuses is named by its number in ``path``."""
    tr = read_trace(path)

    def estimates():
        for i, (t, x) in enumerate(zip(tr.t_s, tr.amplitude), 1):
            try:
                yield est.update(t, x)
            except InputError as exc:
                raise InputError(f"{path} sample {i}: {exc}") from None

    return estimates()
