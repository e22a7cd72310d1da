"""The fit report's figures (lungdeform.plot.fit)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.plot.fit import cumulative_errors, cumulative_panels


def test_cumulative_errors_orders_methods_and_marks_medians():
    # truth: medians of [1, 2, 3] and [0.5, 0.5, 0.5] are 2 and 0.5; methods listed by median; each
    # curve climbs from 0 to 1
    fig = cumulative_errors({"worse": np.array([1.0, 2.0, 3.0]), "better": np.array([0.5, 0.5, np.nan])})
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["better (median 0.50 mm)", "worse (median 2.00 mm)"]
    lines = ax.get_lines()  # per method its curve then its median dot, methods in legend order
    assert lines[0].get_ydata()[0] == 0.0 and lines[0].get_ydata()[-1] == pytest.approx(1.0)
    assert lines[1].get_xydata().tolist() == [[0.5, 0.5]] and lines[3].get_xydata().tolist() == [[2.0, 0.5]]


def test_cumulative_panels_keep_each_methods_colour():
    # truth: per panel the legend lists methods by that panel's median; a method's colour is its rank
    # in the last panel (there "a" is better than "b": C0 and C1) in every panel, also where it ranks
    # otherwise; an empty panel list of methods draws nothing
    fig = cumulative_panels({"first": {"a": np.array([3.0, 4.0]), "b": np.array([1.0, 2.0])},
                             "last": {"a": np.array([0.5]), "b": np.array([1.0])}})
    first, last = fig.axes[:2]
    assert [t.get_text() for t in first.get_legend().get_texts()] == ["b (median 1.50 mm)", "a (median 3.50 mm)"]
    assert [t.get_text() for t in last.get_legend().get_texts()] == ["a (median 0.50 mm)", "b (median 1.00 mm)"]
    assert first.get_lines()[0].get_color() == "C1" and first.get_lines()[2].get_color() == "C0"
    assert last.get_lines()[0].get_color() == "C0" and first.get_title() == "first"
