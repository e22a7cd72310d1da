"""Trace readers: formats, header variants, bad input, orientation and resampling."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.breathing.cycles import cycle_anchors, dominant_period, inspiratory_share, mark_agreement
from lungdeform.breathing.trace import read_trace, resample
from lungdeform.errors import InputError, ReadError
from tests.conftest import require_path


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


def write_marker_folder(folder, rng):
    """A folder of one 80 s marker trace (8 mm breaths of :func:`breath`, 0.1 mm noise), named as the
    shared traces are: what the validate commands read."""
    folder.mkdir()
    t = np.arange(0, 80, 0.1)
    write_marker_csv(folder / "201201010000-LAC-1-N-80-6.csv", t * 1000, 8 * breath(t) + rng.normal(0, 0.1, t.size))
    return folder


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


def asymmetric_breath(t, period=4.0, ti=0.35):
    """Inhale-positive breath with no end-exhale dwell: a rise over ``ti`` of the period, then a
    slower fall; only its timing (inspiration shorter) tells its sign."""
    ph = np.mod(t, period) / period
    return np.where(ph < ti, np.sin(0.5 * np.pi * ph / ti) ** 2, np.cos(0.5 * np.pi * (ph - ti) / (1 - ti)) ** 2)


@pytest.mark.parametrize("direction", [(0.3, 0.1, -0.95), (-0.3, -0.1, 0.95)])
def test_marker_csv_decimal_commas_terminator_and_sign(tmp_path, direction):
    t = np.arange(0.0, 40.0, 0.1)
    s = 12.0 * breath(t)
    f = write_marker_csv(tmp_path / "m.csv", t * 1000, s, direction=direction)
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


@pytest.mark.parametrize("header,scale", [
    ("Frame;Timestamp (s);x;y;z", 1.0),       # an explicit unit beats the "timestamp means ms" default
    ("Frame;Timestamp [s];x;y;z", 1.0),
    ("Frame;Timestamp (ms);x;y;z", 1000.0),
    ("frame;time_ms;x_mm;y_mm;z_mm", 1000.0),  # units as name suffixes
    ("frame;t_s;x_mm;y_mm;z_mm", 1.0),
])
def test_marker_csv_time_unit_from_the_time_column(tmp_path, header, scale):
    # truth: a 30 s trace at 10 Hz written in the unit its header names; read back in seconds
    # (before, "Timestamp (s)" was read as ms: a 0.03 s trace, refused as too short)
    t = np.arange(0.0, 30.0, 0.1)
    f = write_marker_csv(tmp_path / "u.csv", t * scale, 10 * breath(t), header=header, terminator=False)
    tr = read_trace(f)
    assert tr.n == t.size and np.allclose(tr.t_s, t)
    assert not any("unit not given" in x for x in tr.fixes)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_orientation_from_timing_alone(tmp_path, sign):
    # truth: an inhale-positive breath without dwell (rise 35 %, fall 65 % of the period), written
    # with either sign along the marker axis; the reader must return it inhale-positive both times
    t = np.arange(0.0, 48.0, 0.1)
    s = 10.0 * asymmetric_breath(t)
    f = write_marker_csv(tmp_path / "a.csv", t * 1000, sign * s, direction=(0.2, 0.0, 1.0))
    tr = read_trace(f)
    assert np.allclose(tr.amplitude - tr.amplitude.mean(), s - s.mean(), atol=2e-3)
    share, n = inspiratory_share(tr.t_s, tr.amplitude)
    assert share == pytest.approx(0.35, abs=0.05) and n >= 8
    # orient=False keeps the sign of the principal axis: the raw projection, whatever it is
    raw = read_trace(f, orient=False)
    assert np.allclose(np.abs(np.corrcoef(raw.amplitude, s)[0, 1]), 1.0)


def test_vxp_falling_on_inhalation_is_negated_and_marks_swapped(tmp_path):
    # truth: an RPM amplitude that falls on inhalation (as in the shared .vxp: 'Z' at the sharp minima);
    # the reader negates it, relabels the marks (P = end-inhale), and says so in the fixes
    t = np.arange(0.0, 48.0, 0.04)
    s = 0.5 * asymmetric_breath(t)
    marks = np.full(t.size, "", dtype=object)
    ends_inhale = np.arange(0.35 * 4.0, 48.0, 4.0)
    marks[np.searchsorted(t, ends_inhale - 1e-9)] = "Z"  # at the minima of the recorded amplitude
    marks[np.searchsorted(t, np.arange(4.0, 48.0, 4.0) - 1e-9)] = "P"
    f = write_vxp(tmp_path / "inv.vxp", t * 1000, -s, marks)
    tr = read_trace(f)
    assert np.allclose(tr.amplitude, np.round(s, 4), atol=1e-4)
    assert any("negated" in x and "P/Z marks swapped" in x for x in tr.fixes)
    assert np.allclose(tr.mark_times("P"), ends_inhale, atol=0.03)
    raw = read_trace(f, orient=False)
    assert np.allclose(raw.amplitude, np.round(-s, 4)) and not any("negated" in x for x in raw.fixes)
    # recorded marks vs detected anchors: end-inhale marks on the detected peaks
    u = resample(tr, 25.0)
    agree = mark_agreement(u, cycle_anchors(u))
    # (the marks at the first and the last breath lie outside the complete cycles: 10 of 12 inside)
    assert agree["P"]["n"] == 12 and agree["P"]["within_0.5_s"] >= 10 / 12
    assert agree["P"]["median_abs_offset_s"] < 0.08


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
    an = cycle_anchors(tr, use_marks=True)
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


@pytest.mark.realdata
def test_real_traces_orientation_and_cycles(data_dir):
    # real data, two independent truths for the sign. (1) All 15 marker files share one camera frame
    # (same mean positions per marker across sessions): on inhalation the chest and abdomen rise, so
    # every marker must move the same way, +z, once oriented — the principal-axis sign alone had two
    # of them (LT session, upper markers) upside down. (2) The RPM's 'Z' marks (phase 0), relabelled
    # 'P' by the flip, must sit on the detected end-inhale peaks.
    markers = require_path(data_dir, "breathing-traces", "external-markers")
    for f in sorted(markers.glob("*.csv")):
        tr = read_trace(f)
        x = tr.positions - tr.positions.mean(axis=0)
        axis = np.linalg.lstsq(x, tr.amplitude - tr.amplitude.mean(), rcond=None)[0]
        assert axis[2] > 0, f.name
        share, n = inspiratory_share(tr.t_s, tr.amplitude)
        assert share < 0.45 and n >= 18, (f.name, share, n)
        u = resample(tr, 10.0)
        an = cycle_anchors(u)
        # about one breath per dominant period (5.4–6.7 s here): detection neither merges nor splits
        assert an.n_cycles == pytest.approx(tr.duration_s / dominant_period(u.t_s, u.amplitude), rel=0.25)
    rpm = read_trace(require_path(data_dir, "breathing-traces", "rpm", "PT01_PT09-2_13112021.vxp"))
    assert any("negated" in x for x in rpm.fixes)
    u = resample(rpm, 25.0)
    agree = mark_agreement(u, cycle_anchors(u))
    # (the RPM locates its marks its own way: measured median offset 0.16 s, 19 of 25 within 0.5 s;
    # before the flip the 'P' marks fell 0.8 s from any end-inhale)
    assert agree["P"]["median_abs_offset_s"] < 0.25 and agree["P"]["within_0.5_s"] >= 0.7


# --------------------------------------------------------------------------- file-format variants
def _vxp_variant(text: str, kind: str) -> bytes:
    """One realistic variant of a VXP 1.6 text (same samples), as bytes."""
    import re

    if kind == "v17_extra_keys_crlf":
        text = text.replace("Version=1.6", "Version=1.7\r\nSoftware=RPM 1.7.5\r\nGating=Amplitude\r\nComment=a=b")
    elif kind == "no_header_keys":
        text = re.sub(r"\[Header\].*?\[Data\]", "[Header]\r\n[Data]", text, flags=re.S)
    elif kind == "no_header_section":
        text = text[text.index("[Data]"):]
    elif kind == "lowercase_sections_lf":
        text = text.replace("[Data]", "[data]").replace("[Header]", "[header]").replace("\r\n", "\n")
    elif kind == "no_marks":
        text = re.sub(r",[PZ],", ",,", text)
    elif kind == "latin1_header":
        return text.replace("CRC=1", "CRC=1\r\nPatient_name=Müller").encode("latin-1")
    elif kind == "truncated_last_row":
        text = text.rstrip() + "\r\n0.2617,3.07"
    elif kind == "blank_tail":
        text = text + "\r\n\r\n\r\n"
    return text.encode()


VXP_KINDS = ["v17_extra_keys_crlf", "no_header_keys", "no_header_section", "lowercase_sections_lf", "no_marks",
             "latin1_header", "truncated_last_row", "blank_tail"]


@pytest.mark.parametrize("kind", VXP_KINDS)
def test_vxp_variants_read_the_same_samples(tmp_path, kind):
    t = np.arange(0, 60, 0.04)
    amp = 0.5 * breath(t)
    marks = np.where(np.isin(np.arange(t.size), np.searchsorted(t, np.arange(1.8, 60, 4.0))), "P", "")
    base = read_trace(write_vxp(tmp_path / "base.vxp", 1e5 + t * 1000, amp, marks), orient=False)
    f = tmp_path / ("VARIANT.VXP" if kind == "no_header_keys" else "variant.vxp")
    f.write_bytes(_vxp_variant((tmp_path / "base.vxp").read_text(), kind))
    tr = read_trace(f, orient=False)
    # truth: the same file's samples, whatever the header, line endings or encoding
    np.testing.assert_allclose(tr.t_s, base.t_s)
    np.testing.assert_allclose(tr.amplitude, base.amplitude)
    assert (tr.marks != "").sum() == (0 if kind == "no_marks" else (base.marks != "").sum())
    if kind == "truncated_last_row":
        assert any("truncated last row" in x for x in tr.fixes)
    # an unmarked trace still splits into its breaths (marks are not needed)
    assert cycle_anchors(tr).n_cycles >= 12


@pytest.mark.parametrize("kind", ["dot_decimals", "comma_sep_dot", "tabs_comma", "no_terminator", "bom", "utf16",
                                  "comment_preamble", "units_header", "trailing_sep", "truncated_last_row"])
def test_marker_csv_variants_read_the_same_motion(tmp_path, kind):
    t = np.arange(0, 60, 0.1)
    sig = 12 * breath(t)
    base = read_trace(write_marker_csv(tmp_path / "base.csv", t * 1000, sig), orient=False)
    f = tmp_path / "201205101541-XYZ-2-Q-60-6.csv"  # another marker tag and session letters
    kw = {}
    if kind == "dot_decimals":
        kw = dict(decimal_comma=False)
    elif kind == "comma_sep_dot":
        kw = dict(sep=",", decimal_comma=False, header="Frame,Timestamp,x,y,z")
    elif kind == "tabs_comma":
        kw = dict(sep="\t", header="Frame\tTimestamp\tx\ty\tz")
    elif kind == "no_terminator":
        kw = dict(terminator=False)
    elif kind == "units_header":
        kw = dict(header="Frame;Time (ms);X [mm];Y [mm];Z [mm]")
    write_marker_csv(f, t * 1000, sig, **kw)
    text = f.read_text()
    if kind == "bom":
        f.write_bytes(b"\xef\xbb\xbf" + text.encode())
    elif kind == "utf16":
        f.write_bytes(text.encode("utf-16"))
    elif kind == "comment_preamble":
        f.write_text("# exported by the tracker, 10 Hz\r\n" + text)
    elif kind == "trailing_sep":
        f.write_text("".join(ln + ";\r\n" for ln in text.splitlines()))
    elif kind == "truncated_last_row":
        f.write_text(text.rsplit("\r\n0;0;0;0;0", 1)[0] + "\r\n3606;60")
    tr = read_trace(f, orient=False)
    # truth: the same samples and the same principal-axis motion as the canonical file
    np.testing.assert_allclose(tr.t_s, base.t_s)
    np.testing.assert_allclose(tr.amplitude, base.amplitude, atol=2e-3)
    assert np.ptp(tr.amplitude) == pytest.approx(12.0, rel=0.01)
    if kind == "truncated_last_row":
        assert any("truncated last row" in x for x in tr.fixes)


def test_degenerate_files_refused_in_one_line(tmp_path):
    t = np.arange(0, 5, 0.1)
    cases = {
        "empty.csv": (b"", "file is empty"),
        "blank.vxp": (b"\r\n  \r\n", "file is empty"),
        "header_only.csv": (b'"Frame";"Timestamp";"x";"y";"z"\r\n', "no data rows after the header"),
        "terminator_only.csv": (b"Frame;Timestamp;x;y;z\r\n0;0;0;0;0\r\n", "no data rows besides the terminator"),
        "two_rows.csv": (b"Frame;Timestamp;x;y;z\n0;0;1;2;3\n6;100;1;2;4\n", "only 2 data row"),
        "comments_only.csv": (b"# nothing\n# here\n", "only comments"),
        "header_only.vxp": (b"[Header]\r\nVersion=1.7\r\n[Data]\r\n", r"\[Data\] section holds no rows"),
        "binary.csv": (b"\x00\x01\x02Frame", "binary file"),
        "mid_truncated.vxp": (b"[Data]\n0.1,0,0,0,1,,0\n0.2,0\n0.3,0,80,0,1,,0\n", "line 3: expected 7 comma-separated"),
    }
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises((ReadError, InputError)) as exc:
            read_trace(tmp_path / name)
        msg = str(exc.value)
        assert name in msg and len(msg.splitlines()) == 1, msg
        assert __import__("re").search(message, msg), msg
    # one breath only: read, then refused when cycles are needed, naming the file
    one = write_marker_csv(tmp_path / "one_breath.csv", t * 1000, 10 * breath(t, period=4.5))
    with pytest.raises(InputError, match="one_breath.csv: .*too short"):
        cycle_anchors(read_trace(one))


@pytest.mark.realdata
def test_real_trace_variants_keep_their_cycles(data_dir, tmp_path):
    # the real RPM file and one marker file, rewritten (in tmp_path) as other exporter versions:
    # each must give exactly the samples and the cycles of the original
    import re

    src = require_path(data_dir, "breathing-traces")
    rpm = next((src / "rpm").glob("*.vxp"))
    mk = sorted((src / "external-markers").glob("*.csv"))[3]
    orig = {"vxp": read_trace(rpm), "csv": read_trace(mk)}
    vtext, ctext = rpm.read_text(), mk.read_bytes().decode()
    variants = {
        "a.VXP": ("vxp", vtext.replace("Version=1.6", "Version=1.7\nExtra_key=1").replace("\n", "\r\n").encode()),
        "b.vxp": ("vxp", re.sub(r",[PZ],", ",,", vtext[vtext.index("[Data]"):]).encode()),
        "c.csv": ("csv", b"\xef\xbb\xbf" + ctext.replace(",", ".").rsplit("0;0;0;0;0", 1)[0].encode()),
        "d.CSV": ("csv", ctext.replace(",", ".").replace(";", ",").encode()),
    }
    for name, (kind, content) in variants.items():
        (tmp_path / name).write_bytes(content)
        tr = read_trace(tmp_path / name)
        np.testing.assert_allclose(tr.t_s, orig[kind].t_s)
        np.testing.assert_allclose(tr.amplitude, orig[kind].amplitude, atol=1e-9)
        n = [cycle_anchors(resample(x, 10.0, max_gap_s=5.0)).n_cycles for x in (tr, orig[kind])]
        assert n[0] == n[1] >= 15, name  # ≈ 25 (RPM) and ≈ 19 (markers) breaths


def test_a_timestamp_far_off_is_refused_by_row(tmp_path):
    # found by the fuzzer: one timestamp 78 000 000 s late in a 25 Hz trace made every uniform-grid
    # step (orientation, cycles) build billions of samples (a ValueError from numpy, or minutes and
    # gigabytes); the trace is refused, naming the row after the jump. A real gap of a few minutes,
    # within GAP_FACTOR × the samples, is kept (truth: its rows are all read)
    t = np.arange(0, 60_000, 40.0)
    amp = breath(t / 1000.0)
    t_bad = t.copy()
    t_bad[900:] += 7.8e10
    path = write_vxp(tmp_path / "jump.vxp", t_bad, amp, [""] * len(t))
    with pytest.raises(InputError, match=r"jump.vxp, line 908: timestamps span .* a timestamp is wrong"):
        read_trace(path)
    t_gap = t.copy()
    t_gap[900:] += 300_000.0  # a 5-minute pause in the recording
    assert read_trace(write_vxp(tmp_path / "gap.vxp", t_gap, amp, [""] * len(t))).n == len(t)
