"""The rows of validate single-scan given the dome excursion (validate.dome_rows), on analytic lungs whose
larger volume is known exactly."""

import numpy as np
import pytest

from lungdeform.fit.objective import Target
from lungdeform.geometry.dome import dome_weights
from lungdeform.geometry.mesh import Surface
from lungdeform.model.dome import TOLERANCE_MM
from lungdeform.model.population import resolve_default
from lungdeform.validate.dome_rows import dome_row, dome_scaling_row, measured_excursion
from lungdeform.validate.single_scan import LungPair, Training, score
from tests.model.test_dome import _lung


def _pair(scale, shift=(4.0, -6.0, 11.0), keep_target=None):
    # the analytic lung and, as its "larger-volume scan", the same lung scaled along the axes about a point
    # and moved (an unknown shift, as between two breath-hold scans); three landmarks inside
    rest = _lung(5)
    c = np.array([3.0, -2.0, 40.0])
    big = Surface(c + (rest.vertices - c) * scale + shift, rest.faces, "big")
    lm = np.array([[0.0, 0.0, 60.0], [20.0, 10.0, 40.0], [-15.0, 25.0, 80.0]])
    return LungPair("s", "right", rest, np.ones(rest.n_vertices, bool), Target(big, big.volume_ml, keep_target),
                    big.volume_ml, lm, c + (lm - c) * scale + shift)


def test_dome_scaling_is_exact_for_a_lung_that_scaled():
    # a lung that grew 6 % across and 12 % head–foot: the excursion measured from the two scans is 12 % of its
    # apex-to-dome height, and the fair baseline given it reproduces the larger scan (and its landmarks)
    sxy, sz = 1.06, 1.12
    pair = _pair(np.array([sxy, sxy, sz]))
    e = measured_excursion(pair.rest, pair.keep, pair.target)
    assert e == pytest.approx((sz - 1) * dome_weights(pair.rest.vertices, pair.rest.faces).height_mm, rel=1e-9)
    vertices, landmarks, given = dome_scaling_row(pair, Training(resolve_default("population")))
    assert given == {"dome_mm": e}
    row = score(pair, vertices, landmarks)
    assert row["surface_mean_mm"] < 0.05 and row["landmark_mean_mm"] < 0.05


def test_dome_row_moves_the_dome_as_measured():
    # the dome row's prediction has the larger volume and, measured on it, the excursion of the two scans
    pair = _pair(np.array([1.06, 1.06, 1.08]))
    v, landmarks, given = dome_row(pair, Training(resolve_default("population")))
    e = measured_excursion(pair.rest, pair.keep, pair.target)
    assert landmarks.shape == (3, 3) and given == {"dome_mm": e}  # the row records the excursion it was given
    got = dome_weights(v, pair.rest.faces).height_mm - dome_weights(pair.rest.vertices, pair.rest.faces).height_mm
    assert got == pytest.approx(e, abs=TOLERANCE_MM)
    assert Surface(v, pair.rest.faces).volume_ml == pytest.approx(pair.volume_ml, rel=1e-9)


def test_no_rows_when_the_scan_cut_the_dome_off():
    # the larger scan's floor on a crop face: its excursion is unknown, so neither row is scored
    pair = _pair(np.array([1.03, 1.03, 1.15]))
    tv = pair.target.surface.vertices
    keep = ~((np.abs(tv[:, 0]) < 40) & (np.abs(tv[:, 1]) < 50) & (tv[:, 2] < 80))
    cut = LungPair(pair.subject, pair.side, pair.rest, pair.keep, Target(pair.target.surface, pair.target.volume_ml, keep),
                   pair.volume_ml, pair.landmarks_rest, pair.landmarks_target)
    assert measured_excursion(cut.rest, cut.keep, cut.target) is None
    training = Training(resolve_default("population"))
    assert dome_row(cut, training) is None and dome_scaling_row(cut, training) is None
