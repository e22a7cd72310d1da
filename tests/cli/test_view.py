"""``lungdeform view``: bad input exits 2 with one line on stderr."""

import json
import socket

import numpy as np
import pytest

from lungdeform.cli.main import main
from lungdeform.io.modelfile import save_model
from lungdeform.playback.export import glb_bytes
from tests.breathing.test_trace import breath, write_marker_csv
from tests.browser.support import two_lungs


def test_view_port_in_use_exits_2_naming_the_address(tmp_path, capsys):
    # another program listens on the port: one line naming host:port and the option to change,
    # before anything is served (the server is never started)
    model = tmp_path / "m.glb"
    model.write_bytes(glb_bytes(two_lungs(2)))
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert main(["view", str(model), "--port", str(port)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and f"127.0.0.1:{port}" in err[0] and "--port" in err[0]
    assert "viewer for" not in captured.out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.glb"]  # nothing written


class _Captured:
    """Stands in for ViewerServer: keeps what would be served, serves nothing."""

    served: dict = {}

    def __init__(self, glb, *, host, port, trace, live, report=None):
        _Captured.served = {"glb": glb, "trace": trace}
        self.url = "http://127.0.0.1:0/"

    def serve_forever(self):
        pass

    def close(self):
        pass


def test_view_trace_serves_what_stream_prints(tmp_path, capsys, monkeypatch):
    # one estimator: /trace.json's predicted volume per sample is what `stream --predict-ms 400` prints
    # for the same file, and its measured volume what plain `stream` prints (same rounding, %.3f)
    import lungdeform.cli.view as view

    t = np.arange(0.0, 40.0, 0.1)
    trace = write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t))
    model = save_model(tmp_path / "m.npz", two_lungs(2))
    monkeypatch.setattr(view, "ViewerServer", _Captured)
    assert main(["view", str(model), "--trace", str(trace), "--predict-ms", "400"]) == 0
    served = json.loads(_Captured.served["trace"])["trace"]
    capsys.readouterr()
    printed = {}
    for h in ("0", "400"):
        assert main(["stream", str(trace), "--predict-ms", h]) == 0
        printed[h] = [line.split(",") for line in capsys.readouterr().out.split()[1:]]
    assert [f"{v:.3f}" for v in served["predicted_ml"]] == [row[1] for row in printed["400"]]
    assert [f"{v:.3f}" for v in served["measured_ml"]] == [row[1] for row in printed["0"]]
    assert [f"{v:.6g}" for v in served["t_s"]] == [row[0] for row in printed["400"]]
    assert {f"{v:g}" for v in served["ahead_s"]} == {row[2] for row in printed["400"]} == {"0.4"}


@pytest.mark.parametrize("args, needle", [
    (["--predict-ms", "-1"], "--predict-ms must be a finite number in [0, 2000] ms"),
    (["--predict-ms", "2500"], "--predict-ms must be a finite number in [0, 2000] ms"),
    (["--curve", "CURVE"], "--trace and --curve"),
    (["--window", "end-exhale:30"], "--window, --confident and --coverage set the gate of --predict-ms"),
    (["--predict-ms", "300", "--coverage", "1.5"], "--coverage must be a finite number in (0, 1)"),
    (["--predict-ms", "300", "--window", "mid:30"], "--window 'mid:30': window kind must be one of"),
])
def test_view_trace_bad_options_exit_2_with_one_line(tmp_path, capsys, args, needle):
    # refused by option name before anything is served or written
    t = np.arange(0.0, 20.0, 0.1)
    trace = write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t))
    model = save_model(tmp_path / "m.npz", two_lungs(2))
    args = [str(tmp_path / "c.csv") if a == "CURVE" else a for a in args]
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(["view", str(model), "--trace", str(trace), "--port", "0", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_view_trace_with_glb_or_bad_trace_exits_2_naming_the_file(tmp_path, capsys):
    # a .glb cannot take a trace (refused naming it); a trace that does not parse: the reader's error,
    # naming the trace file, one line, no traceback
    glb = tmp_path / "m.glb"
    glb.write_bytes(glb_bytes(two_lungs(2)))
    model = save_model(tmp_path / "m.npz", two_lungs(2))
    bad = tmp_path / "bad.csv"
    bad.write_text("Frame;Timestamp;x;y;z\n1;0;abc;0;0\n")
    assert main(["view", str(glb), "--trace", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(glb) in err[0] and "--trace" in err[0], err
    assert main(["view", str(model), "--trace", str(bad), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "Traceback" not in err[0], err


def test_view_live_bad_stdin_line_exits_2_naming_it(tmp_path, capsys, monkeypatch):
    # `view MODEL --trace -`: samples from stdin; a bad line stops it with one line naming the line,
    # and the server it started is closed (no traceback)
    import io

    model = save_model(tmp_path / "m.npz", two_lungs(2))
    monkeypatch.setattr("sys.stdin", io.StringIO("t_s,amplitude\n0,1\n0.1,2\n0.2,oops\n"))
    assert main(["view", str(model), "--trace", "-", "--predict-ms", "300", "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "stdin line 4" in err[0], err


def test_view_gate_options_set_the_served_gate(tmp_path, capsys, monkeypatch):
    # --window/--confident/--coverage reach /trace.json: the gate's meta says them, and its beam
    # decisions are those of `stream --gate` with the same options (one gate, BeamGate)
    from lungdeform.cli import view

    t = np.arange(0.0, 40.0, 0.1)
    trace = write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t))
    model = save_model(tmp_path / "m.npz", two_lungs(2))
    monkeypatch.setattr(view, "ViewerServer", _Captured)
    opts = ["--predict-ms", "300", "--window", "end-inhale:20", "--confident", "--coverage", "0.8"]
    assert main(["view", str(model), "--trace", str(trace), *opts]) == 0
    gate = json.loads(_Captured.served["trace"])["trace"]["gate"]
    assert gate["window"] == "end-inhale:20" and gate["coverage"] == 0.8 and gate["rule"].startswith("whole 0.8")
    assert set(gate["window_high"]) == {None}  # end-inhale: open above
    capsys.readouterr()
    assert main(["stream", str(trace), "--gate", *opts]) == 0
    rows = [line.split(",") for line in capsys.readouterr().out.split()[1:]]
    assert [("on" if b else "off") for b in gate["beam_on"]] == [r[-1] for r in rows]
