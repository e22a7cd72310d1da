"""The split of a both-lung tidal volume between a model's lungs (lungdeform.model.tidal): two lungs by
end-exhale volume, a lone lung its side's published share; playback divides by the recorded volume."""

from __future__ import annotations

import pytest

from lungdeform.errors import InputError
from lungdeform.model.tidal import ONE_LUNG_SHARE, played_shares, split_rule, tidal_split


def test_published_one_lung_shares_make_up_both_lungs():
    # Yamada et al. 2020, Table 3 (supine CT): right 53.6 %, left 46.4 % of both lungs' volume
    assert ONE_LUNG_SHARE == {"right": 0.536, "left": 0.464}
    assert sum(ONE_LUNG_SHARE.values()) == pytest.approx(1.0, abs=1e-12)


def test_two_lungs_share_by_volume_one_lung_takes_its_sides_share():
    # analytic: 2000 and 3000 mL lungs take 2/5 and 3/5 of 500 mL; a lone lung its side's share, whatever its size
    assert tidal_split({"left": 2000.0, "right": 3000.0}, 500.0) == pytest.approx({"left": 200.0, "right": 300.0})
    assert tidal_split({"left": 2393.0}, 500.0) == pytest.approx({"left": 232.0})
    assert tidal_split({"right": 10.0}, 500.0) == pytest.approx({"right": 268.0})
    assert "46.4%" in split_rule(["left"]) and "end-exhale volumes" in split_rule(["left", "right"])


@pytest.mark.parametrize("volumes, tidal, match", [
    ({"left": 2000.0}, 0.0, "tidal_ml must be > 0"),
    ({"left": 2000.0}, float("nan"), "tidal_ml must be > 0"),
    ({"lung": 2000.0}, 500.0, "side of a lone lung must be 'left' or 'right'"),
    ({}, 500.0, "volumes_ml must be one or two"),
    ({"left": -1.0}, 500.0, "volumes_ml must be one or two"),
])
def test_split_refuses_what_it_cannot_share(volumes, tidal, match):
    with pytest.raises(InputError, match=match):
        tidal_split(volumes, tidal)


def test_played_shares():
    # a two-lung build (calibrated at all of the recorded 500 mL): exactly its volume proportion
    two = tidal_split({"left": 2393.0, "right": 2953.0}, 500.0)
    assert played_shares(two, 500.0) == played_shares(two)
    assert sum(played_shares(two, 500.0).values()) == 1.0
    # a lone lung calibrated at its 46.4 % plays 46.4 % of any both-lung breath
    assert played_shares({"left": 232.0}, 500.0) == pytest.approx({"left": 0.464})
    # a model built before (a lone lung calibrated at the whole 500 mL) plays as it did: all of it
    assert played_shares({"left": 500.0}, 500.0) == {"left": 1.0}
    # a fit records no tidal volume: its measured per-lung volume changes share in proportion
    assert played_shares({"left": 400.0, "right": 600.0}) == pytest.approx({"left": 0.4, "right": 0.6})
    assert played_shares({"right": 350.0}) == {"right": 1.0}
    for bad in ("500", float("inf"), -5.0, True):
        with pytest.raises(InputError, match="provenance entry tidal_ml must be a volume"):
            played_shares({"left": 232.0}, bad)
    with pytest.raises(InputError, match=r"tidal_ml \(400 mL, both lungs\) is less than"):
        played_shares({"left": 232.0, "right": 268.0}, 400.0)
