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
from pathlib import Path

import typer

from lungdeform.breathing.gating import GateRule, parse_window
from lungdeform.breathing.predict_interval import IntervalConfig
from lungdeform.breathing.stream import MAX_PREDICT_MS, StreamingVolumeEstimator, stream_lines
from lungdeform.breathing.trace import read_trace
from lungdeform.errors import InputError

from .common import MAX_LUNGS_ML, bounded, tidal_option


def register(apps) -> None:
    @apps.root.command("stream")
    def stream(
        source: str = typer.Argument("-", help="A trace file to replay, or - to read 't_s,amplitude' lines from stdin."),
        predict_ms: float = typer.Option(0.0, "--predict-ms", callback=bounded(0, MAX_PREDICT_MS, "ms"),
                                         help=f"Play the volume predicted this many ms ahead (0-{MAX_PREDICT_MS:g})."),
        tidal_volume_ml: float = typer.Option(500.0, "--tidal-volume-ml", callback=tidal_option,
                                              help="Volume of one breath (mL)."),
        v_ee_ml: float = typer.Option(2400.0, "--v-ee-ml", callback=bounded(0, MAX_LUNGS_ML, "mL"),
                                      help="End-exhale lung volume (mL); 0: volumes above end-exhale."),
        window_s: float = typer.Option(10.0, "--window-s", callback=bounded(0, 3600, "s", low_open=True),
                                       help="Calibration window (s): two or more breaths."),
        gate: bool = typer.Option(False, "--gate", help="Add the beam decision for t_s + H (needs --predict-ms H) "
                                                        "with the prediction's interval."),
        window: str = typer.Option("end-exhale:30", "--window", help="With --gate: the gating window KIND:PERCENT."),
        confident: bool = typer.Option(False, "--confident", help="With --gate: the whole interval must be inside."),
        coverage: float = typer.Option(0.9, "--coverage", callback=bounded(0, 1, low_open=True, high_open=True), help="With --gate: the interval's coverage (0-1)."),
    ):
        """Volume per sample from a live breathing signal (stdin) or a recorded trace, optionally predicted ahead."""

        rule = GateRule(parse_window(window), confident, interval=IntervalConfig(coverage=coverage)) if gate else None
        if gate and predict_ms <= 0:
            raise InputError("--gate needs --predict-ms H > 0: the beam's latency, the time its decision is for")
        est = StreamingVolumeEstimator(tidal_volume_ml=tidal_volume_ml, v_ee_ml=v_ee_ml, window_s=window_s,
                                       predict_ms=predict_ms, gate=rule)
        if source == "-":
            samples = stream_lines(sys.stdin, est)
        else:
            samples = _replay(Path(source), est)
        typer.echo("t_s,volume_ml,ahead_s" + (",predicted,lo,hi,window_low,window_high,beam" if gate else ""))
        for s in samples:
            typer.echo(f"{s.t_s:.6g},{s.volume_ml:.3f},{s.ahead_s:g}" + (_gate_cells(s.gate) if gate else ""))
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
