"""The fit report's figures (lungdeform.plot.fit)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.plot.fit import cumulative_errors, cumulative_panels, target_errors


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


def test_target_errors_headline_distribution_and_every_targets_median_and_p95():
    # truth: the left panel is the last target's cumulative distribution (as cumulative_panels draws
    # it); on the right each method's median and 95th percentile per target, in the order given, equal
    # numpy's percentiles; a method missing at a target leaves a gap (NaN), not a zero; colours are the
    # ranks at the last target ("a" better there: C0), as in cumulative_panels
    rng = np.random.default_rng(3)
    errors = {t: {"a": rng.gamma(2.0, 0.5 * s, 400), "b": rng.gamma(2.0, 1.0 * s, 400)}
              for s, t in zip((1.0, 2.0, 3.0), ("10%", "90%", "50%"))}
    errors["90%"]["a"][:5] = np.nan
    del errors["10%"]["b"]
    fig = target_errors(errors)
    headline, spread = fig.axes[:2]
    assert headline.get_title() == "at 50% (the last target)"
    assert [t.get_text() for t in headline.get_legend().get_texts()][0].startswith("a (median ")
    assert [t.get_text() for t in spread.get_xticklabels()] == ["10%", "90%", "50%"]
    lines = spread.get_lines()  # per method its medians then its 95th percentiles, methods by colour
    for k, name in enumerate(("a", "b")):
        median, p95 = lines[2 * k].get_ydata(), lines[2 * k + 1].get_ydata()
        for i, t in enumerate(errors):
            e = errors[t].get(name, np.zeros(0))
            e = e[np.isfinite(e)]
            want = np.percentile(e, (50, 95)) if e.size else (np.nan, np.nan)
            np.testing.assert_allclose([median[i], p95[i]], want)
        assert lines[2 * k].get_color() == f"C{k}" and lines[2 * k + 1].get_linestyle() == "--"
    assert np.isnan(lines[2].get_ydata()[0])
