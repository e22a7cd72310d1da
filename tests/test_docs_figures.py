"""Every documented table of figures that a command recomputes in minutes is recomputed here and
compared with the document.

Why (issue 39): a figure in the docs is only worth what the command behind it gives today; renamed
keys, a changed baseline or protocol, and a table copied from an older run all drift silently. Each
checked table follows a marker in the document, ``<!-- figures NAME: lungdeform … -->``, that names
the command producing it; this test runs that command (on ``LUNGDEFORM_DATA``; the runs are shared
with the real-data tests of each command, ``traces_validated`` in tests/conftest.py) and compares every
figure of the table with the metrics it wrote, at the precision the table prints. The fit tables
(``validate copd``: five cases, each a full fit of both lungs; ``validate itk-pair``: the 5-fold run
with 300 evaluations) take too long for the suite; they carry no marker, and name their command
beside them.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest


DOCS = Path(__file__).resolve().parents[1] / "docs"
MARKER = re.compile(r"<!-- figures (?P<name>[\w-]+): (?P<command>lungdeform [^>]*?) -->")


def marked_tables(path: Path) -> dict[str, tuple[str, list[list[str]]]]:
    """``{name: (command, rows)}``: each marker of the document and the markdown table right after it
    (header and separator left out; cells stripped of spaces and ``**``)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out = {}
    for i, line in enumerate(lines):
        m = MARKER.search(line)
        if not m:
            continue
        j = i + 1
        while j < len(lines) and not lines[j].startswith("|"):
            j += 1
        rows = []
        while j < len(lines) and lines[j].startswith("|"):
            rows.append([c.strip().strip("*").strip() for c in lines[j].strip().strip("|").split("|")])
            j += 1
        out[m.group("name")] = (m.group("command"), rows[2:])
    return out


def number(cell: str) -> tuple[float, int]:
    """The first number of a cell and its decimals (the precision the table prints)."""
    m = re.search(r"-?\d+(?:\.(\d+))?", cell)
    assert m, f"no figure in cell {cell!r}"
    return float(m.group(0)), len(m.group(1) or "")


def agrees(cell: str, value) -> bool:
    """Whether ``value`` printed at the cell's precision is the cell's figure."""
    shown, decimals = number(cell)
    return value is not None and abs(round(float(value), decimals) - shown) < 0.5 * 10 ** -decimals + 1e-12


def test_every_marker_has_a_table_and_a_command_this_test_checks():
    # why: a marker this test does not know would be a table nobody checks
    found = {n for doc in DOCS.glob("*.md") for n in marked_tables(doc)}
    assert found == {"prediction", "gating", "breathing"}
    for doc in DOCS.glob("*.md"):
        for name, (command, rows) in marked_tables(doc).items():
            assert rows and command.startswith("lungdeform validate "), (doc.name, name)


PREDICTION_COLUMNS = ("model_over_linear", "model_over_linear_plain", "model_over_none", "linear_over_none",
                      "linear_plain_over_none", None)


@pytest.mark.realdata
@pytest.mark.slow
def test_prediction_table_is_what_validate_prediction_gives(traces_validated):
    # the table of docs/PREDICTION.md, every horizon (the run is shared with tests/validate/test_prediction.py)
    command, rows = marked_tables(DOCS / "PREDICTION.md")["prediction"]
    code, m, _ = traces_validated(command)
    assert code == 0
    checked = 0
    for row in rows:
        h = str(int(number(row[0])[0]))
        if h not in m["medians"]:
            continue
        values = [m["medians"][h][k] if k else m["quiet_medians"][h]["model_over_none"] for k in PREDICTION_COLUMNS]
        for cell, value in zip(row[1:], values):
            assert agrees(cell, value), (h, cell, value)
            checked += 1
    assert checked == 6 * len(rows) == 30


@pytest.mark.realdata
@pytest.mark.slow
def test_gating_table_is_what_validate_gating_gives(traces_validated):
    # the default run's rows of docs/PREDICTION.md's gating table: every strategy, causal and oracle
    # (the run is shared with tests/validate/test_gating.py)
    command, rows = marked_tables(DOCS / "PREDICTION.md")["gating"]
    code, m, _ = traces_validated(command)
    assert code == 0
    names = [re.match(r"[\w]+", r[0]).group(0) for r in rows]
    assert set(names) == set(m["summary"]) - {"oracle_matched"}
    for name, row in zip(names, rows):
        s = m["summary"][name]
        for cell, key in zip(row[1:], ("duty_cycle", "beam_on_error", "residual_rms")):
            assert agrees(cell, s[key]), (name, key, cell, s[key])


BREATHING_ROWS = {"shared shape": "median_shared_shape", "no drift": "median_shared_shape_no_drift",
                  "anchored": "median_anchored", "% of the held-out range": "median_percent_of_trace_range",
                  "regular cycles only": "median_regular_cycles"}


@pytest.mark.realdata
@pytest.mark.slow
def test_breathing_table_is_what_validate_breathing_gives(traces_validated):
    # docs/METHOD_NOTES.md's held-out table: medians over the 16 traces, and the in-sample row apart
    # (run with --strict, which changes only the exit code: 3, the target is not met; the run is
    # shared with tests/cli/test_validate_breathing.py)
    command, rows = marked_tables(DOCS / "METHOD_NOTES.md")["breathing"]
    code, m, _ = traces_validated(command, "--strict")
    assert code == 3
    seen = set()
    for row in rows:
        label = row[0].lower()
        key = next((k for k in BREATHING_ROWS if label.startswith(k)), None)
        block = m[BREATHING_ROWS[key]] if key else m["in_sample"]["median_per_cycle_refit_insample"]
        assert key or "in-sample" in label, row[0]
        for cell, model in zip(row[1:], ("model", "lujan", "fourier")):
            assert agrees(cell, block[model]), (row[0], model, cell, block[model])
        seen.add(key)
    assert seen == {*BREATHING_ROWS, None}
