"""Trace readers: formats, header variants, bad input, resampling and cycle splitting."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import require_path
from lungdeform.errors import InputError, ReadError
from lungdeform.trace import cycle_anchors, read_trace, resample


def breath(t, period=4.0):
    """A breath with a long end-exhale dwell: onsets at k·period, inhale positive, 0..1."""
    ph = np.mod(t, period) / period
    return np.where(ph < 0.6, np.sin(np.pi * ph / 0.6) ** 2, 0.0) ** 1.5


def write_marker_csv(path, t_ms, signal_mm, header='"Frame";"Timestamp";"x";"y";"z"', sep=";",
                     decimal_comma=True, terminator=True, direction=(0.3, 0.1, -0.95)):
    d = np.asarray(direction) / np.linalg.norm(direction)
    base = np.array([-396.9, 5.1, 85.6])
    lines = [header]
    for i, (tm, s) in enumerate(zip(t_ms, signal_mm)):
        p = base + s * d
        vals = [str(6 * i), f"{tm:g}"] + [f"{x:.3f}" for x in p]
        row = sep.join(vals)
        if decimal_comma:
            row = row.replace(".", ",")
        lines.append(row)
    if terminator:
        lines.append(sep.join(["0"] * 5))
    path.write_text("\r\n".join(lines) + "\r\n")
    return path


def write_vxp(path, t_ms, amp, marks, layout="amplitude,phase,timestamp,validflag,ttlin,mark,ttlout"):
    cols = layout.split(",")
    lines = ["[Header]", "CRC=1", "Version=1.6", f"Data_layout={layout}", "Samples_per_second=25",
             "Scale_factor=10.0", "[Data]"]
    for tm, a, m in zip(t_ms, amp, marks):
        row = {"amplitude": f"{a:.4f}", "phase": "0", "timestamp": f"{tm:.0f}", "validflag": "0",
               "ttlin": "1", "mark": m, "ttlout": "0"}
        lines.append(",".join(row[c] for c in cols))
    path.write_text("\r\n".join(lines) + "\r\n")
    return path


def test_marker_csv_decimal_commas_terminator_and_sign(tmp_path):
    t = np.arange(0.0, 40.0, 0.1)
    s = 12.0 * breath(t)
    f = write_marker_csv(tmp_path / "m.csv", t * 1000, s, direction=(0.3, 0.1, -0.95))
    tr = read_trace(f)
    assert tr.n == t.size  # terminator dropped
    assert any("terminator" in x for x in tr.fixes)
    assert tr.unit == "mm" and tr.source == "m.csv"
    assert np.allclose(tr.t_s, t)
    # amplitude = displacement along the motion axis, inhale positive (the truth s up to an offset)
    assert np.allclose(tr.amplitude - tr.amplitude.mean(), s - s.mean(), atol=2e-3)
    assert tr.positions.shape == (t.size, 3)


@pytest.mark.parametrize("header,sep,comma", [
    ("Frame;Timestamp(ms);x;y;z", ";", True),
    ("frame;time;X;Y;Z", ";", True),
    ("Frame,Timestamp (ms),x,y,z", ",", False),
    ("Frame\tTimestamp\tx\ty\tz", "\t", True),
])
def test_marker_csv_header_variants(tmp_path, header, sep, comma):
    t = np.arange(0.0, 20.0, 0.1)
    f = write_marker_csv(tmp_path / "v.csv", t * 1000, 10 * breath(t), header=header, sep=sep,
                         decimal_comma=comma, terminator=False)
    tr = read_trace(f)
    assert tr.n == t.size and np.allclose(tr.t_s, t)
    assert np.ptp(tr.amplitude) == pytest.approx(10.0, rel=1e-3)


def test_vxp_parses_marks_and_layout(tmp_path):
    t = np.arange(0.0, 20.0, 0.04)
    a = 0.5 * breath(t)
    marks = np.full(t.size, "", dtype=object)
    marks[np.searchsorted(t, [4.0, 8.0, 12.0])] = "Z"
    marks[np.searchsorted(t, [5.2, 9.2])] = "P"
    f = write_vxp(tmp_path / "r.vxp", 185666 + t * 1000, a, marks)
    tr = read_trace(f)
    assert tr.unit == "cm" and np.allclose(tr.amplitude, np.round(a, 4))
    assert np.allclose(tr.t_s, t, atol=1e-3)
    assert np.allclose(tr.mark_times("Z"), [4.0, 8.0, 12.0], atol=1e-3)
    # another column order, declared in the header
    g = write_vxp(tmp_path / "r2.vxp", 1000 + t * 1000, a, marks, layout="timestamp,amplitude,mark")
    tr2 = read_trace(g)
    assert np.allclose(tr2.amplitude, tr.amplitude) and (tr2.marks == tr.marks).all()
    an = cycle_anchors(tr)
    assert an.source.startswith("recorded") and an.n_cycles == 2
    assert np.allclose(an.peaks_s, [5.2, 9.2], atol=1e-3)


def test_out_of_order_timestamps_refused_or_dropped(tmp_path):
    t_ms = np.arange(0.0, 30000.0, 100.0)
    t_bad = t_ms.copy()
    t_bad[50] = 25.6  # a corrupted timestamp as in the real marker files
    f = write_marker_csv(tmp_path / "bad.csv", t_bad, 10 * breath(t_ms / 1000))
    with pytest.raises(InputError, match=r"bad\.csv, line 52: timestamp 25\.6 ms is not after"):
        read_trace(f, repair=False)
    tr = read_trace(f)
    assert tr.n == t_ms.size - 1
    assert any("out of order (lines 52)" in x for x in tr.fixes)
    assert np.all(np.diff(tr.t_s) > 0)


def test_too_many_bad_rows_refused(tmp_path):
    t_ms = np.arange(0.0, 30000.0, 100.0)
    t_bad = t_ms.copy()
    t_bad[10:30] = 5.0
    f = write_marker_csv(tmp_path / "many.csv", t_bad, 10 * breath(t_ms / 1000))
    with pytest.raises(InputError, match="many.csv: 20 of 300 rows are bad"):
        read_trace(f)


def test_nan_rows(tmp_path):
    t = np.arange(0.0, 20.0, 0.04)
    a = 0.5 * breath(t)
    a[100] = np.nan
    f = write_vxp(tmp_path / "n.vxp", t * 1000, a, [""] * t.size)
    text = f.read_text().replace("nan", "")
    f.write_text(text)
    with pytest.raises(InputError, match=r"n\.vxp, line 108: missing or NaN"):
        read_trace(f, repair=False)
    tr = read_trace(f)
    assert tr.n == t.size - 1 and np.all(np.isfinite(tr.amplitude))


def test_gap_refused_on_resampling(tmp_path):
    t = np.concatenate([np.arange(0, 10, 0.1), np.arange(13, 30, 0.1)])
    f = write_marker_csv(tmp_path / "gap.csv", t * 1000, 10 * breath(t), terminator=False)
    tr = read_trace(f)
    with pytest.raises(InputError, match=r"gap\.csv: gap of 3\.10 s at t = 9\.90 s"):
        resample(tr, 10.0)
    u = resample(tr, 10.0, max_gap_s=5.0)
    assert any("interpolated across gaps" in x for x in u.fixes)
    assert np.allclose(np.diff(u.t_s), 0.1)


def test_too_short_for_one_cycle(tmp_path):
    t = np.arange(0.0, 3.0, 0.1)
    f = write_marker_csv(tmp_path / "short.csv", t * 1000, 10 * breath(t), terminator=False)
    with pytest.raises(InputError, match="short.csv: .*too short to hold one breathing cycle"):
        cycle_anchors(read_trace(f))


def test_malformed_files(tmp_path):
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(ReadError, match="empty.csv: file is empty"):
        read_trace(tmp_path / "empty.csv")
    (tmp_path / "cols.csv").write_text("Frame;Time;a;b\n0;0;1;2\n")
    with pytest.raises(ReadError, match=r"cols.csv, line 1: header .* lacks column\(s\) x, y, z"):
        read_trace(tmp_path / "cols.csv")
    (tmp_path / "word.csv").write_text("Frame;Timestamp;x;y;z\n0;0;1;2;3\n1;100;abc;2;3\n")
    with pytest.raises(ReadError, match=r"word.csv, line 3: column 'x' is not a number"):
        read_trace(tmp_path / "word.csv")
    (tmp_path / "x.vxp").write_text("[Header]\nVersion=1.6\n")
    with pytest.raises(ReadError, match=r"x.vxp: no \[Data\] section"):
        read_trace(tmp_path / "x.vxp")
    with pytest.raises(ReadError, match="unknown trace format"):
        read_trace(tmp_path / "trace.dat")
    with pytest.raises(ReadError, match="no such file"):
        read_trace(tmp_path / "missing.csv")


def test_detected_cycles_match_truth(tmp_path, rng):
    # truth: onsets at k·4 s (+ seeded noise); peak of each breath at onset + 1.8 s
    t = np.arange(0.0, 60.0, 0.1)
    s = 10 * breath(t) + rng.normal(0, 0.05, t.size)
    f = write_marker_csv(tmp_path / "c.csv", t * 1000, s, terminator=False)
    an = cycle_anchors(resample(read_trace(f), 10.0))
    k = np.rint(an.starts_s / 4.0)
    # the 5 % onset level sits a little after the true onset (the rise is smooth): < 0.4 s
    assert np.all((an.starts_s - 4.0 * k >= 0) & (an.starts_s - 4.0 * k < 0.4))
    assert np.allclose(np.diff(an.starts_s), 4.0, atol=0.15)
    assert np.allclose(an.peaks_s - 4.0 * k[:-1], 1.2, atol=0.15)


def test_real_traces_read(data_dir):
    rpm = require_path(data_dir, "breathing-traces", "rpm", "PT01_PT09-2_13112021.vxp")
    tr = read_trace(rpm)
    # README: 25 Hz, 153 s, about 25 breaths, with P and Z marks
    assert tr.duration_s == pytest.approx(152.8, abs=0.5)
    assert (tr.marks == "P").sum() == 25 and (tr.marks == "Z").sum() == 25
    markers = require_path(data_dir, "breathing-traces", "external-markers")
    f = markers / "201205101534-UAC-1-NO-130-6.csv"
    m = read_trace(f)
    # this file holds 5 corrupted timestamps (e.g. "25,6" among 12700, 13017 ms) and a terminator
    assert any("out of order" in x for x in m.fixes) and any("terminator" in x for x in m.fixes)
    assert np.all(np.diff(m.t_s) > 0) and m.duration_s == pytest.approx(129.6, abs=0.5)
