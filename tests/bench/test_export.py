"""lungdeform.bench.export: the record of the USD exports against the glb (timings are never asserted)."""

from __future__ import annotations

import pytest

from lungdeform.bench.export import export_record
from lungdeform.errors import InputError
from lungdeform.playback import schedule as S
from lungdeform.playback.export import glb_bytes
from lungdeform.playback.usd import export_usd
from tests.browser.support import two_lungs

pytest.importorskip("pxr", reason="usd-core is not installed (pip install 'lungdeform[usd]')")


def test_record_sizes_are_the_files_written_and_ratios_to_the_glb(tmp_path):
    # truth: the bytes of each format are those of the same export written directly; each ratio is
    # the format's figure over the glb's of the same run
    model = two_lungs(2)
    trace = S.plain_cycle(500, 2.0)
    row = export_record(model, "ellipsoids", trace, repeats=2)
    f = row["formats"]
    assert list(f) == ["glb", "usdc", "usdz", "usdz --baked"]
    assert row["vertices"] == sum(lung.n_vertices for lung in model.lungs.values()) and row["frames"] == 61
    assert f["glb"]["bytes"] == len(glb_bytes(model, trace))
    assert f["usdz"]["bytes"] == export_usd(model, tmp_path / "x.usdz", trace).stat().st_size
    assert f["usdz --baked"]["bytes"] == export_usd(model, tmp_path / "b.usdz", trace, baked=True).stat().st_size
    for rec in f.values():
        assert len(rec["seconds_all"]) == 2 and rec["seconds"] > 0
        assert rec["bytes_ratio_to_glb"] == pytest.approx(rec["bytes"] / f["glb"]["bytes"])
        assert rec["seconds_ratio_to_glb"] == pytest.approx(rec["seconds"] / f["glb"]["seconds"])
    # the baked file is left out above its vertex limit
    assert "usdz --baked" not in export_record(model, "e", trace, repeats=1, baked_max_vertices=100)["formats"]
    with pytest.raises(InputError, match="repeats"):
        export_record(model, "e", trace, repeats=0)
