"""``lungdeform stream``: one output line per input sample, predicted ahead on request."""

import io

import numpy as np

from lungdeform.cli.main import main
from tests.breathing.test_trace import breath, write_marker_csv


def test_stdin_samples_give_one_line_each_and_a_bad_line_is_named(monkeypatch, capsys):
    # 3 samples after a header → 3 lines after the output header; ahead_s says the horizon
    monkeypatch.setattr("sys.stdin", io.StringIO("t_s,x\n0,1\n0.1,1.2\n0.2,1.5\n"))
    assert main(["stream", "--predict-ms", "300"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out[0] == "t_s,volume_ml,ahead_s" and len(out) == 4 and out[-1].endswith(",0.3")
    monkeypatch.setattr("sys.stdin", io.StringIO("0,1\n0.1,abc\n"))
    assert main(["stream"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "stdin line 2" in err[0]


def test_replayed_trace_with_prediction_leads_the_plain_stream(tmp_path, capsys):
    # a regular breath replayed: the volume predicted 400 ms ahead reaches each end-inhale earlier
    # than the plain estimate (truth: the prediction is for t + 0.4 s)
    t = np.arange(0, 80, 0.1)
    path = write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t))
    rows = {}
    for h in ("0", "400"):
        assert main(["stream", str(path), "--predict-ms", h]) == 0
        rows[h] = np.array([[float(v) for v in line.split(",")] for line in capsys.readouterr().out.split()[1:]])
    late = rows["0"][:, 0] > 50
    lag = [np.argmax(np.correlate(rows["400"][late, 1] - rows["400"][late, 1].mean(),
                                  rows["0"][late, 1] - rows["0"][late, 1].mean(), "full")) - (late.sum() - 1)]
    assert -6 <= lag[0] <= -2  # the predicted stream leads by about 4 samples of 0.1 s


def test_an_absurd_amplitude_is_refused_naming_its_line_or_sample(tmp_path, monkeypatch, capsys):
    # why: amplitudes of ±1e308 overflow the calibration's span and printed nan/inf volumes with
    # exit 0; a sample beyond ±MAX_SAMPLE is refused, naming the stdin line or the trace's sample
    monkeypatch.setattr("sys.stdin", io.StringIO("0,1\n0.1,-1e308\n0.2,1e308\n"))
    assert main(["stream"]) == 2
    captured = capsys.readouterr()
    assert "nan" not in captured.out and "inf" not in captured.out
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "stdin line 2" in err[0] and "-1e+308" in err[0], err
    t = np.arange(0, 20, 0.1)
    amplitude = 8 * breath(t)
    amplitude[50] = 1e12
    path = write_marker_csv(tmp_path / "b.csv", t * 1000, amplitude)
    assert main(["stream", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path} sample " in err[0] and "beyond" in err[0], err


def test_stream_and_view_share_the_predict_ms_bound(capsys):
    # why: the viewer refused --predict-ms above 2000 while stream took up to 5000; one constant,
    # one message for both
    from lungdeform.breathing.stream import MAX_PREDICT_MS

    lines = []
    for words in (["stream"], ["view", "m.npz"]):
        assert main([*words, "--predict-ms", f"{MAX_PREDICT_MS + 1:g}"]) == 2
        lines += capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and lines[0] == lines[1] and f"[0, {MAX_PREDICT_MS:g}] ms" in lines[0], lines


def test_gate_prints_the_beam_with_the_interval_and_needs_a_latency(tmp_path, capsys):
    # a regular breath replayed with --gate: every line carries the prediction, its interval (lo <= hi
    # once learned), the window and on/off; the beam is on for part of each breath only
    t = np.arange(0, 80, 0.1)
    path = write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t))
    assert main(["stream", str(path), "--predict-ms", "300", "--gate"]) == 0
    lines = capsys.readouterr().out.split()
    assert lines[0] == "t_s,volume_ml,ahead_s,predicted,lo,hi,window_low,window_high,beam"
    rows = [line.split(",") for line in lines[1:]]
    assert len(rows) == t.size
    late = [r for r in rows if float(r[0]) > 40]
    assert all(float(r[4]) <= float(r[3]) <= float(r[5]) for r in late)
    beams = {r[-1] for r in late}
    assert beams == {"on", "off"}
    assert main(["stream", str(path), "--gate"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--predict-ms" in err[0]


def test_stream_tidal_ml_and_its_old_name(tmp_path, capsys):
    # --tidal-ml names the volume of one breath, as in build, export and track; the old name
    # --tidal-volume-ml still works (hidden). Truth: with --v-ee-ml 0 the volume is tidal × the
    # calibrated fraction, so 600 mL gives 1.2 × the default 500 mL's volumes, sample by sample
    t = np.arange(0, 30, 0.1)
    path = write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t))
    rows = {}
    for args in ((), ("--tidal-ml", "600"), ("--tidal-volume-ml", "600")):
        assert main(["stream", str(path), "--v-ee-ml", "0", *args]) == 0
        captured = capsys.readouterr()
        rows[args[:1]] = np.array([float(line.split(",")[1]) for line in captured.out.split()[1:]])
        assert ("note: --tidal-volume-ml is now --tidal-ml" in captured.err) == (args[:1] == ("--tidal-volume-ml",))
    assert np.ptp(rows[()]) > 100
    np.testing.assert_allclose(rows[("--tidal-ml",)], 1.2 * rows[()], rtol=1e-9, atol=1e-3)
    np.testing.assert_array_equal(rows[("--tidal-volume-ml",)], rows[("--tidal-ml",)])
    assert main(["stream", "--help"]) == 0
    assert "--tidal-volume-ml" not in capsys.readouterr().out
