"""scripts/hostile_probe.py: its classification of outcomes, and two of its cases run end to end
(so that the hostile-input probe does not rot as the commands change)."""

from __future__ import annotations

import signal

import pytest

from tests.script_support import loaded_script

@pytest.fixture(scope="module")
def probe():
    yield from loaded_script("hostile_probe")


def _case(probe, expect="refuse", **kw):
    return probe.Case("c", "track", expect, lambda fx, d: [], **kw)


ARGV = ["python", "track", "/tmp/p/model.npz", "--out", "/tmp/p/out", "--reference-ct", "/tmp/p/ct"]


@pytest.mark.parametrize("expect, rc, stderr, before, after, timed_out, want", [
    # a refusal of one line naming an option or a file, nothing left: what issue 26 asks for
    ("refuse", 2, "error: --out /tmp/p/out: exists and is not a folder\n", {}, {}, False, "clean"),
    ("refuse", 2, "error: model.npz: no such model file\n", {}, {}, False, "clean"),
    # the same refusal after the output folder was made: half-written
    ("refuse", 2, "error: --volume-ml must be > 0\n", {}, {"out": "dir"}, False, "partial"),
    # a refusal that names nothing the user gave, or spreads over lines
    ("refuse", 2, "error: degenerate polygon\n", {}, {}, False, "unclear"),
    # a file's name counts as a whole word only: "structure" does not name the folder "ct"
    ("refuse", 2, "error: structure 'GTV': slices are not evenly spaced\n", {}, {}, False, "unclear"),
    ("refuse", 2, "error: ct: no DICOM series in this directory\n", {}, {}, False, "clean"),
    ("refuse", 2, "error: a\nerror: b\n", {}, {}, False, "unclear"),
    # exit 0 on an input known to be wrong; exit 0 on a "warn" case with and without a warning
    ("refuse", 0, "", {}, {"out": "dir"}, False, "silent"),
    ("warn", 0, "", {}, {"out": "dir"}, False, "silent"),
    ("warn", 0, "warning: slices 6 and 3 mm apart: resampled to 3 mm\n", {}, {"out": "dir"}, False, "clean"),
    # an input overwritten by a run that succeeded
    ("any", 0, "", {"rs.dcm": (10, 1)}, {"rs.dcm": (12, 2)}, False, "silent"),
    # a Python traceback, an undocumented exit code, a time-out
    ("refuse", 2, "Traceback (most recent call last):\n  ...\nValueError: x\n", {}, {}, False, "traceback"),
    ("refuse", 1, "error\n", {}, {}, False, "traceback"),
    ("refuse", -9, "", {}, {}, False, "traceback"),
    ("refuse", None, "", {}, {}, True, "hang"),
    # a valid input refused
    ("ok", 2, "error: --out: x\n", {}, {}, False, "refused"),
])
def test_classify(probe, tmp_path, expect, rc, stderr, before, after, timed_out, want):
    run = probe.Run(rc, "", stderr, timed_out)
    outcome, reason = probe.classify(_case(probe, expect), run, before, after, tmp_path, ARGV)
    assert outcome == want, reason


def test_classify_signal_cases(probe, tmp_path):
    # after SIGTERM: a file left is half-written whatever the exit code; nothing left is clean, even
    # when Python's default action killed the process (there was nothing to clean)
    case = _case(probe, signal=(signal.SIGTERM, "x", probe._no_leftovers))
    interrupted = probe.Run(130, "", "interrupted\n", signalled=True)
    left = {"ct_phase00.mha": (1, 1)}
    assert probe.classify(case, interrupted, {}, left, tmp_path, ARGV)[0] == "partial"
    assert probe.classify(case, interrupted, {}, {}, tmp_path, ARGV)[0] == "clean"
    killed = probe.Run(-signal.SIGTERM, "", "", signalled=True)
    assert probe.classify(case, killed, {}, {}, tmp_path, ARGV)[0] == "clean"
    # a signal case that finished before its trigger appeared is judged as an ordinary run
    assert probe.classify(case, probe.Run(0, "", ""), {}, {}, tmp_path, ARGV)[0] == "silent"


def test_every_case_is_named_once_and_declares_an_expectation(probe):
    cases = probe.all_cases()
    names = [c.name for c in cases]
    assert len(names) == len(set(names)) and probe.EXTRA <= set(names)
    assert {c.expect for c in cases} <= {"refuse", "warn", "ok", "any"}
    assert 60 <= len(probe.select(cases, None)) <= len(cases)


@pytest.mark.slow
def test_two_cases_end_to_end(probe, tmp_path):
    # a valid stream (control) exits 0 with finite volumes; a line of text on stdin is refused with
    # one line naming stdin: both clean, each with its record filled in
    only = ["stream_valid_control", "stream_garbage_line"]
    results = sorted(probe.run_probe(tmp_path, probe.Settings(timeout=120), only=only), key=lambda r: r.name)
    assert [r.name for r in results] == ["stream_garbage_line", "stream_valid_control"]
    assert [(r.outcome, r.rc) for r in results] == [("clean", 2), ("clean", 0)], [r.reason for r in results]
    assert "stdin line" in results[0].stderr_first_line and results[0].argv.startswith("lungdeform stream")
    # nothing but the probe's own folders under its root
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "cases", "logs", "mpl", "shared", "src", "tmp"]
