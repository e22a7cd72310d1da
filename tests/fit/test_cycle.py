"""A full breathing cycle as fit inputs (lungdeform.fit.cycle): order, branches, hysteresis, alignment."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.fit.cycle import branches, choose_alignment, hysteresis, surface_gap, volume_order
from lungdeform.geometry.mesh import Surface, icosphere


def test_volume_order_keeps_equal_volumes_in_phase_order():
    # a cosine cycle sampled at 0 … 90 %: 10 % and 90 % share a volume; smallest first, ties by phase
    keys = np.arange(0, 100, 10.0)
    v = 1000 + 250 * (1 - np.cos(2 * np.pi * keys / 100))
    order = volume_order(keys, np.round(v, 6))
    assert order[0] == 0 and order[-1] == 5
    assert order[1:3] == [1, 9] and order[3:5] == [2, 8]


def test_branches_follow_the_phase_order_from_end_exhale():
    # end-exhale at phase 3 (smallest), end-inhale at phase 6: inhale 3→6, exhale 7, 0, 1, 2 (cyclic)
    v = [5.0, 4.0, 2.0, 1.0, 2.5, 4.5, 6.0, 5.5]
    inhale, exhale = branches(v)
    assert inhale == [3, 4, 5, 6] and exhale == [7, 0, 1, 2]
    # a monotone series has no exhale branch
    assert branches([1.0, 2.0, 3.0]) == ([0, 1, 2], [])
    with pytest.raises(InputError, match="two or more"):
        branches([1.0])


def test_hysteresis_of_a_translated_sphere_is_bounded_by_the_shift():
    # truth: a sphere moved by 3 mm: every vertex lies within 3 mm of the other surface (its image
    # under the shift lies on it), and the mean is well above 0; the same sphere gives 0 exactly
    s = icosphere(4, 30.0)
    moved = Surface(s.vertices + [0, 0, 3.0], s.faces)
    same = surface_gap(s, Surface(s.vertices.copy(), s.faces))
    assert same.max == 0.0
    gap = surface_gap(s, moved)
    assert 0.8 < gap.mean < 3.0 and gap.max <= 3.0 + 1e-9
    # phases 0 (EE), 1, 2 (EI), 3 (exhale, the moved sphere at phase 1's volume): one pair, 3 against 1
    pairs = hysteresis(["0%", "25%", "50%", "75%"], [s, s, s, moved], [100.0, 150.0, 200.0, 150.0])
    assert [(p.exhale, p.inhale) for p in pairs] == [("75%", "25%")]
    assert pairs[0].mean_mm == pytest.approx(gap.mean) and pairs[0].p95_mm <= 3.0 + 1e-9


def test_alignment_none_only_for_one_frame_of_reference():
    # one shared Frame of Reference is one patient frame: nothing to align unless asked
    assert choose_alignment("auto", "1.2.3.4.5")[0] == "none"
    assert choose_alignment("auto", None)[0] == "apex"
    assert choose_alignment("joint", "1.2.3.4.5") == ("joint", "asked (--align)")
