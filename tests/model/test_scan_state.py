"""lungdeform.model.scan_state: what ``build --scan-state`` accepts and what each value means."""

import pytest

from lungdeform.errors import InputError
from lungdeform.model.scan_state import ScanState, parse_scan_state


@pytest.mark.parametrize("text, name, above", [
    ("end-exhale", "end-exhale", 0.0), ("End-Inhale", "end-inhale", 500.0), ("mid", "mid", 250.0),
    ("0.3", "fraction", 150.0), ("0", "end-exhale", 0.0), ("1", "fraction", 500.0),
    ("300mL", "volume", 300.0), ("1200 ml", "volume", 1200.0), ("0mL", "end-exhale", 0.0),
])
def test_a_scan_state_is_its_height_above_end_exhale(text, name, above):
    # why: every playback subtracts above_ee_ml (mL of both lungs) from the breath's volume above
    # end-exhale; the named states are fractions of the build's tidal volume (500 mL here), a
    # volume is taken as given (a breath-hold scan may lie beyond the tidal volume: 1200 mL)
    s = parse_scan_state(text, 500.0)
    assert (s.name, s.above_ee_ml) == (name, pytest.approx(above))
    assert s.is_end_exhale == (above == 0.0)


@pytest.mark.parametrize("text", ["inhale", "1.5", "-0.1", "-5mL", "nan", "20000mL", ""])
def test_a_state_that_is_none_of_them_is_refused_naming_the_option(text):
    with pytest.raises(InputError, match="--scan-state"):
        parse_scan_state(text, 500.0)


def test_the_state_in_words_and_as_recorded():
    assert ScanState().describe() == "end-exhale"
    assert parse_scan_state("end-inhale", 500).describe() == "end-inhale, 500 mL above end-exhale"
    assert parse_scan_state("mid", 500).describe() == "mid-ventilation, 250 mL above end-exhale"
    assert parse_scan_state("300mL", 500).record() == {"state": "volume", "above_end_exhale_ml": 300.0,
                                                       "in_words": "300 mL above end-exhale"}
    with pytest.raises(InputError, match="0 mL above end-exhale"):
        ScanState("end-exhale", 10.0)
