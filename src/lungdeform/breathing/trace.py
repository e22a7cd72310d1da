"""Breathing surrogate traces: readers, checks, orientation and resampling (cycle splitting:
:mod:`lungdeform.breathing.cycles`).

Two formats (see ../shared/data/README.md, breathing-traces rows):

- Varian RPM ``.vxp`` (1.x): ``[Header]`` ``key=value`` lines, then ``[Data]`` rows in the order given by
  ``Data_layout`` (default ``amplitude,phase,timestamp,validflag,ttlin,mark,ttlout``); amplitude in cm,
  timestamp in ms; ``mark`` is ``P`` or ``Z`` (the RPM's own marks at the two extremes of the
  amplitude; ``Z`` = phase 0).
- External-marker ``.csv``: ``Frame;Timestamp(ms);x;y;z`` (header names may be quoted or carry
  units), ``;`` separator with decimal commas (a ``,``-separated file with decimal points is read too),
  positions in mm, and a ``0;0;0;0;0`` terminator row that is dropped. The breathing amplitude is
  the projection on the first principal axis of the 3-D motion.

Orientation (both formats, ``orient=True``): a breathing amplitude is returned inhalation-positive.
The sign of a principal axis is arbitrary, and an RPM amplitude may fall on inhalation (the file in
../shared/data does: its ``Z`` marks sit at the sharp amplitude minima, i.e. at end-inhale). The rule,
one for every trace: inspiration — from the end of the end-exhale dwell to end-inhale — is the
shorter part of a breath (T_i/T_tot ≈ 0.35–0.45 at rest), so of the two signs the one whose median
onset-to-peak share of the breath (:func:`lungdeform.breathing.cycles.inspiratory_share`) is smaller is kept.
Measured on the 16 real traces (as read): 0.30–0.37 for the kept sign, 0.50–0.59 for the other. A flip
is recorded in :attr:`Trace.fixes` and RPM marks are relabelled with it, so that on a :class:`Trace`
``P`` always marks end-inhale (a maximum) and ``Z`` end-exhale.

Bad input: unreadable numbers, NaNs, timestamps that go backwards, gaps, too-short traces. Readers
refuse with :class:`ReadError` / :class:`InputError` naming the file and line, unless ``repair=True``
(the default) where *isolated* bad rows (a NaN row, a corrupted out-of-order timestamp) are dropped
and every fix is recorded in :attr:`Trace.fixes`; more than ``max_fix_fraction`` of the rows bad, or a
gap longer than ``max_gap_s`` once resampled, is refused.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lungdeform.errors import InputError, ReadError

from .cycles import CYCLE_RANGE_S, inspiratory_shares

VXP_DEFAULT_LAYOUT = ("amplitude", "phase", "timestamp", "validflag", "ttlin", "mark", "ttlout")


@dataclass(frozen=True)
class Trace:
    """A breathing surrogate signal.

    t_s : (n,) float, s, strictly increasing, starting at 0; amplitude : (n,) float, in ``unit``
    (inhalation positive); marks : (n,) str, '' / 'P' (end-inhale) / 'Z' (end-exhale) as recorded;
    source : file name; unit : 'cm', 'mm', 'mL' …; fixes : what the reader repaired, one line each;
    positions : (n, 3) float mm or None (markers: the raw 3-D position).
    """

    t_s: np.ndarray
    amplitude: np.ndarray
    unit: str
    marks: np.ndarray
    source: str = ""
    fixes: tuple = ()
    positions: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self):
        t = np.ascontiguousarray(self.t_s, dtype=float)
        a = np.ascontiguousarray(self.amplitude, dtype=float)
        marks = np.asarray(self.marks, dtype="<U1")
        if t.ndim != 1 or a.shape != t.shape or marks.shape != t.shape:
            raise InputError(f"{self.source or 'trace'}: t_s, amplitude and marks must be (n,) of one length")
        for arr in (t, a, marks):
            arr.setflags(write=False)
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "amplitude", a)
        object.__setattr__(self, "marks", marks)

    @property
    def n(self) -> int:
        return int(self.t_s.size)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0]) if self.n else 0.0

    @property
    def sample_interval_s(self) -> float:
        return float(np.median(np.diff(self.t_s))) if self.n > 1 else float("nan")

    def mark_times(self, kind: str) -> np.ndarray:
        """Times (s) of the recorded marks of ``kind`` ('P' or 'Z')."""
        return self.t_s[self.marks == kind]


# --------------------------------------------------------------------------- reading
def read_trace(path, repair: bool = True, max_fix_fraction: float = 0.01, orient: bool = True) -> Trace:
    """Read a ``.vxp`` or marker ``.csv`` trace (dispatch on the extension); inhalation-positive
    unless ``orient=False`` (see the module doc)."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".vxp":
        return read_vxp(p, repair=repair, max_fix_fraction=max_fix_fraction, orient=orient)
    if ext in (".csv", ".txt"):
        return read_marker_csv(p, repair=repair, max_fix_fraction=max_fix_fraction, orient=orient)
    raise ReadError(f"{p}: unknown trace format '{ext}' (expected .vxp or .csv)")


def _read_lines(path: Path) -> list[str]:
    if not path.is_file():
        raise ReadError(f"{path}: no such file")
    raw = path.read_bytes()
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):  # UTF-16 with a byte-order mark ("Unicode text" exports)
        try:
            raw = raw.decode("utf-16").encode("utf-8")
        except UnicodeDecodeError as exc:
            raise ReadError(f"{path}: starts with a UTF-16 byte-order mark but is not UTF-16 text ({exc.reason})") from None
    if not raw.strip():
        raise ReadError(f"{path}: file is empty")
    if b"\x00" in raw:
        raise ReadError(f"{path}: binary file (NUL bytes), not a text trace")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return text.splitlines()


def _is_truncated_last(lines: list[str], i: int) -> bool:
    """True when line ``i`` is the last non-blank line of the data (a recording cut mid-row)."""
    return not any(ln.strip() for ln in lines[i + 1:])


def _number(text: str, path: Path, line: int, column: str, decimal_comma: bool) -> float:
    s = text.strip().strip('"')
    if decimal_comma:
        s = s.replace(",", ".")
    if s == "" or s.lower() in ("nan", "na", "null", "none", "-"):
        return float("nan")
    try:
        return float(s)
    except ValueError:
        raise ReadError(f"{path}, line {line}: column '{column}' is not a number: {text!r}") from None


def read_vxp(path, repair: bool = True, max_fix_fraction: float = 0.01, orient: bool = True) -> Trace:
    """Read a Varian RPM ``.vxp`` file. Amplitude in cm (``Scale_factor`` is reported, not applied);
    negated (and the P/Z marks swapped) when it falls on inhalation, unless ``orient=False``."""
    p = Path(path)
    lines = _read_lines(p)
    header: dict[str, str] = {}
    data_at = None
    for i, line in enumerate(lines):
        s = line.strip()
        if s.lower() == "[data]":
            data_at = i
            break
        if "=" in s and not s.startswith("["):
            k, v = s.split("=", 1)
            header[k.strip().lower()] = v.strip()
    if data_at is None:
        raise ReadError(f"{p}: no [Data] section: not a Varian RPM .vxp file")
    layout = tuple(x.strip().lower() for x in header.get("data_layout", ",".join(VXP_DEFAULT_LAYOUT)).split(","))
    for need in ("amplitude", "timestamp"):
        if need not in layout:
            raise ReadError(f"{p}: Data_layout lacks '{need}' (got {','.join(layout)})")
    ia, it = layout.index("amplitude"), layout.index("timestamp")
    im = layout.index("mark") if "mark" in layout else None
    rows_t, rows_a, rows_m, line_no, vxp_fixes = [], [], [], [], []
    for i in range(data_at + 1, len(lines)):
        s = lines[i].strip()
        if not s:
            continue
        if s.startswith("["):
            break
        parts = s.split(",")
        if len(parts) < max(ia, it) + 1:
            if repair and rows_t and _is_truncated_last(lines, i):
                vxp_fixes.append(f"dropped the truncated last row (line {i + 1}: {len(parts)} of {len(layout)} fields)")
                break
            raise ReadError(f"{p}, line {i + 1}: expected {len(layout)} comma-separated fields "
                            f"({','.join(layout)}), got {len(parts)}")
        rows_a.append(_number(parts[ia], p, i + 1, "amplitude", False))
        rows_t.append(_number(parts[it], p, i + 1, "timestamp", False))
        rows_m.append(parts[im].strip().upper()[:1] if im is not None and im < len(parts) else "")
        line_no.append(i + 1)
    if not rows_t:
        raise ReadError(f"{p}: [Data] section holds no rows")
    t_ms = np.array(rows_t)
    rows = _Rows(t_ms / 1000.0, np.array(rows_a), np.array(rows_m, dtype="<U1"), np.array(line_no))
    tr = _finish(p, rows, "cm", repair, max_fix_fraction, fixes=vxp_fixes)
    return orient_inhale_positive(tr) if orient else tr


_HEADER_ALIASES = {"frame": "frame", "timestamp": "timestamp", "time": "timestamp", "t": "timestamp",
                   "x": "x", "y": "y", "z": "z"}


def read_marker_csv(path, repair: bool = True, max_fix_fraction: float = 0.01, orient: bool = True) -> Trace:
    """Read an external-marker CSV (``Frame;Timestamp(ms);x;y;z``, decimal commas, terminator row).

    The amplitude is the displacement (mm) along the first principal axis of the 3-D motion, signed
    inhalation-positive by :func:`orient_inhale_positive` (``orient=False``: the sign of
    :func:`principal_motion`)."""
    p = Path(path)
    lines = [ln for ln in _read_lines(p)]
    # the header is the first line that is neither blank nor a '#' / '//' comment (exporter preamble)
    first = next((i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith(("#", "//"))), None)
    if first is None:
        raise ReadError(f"{p}: only comments, no header 'Frame;Timestamp(ms);x;y;z'")
    head = lines[first].strip()
    sep = ";" if ";" in head else ("\t" if "\t" in head else ",")
    decimal_comma = sep != ","
    raw_names = [h.strip().strip('"').strip("'").strip().lower() for h in head.split(sep)]
    # "Timestamp (ms)", "X [mm]", "time_ms", "x_mm": the name without its unit
    names = [re.sub(r"_(ms|s|sec|mm|cm|m)$", "", re.sub(r"\(.*?\)|\[.*?\]", "", h).strip()) for h in raw_names]
    cols = {}
    for j, nm in enumerate(names):
        key = _HEADER_ALIASES.get(nm)
        if key and key not in cols:
            cols[key] = j
    missing = [k for k in ("timestamp", "x", "y", "z") if k not in cols]
    if missing:
        raise ReadError(f"{p}, line {first + 1}: header {head!r} lacks column(s) {', '.join(missing)} "
                        "(expected Frame;Timestamp(ms);x;y;z)")
    # the time unit from the time column's own header: an explicit unit first, else "timestamp"
    # means ms (the marker files' convention), else it is guessed from the step below
    tl = raw_names[cols["timestamp"]]
    unit_ms = None
    if re.search(r"[(\[]\s*ms\s*[)\]]|_ms$", tl):
        unit_ms = True
    elif re.search(r"[(\[]\s*(s|sec|seconds?)\s*[)\]]|_(s|sec)$", tl):
        unit_ms = False
    elif "timestamp" in tl:
        unit_ms = True
    rows, line_no, trunc_fix = [], [], None
    for i in range(first + 1, len(lines)):
        s = lines[i].strip()
        if not s:
            continue
        parts = s.split(sep)
        if len(parts) < len(names):
            if repair and rows and _is_truncated_last(lines, i):
                trunc_fix = f"dropped the truncated last row (line {i + 1}: {len(parts)} of {len(names)} fields)"
                break
            raise ReadError(f"{p}, line {i + 1}: expected {len(names)} '{sep}'-separated fields, got {len(parts)}")
        rows.append([_number(parts[cols[k]], p, i + 1, k, decimal_comma) for k in ("timestamp", "x", "y", "z")])
        line_no.append(i + 1)
    if not rows:
        raise ReadError(f"{p}: no data rows after the header")
    arr = np.array(rows)
    line_no = np.array(line_no)
    fixes = [trunc_fix] if trunc_fix else []
    if np.all(arr[-1] == 0) and "frame" in cols:
        fixes.append(f"dropped the 0;0;0;0;0 terminator row (line {line_no[-1]})")
        arr, line_no = arr[:-1], line_no[:-1]
    elif np.all(arr[-1] == 0):
        fixes.append(f"dropped an all-zero last row (line {line_no[-1]}), taken as a terminator")
        arr, line_no = arr[:-1], line_no[:-1]
    if arr.shape[0] == 0:
        raise ReadError(f"{p}: no data rows besides the terminator")
    if arr.shape[0] < 3:
        raise ReadError(f"{p}: only {arr.shape[0]} data row(s): too few for a breathing trace")
    if unit_ms is None:  # a bare "time" column: a breathing trace is never sampled slower than 1 Hz
        dt = np.nanmedian(np.diff(arr[:, 0])) if arr.shape[0] > 1 else 0.0
        unit_ms = bool(dt >= 1.0)
        fixes.append(f"time column unit not given: read as {'ms' if unit_ms else 's'} (median step {dt:g})")
    t_s = arr[:, 0] / 1000.0 if unit_ms else arr[:, 0]
    pos = arr[:, 1:4]
    amp = np.full(arr.shape[0], np.nan)
    finite = np.all(np.isfinite(pos), axis=1)
    if finite.sum() >= 3:
        amp[finite] = principal_motion(pos[finite])
    marks = np.full(arr.shape[0], "", dtype="<U1")
    tr = _finish(p, _Rows(t_s, amp, marks, line_no, positions=pos), "mm", repair, max_fix_fraction, fixes=fixes)
    return orient_inhale_positive(tr) if orient else tr


def principal_motion(positions: np.ndarray, fit: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) mm positions -> (n,) mm displacement along the first principal axis.

    ``fit : (n,) bool`` (default all rows): the rows whose mean and principal axis define the
    projection (the held-out protocol of :mod:`lungdeform.breathing.holdout` passes its training
    part). The sign is a first guess only (the end-exhale dwell at the low end: median below mean,
    over the ``fit`` rows); the readers settle it with :func:`orient_inhale_positive`, which uses
    timing, not levels (on the real marker files this guess is wrong for 2 of 15)."""
    x = np.asarray(positions, dtype=float)
    rows = x if fit is None else x[np.asarray(fit, bool)]
    centre = rows.mean(axis=0)
    _, _, vt = np.linalg.svd(rows - centre, full_matrices=False)
    s = (x - centre) @ vt[0]
    ref = s if fit is None else s[np.asarray(fit, bool)]
    if np.median(ref) > np.mean(ref):  # end-exhale dwell must sit at the low end
        s = -s
    return s


@dataclass(frozen=True)
class _Rows:
    """The rows of a trace file as read, before repair: times ``t_s (n,)`` s, amplitudes ``amp (n,)``,
    marks ``(n,)`` str, source line numbers ``line_no (n,)`` int, optional ``positions (n, 3)``."""

    t_s: np.ndarray
    amp: np.ndarray
    marks: np.ndarray
    line_no: np.ndarray
    positions: np.ndarray | None = None


def _finish(path: Path, rows: _Rows, unit, repair, max_fix_fraction, fixes=None) -> Trace:
    t_s, amp, marks, line_no, positions = rows.t_s, rows.amp, rows.marks, rows.line_no, rows.positions
    fixes = list(fixes or [])
    n0 = t_s.size
    bad_lines: list[int] = []
    # NaN rows
    nan = ~np.isfinite(t_s) | ~np.isfinite(amp)
    if nan.any():
        where = ", ".join(str(x) for x in line_no[nan][:5])
        if not repair:
            raise InputError(f"{path}, line {line_no[nan][0]}: missing or NaN value "
                             f"({nan.sum()} row(s), lines {where}...); pass repair=True to drop them")
        fixes.append(f"dropped {nan.sum()} row(s) with NaN/missing values (lines {where}"
                     f"{'…' if nan.sum() > 5 else ''})")
        bad_lines += list(line_no[nan])
    keep = ~nan
    # timestamps that go backwards or repeat: keep the longest non-decreasing chain, greedily, by
    # dropping each row that is not after the last kept one *and* not before the next row.
    tk = t_s[keep]
    order_bad = np.zeros(tk.size, dtype=bool)
    if tk.size > 2:
        last = tk[0]
        for i in range(1, tk.size):
            nxt = tk[i + 1] if i + 1 < tk.size else np.inf
            if tk[i] <= last or (tk[i] > nxt and nxt > last):
                order_bad[i] = True
            else:
                last = tk[i]
    if order_bad.any():
        lines_bad = line_no[keep][order_bad]
        first_bad = int(lines_bad[0])
        if not repair:
            raise InputError(f"{path}, line {first_bad}: timestamp {tk[order_bad][0] * 1000:g} ms is not "
                             f"after the previous one (timestamps must increase; {order_bad.sum()} row(s))")
        where = ", ".join(str(x) for x in lines_bad[:6])
        fixes.append(f"dropped {order_bad.sum()} row(s) whose timestamp is out of order (lines {where}"
                     f"{'…' if order_bad.sum() > 6 else ''})")
        bad_lines += list(lines_bad)
        idx = np.flatnonzero(keep)
        keep[idx[order_bad]] = False
    if len(bad_lines) > max(1, max_fix_fraction * n0):
        raise InputError(f"{path}: {len(bad_lines)} of {n0} rows are bad (NaN or out-of-order timestamps, "
                         f"first at line {min(bad_lines)}); more than {max_fix_fraction:.0%} is refused")
    t = t_s[keep]
    if t.size < 2:
        raise InputError(f"{path}: fewer than 2 usable samples")
    t = t - t[0]
    _check_span(path, t, line_no[keep])
    return Trace(t, amp[keep], unit, marks[keep], source=path.name, fixes=tuple(fixes),
                 positions=None if positions is None else positions[keep])


#: A trace spanning more than this many of its median sample intervals (beyond ``GAP_FACTOR`` times
#: its sample count) holds a timestamp that cannot be right: every step on a uniform grid would cost
#: time and memory in proportion (a 25 Hz trace of 2·10⁶ intervals is 22 hours).
MAX_INTERVALS = 2_000_000
GAP_FACTOR = 10


def _check_span(path: Path, t, lines) -> None:
    """InputError naming the file and the row when the times ``t (n,)`` s (from 0, increasing) span
    more median intervals than :data:`MAX_INTERVALS` and :data:`GAP_FACTOR` × n allow."""
    dt = float(np.median(np.diff(t)))
    span = float(t[-1])
    if dt > 0 and span / dt > max(MAX_INTERVALS, GAP_FACTOR * t.size):
        jump = int(np.argmax(np.diff(t))) + 1
        raise InputError(f"{path}, line {int(lines[jump])}: timestamps span {span:.4g} s at a median sample "
                         f"interval of {dt:.3g} s ({span / dt:.3g} intervals for {t.size} samples): a timestamp is wrong "
                         f"(largest jump, {np.max(np.diff(t)):.4g} s, before this row)")


# --------------------------------------------------------------------------- resampling
def resample(trace: Trace, fs_hz: float, max_gap_s: float = 1.0) -> Trace:
    """Trace on a uniform grid at ``fs_hz`` (linear interpolation). Marks move to the nearest sample.

    Gaps longer than ``max_gap_s`` are refused (InputError naming the file and the time): they
    would be bridged by a straight line through a breath.
    """
    if not (np.isfinite(fs_hz) and fs_hz > 0):
        raise InputError(f"fs_hz must be > 0, got {fs_hz!r}")
    t = trace.t_s
    if t.size < 2:
        raise InputError(f"{trace.source}: fewer than 2 samples")
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.flatnonzero(dt <= 0)[0])
        raise InputError(f"{trace.source}: time goes backwards at sample {k + 1} (t = {t[k + 1]:.3f} s)")
    if dt.max() > max_gap_s:
        k = int(np.argmax(dt))
        raise InputError(f"{trace.source}: gap of {dt[k]:.2f} s at t = {t[k]:.2f} s exceeds max_gap_s = "
                         f"{max_gap_s:g} s; split the trace or raise the limit")
    tu = np.arange(0.0, t[-1] + 1e-9, 1.0 / fs_hz)
    au = np.interp(tu, t, trace.amplitude)
    marks = np.full(tu.size, "", dtype="<U1")
    for i in np.flatnonzero(trace.marks != ""):
        j = int(np.clip(np.rint(t[i] * fs_hz), 0, tu.size - 1))
        marks[j] = trace.marks[i]
    fixes = trace.fixes
    if dt.max() > 2.5 * np.median(dt):
        k = int(np.argmax(dt))
        fixes = fixes + (f"interpolated across gaps up to {dt[k]:.2f} s (largest at t = {t[k]:.2f} s)",)
    return replace(trace, t_s=tu, amplitude=au, marks=marks, fixes=fixes, positions=None)


# --------------------------------------------------------------------------- orientation
def _inspiratory_shares(t_s, amplitude) -> tuple[float, float, int] | None:
    """:func:`lungdeform.breathing.cycles.inspiratory_shares` of a signal, None when it cannot say
    (too short, flat, fewer than 3 breaths either way)."""
    t = np.asarray(t_s, float)
    if t.size < 16 or t[-1] - t[0] < 4 * CYCLE_RANGE_S[0]:
        return None
    try:
        keep, flip, n = inspiratory_shares(t, amplitude, 0.05)
    except InputError:
        return None
    return (keep, flip, n) if np.isfinite(keep) and np.isfinite(flip) else None


def inhale_sign(t_s, amplitude) -> float:
    """−1.0 when the signal ``amplitude (n,)`` at ``t_s (n,)`` s must be negated to be
    inhalation-positive (the rule of the module doc), else 1.0 (also when it cannot say)."""
    shares = _inspiratory_shares(t_s, amplitude)
    return -1.0 if shares is not None and shares[1] < shares[0] else 1.0


def orient_inhale_positive(trace: Trace) -> Trace:
    """The trace signed so that inhalation is positive (see the module doc), the decision in
    :attr:`Trace.fixes` when the sign changes. Too short or flat a trace is returned as it is."""
    shares = _inspiratory_shares(trace.t_s, trace.amplitude)
    if shares is None or shares[1] >= shares[0]:
        return trace
    keep, flip, n = shares
    note = (f"amplitude negated so that inhalation is positive: inspiration took a median {keep:.0%} of "
            f"each of {n} breaths as recorded, {flip:.0%} negated (it is the shorter phase)")
    if (trace.marks != "").any():
        note += "; P/Z marks swapped with it (P = end-inhale)"
    return replace(negated(trace), fixes=trace.fixes + (note,))


def negated(trace: Trace) -> Trace:
    """The trace with its amplitude negated and its P/Z marks swapped (P stays end-inhale)."""
    swap = {"P": "Z", "Z": "P"}
    marks = np.array([swap.get(x, x) for x in trace.marks], dtype="<U1")
    return replace(trace, amplitude=-trace.amplitude, marks=marks)
