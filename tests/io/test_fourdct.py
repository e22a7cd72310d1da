"""A 4-D CT in one DICOM folder (lungdeform.io.fourdct): phases told apart by SeriesDescription
percentages or TemporalPositionIndex, ordered, and refused when they cannot be told apart."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.errors import ReadError
from lungdeform.io.fourdct import _number, _percent, read_phases
from tests.fourdct_phantom import SHAPE, phase_ct, write_4dct, write_slices


@pytest.mark.parametrize("mode, labels", [
    ("description", ["0%", "10%", "20%", "30%", "40%"]),
    ("index", [f"TemporalPositionIndex {p}" for p in range(1, 6)]),
])
def test_phases_ordered_by_their_tags(tmp_path, rng, mode, labels):
    # the phases are written last phase first, so only the tags can give the order; phase p's lungs are
    # the phantom scaled by 1 + 0.06 p, so their air (< -400 HU) grows strictly with the phase
    write_4dct(tmp_path, rng, 5, mode)
    phases = read_phases(tmp_path)
    assert [p.label for p in phases] == labels
    air = [int((p.image.array < -400).sum()) for p in phases]
    assert air == sorted(air) and len(set(air)) == 5
    # each phase is one full volume in slice order (z increasing along the files)
    assert all(p.image.array.shape == SHAPE and len(p.files) == SHAPE[0] for p in phases)
    assert np.allclose(phases[0].image.spacing, [4.0, 4.0, 6.0])


def test_phases_that_cannot_be_told_apart(tmp_path, rng):
    # four series with the same description and no temporal tags: nothing orders them
    write_4dct(tmp_path / "same", rng, 4, "same")
    with pytest.raises(ReadError, match="4 phases .* cannot be told apart") as e:
        read_phases(tmp_path / "same")
    assert str(tmp_path / "same") in str(e.value) and "\n" not in str(e.value)
    # one series repeating its slice positions with no temporal tag at all
    ct = phase_ct(1.0, rng)
    write_slices(tmp_path / "rep", ct, {}, "1.2.3.4", name="a")
    write_slices(tmp_path / "rep", ct, {}, "1.2.3.4", first_instance=100, name="b")
    with pytest.raises(ReadError, match="repeats slice positions"):
        read_phases(tmp_path / "rep")


def test_one_phase_and_no_dicom_refused(tmp_path, rng):
    # a 3-D series is one phase: not a 4-D CT
    write_slices(tmp_path / "one", phase_ct(1.0, rng), {"0008|103e": "CT 0%"}, "1.2.3.4")
    with pytest.raises(ReadError, match="one phase only"):
        read_phases(tmp_path / "one")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReadError, match="no DICOM files"):
        read_phases(tmp_path / "empty")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "x.dcm").write_bytes(b"\0" * 200)
    with pytest.raises(ReadError, match="x.dcm is not a readable DICOM image"):
        read_phases(tmp_path / "bad")


def test_percent_and_time_parsing():
    # the spellings of the docstring; AcquisitionTime HHMMSS.frac counts seconds since midnight
    assert [_percent(s) for s in ("CT 30%", "Gated 40.0%", "T=50%", "phase 20", "4D CT")] == [30, 40, 50, 20, None]
    assert _number("0008|0032", "101502.5") == 10 * 3600 + 15 * 60 + 2.5
    assert _number("0018|1060", "nan") is None and _number("0020|9128", "") is None


def test_damaged_or_unreadable_file_stops_the_reading_early(tmp_path, rng, monkeypatch):
    # why: the element headers of every file are checked (cheap) before GDCM reads any header, and
    # the reading stops at the first file GDCM cannot read; the error is the one the file-by-file
    # reading gave (the first damaged file, else the first unreadable one), only sooner.
    made = []
    real = sitk.ImageFileReader
    monkeypatch.setattr(sitk, "ImageFileReader", lambda: made.append(1) or real())
    write_4dct(tmp_path / "ct", rng, 2, "index")
    files = sorted((tmp_path / "ct").rglob("*.dcm"))
    last = files[-1]
    last.write_bytes(last.read_bytes()[:-10])  # the pixel data now claims 10 bytes more than are left
    with pytest.raises(ReadError, match=f"{last.name}: damaged DICOM file: element \\(7FE0,0010\\)"):
        read_phases(tmp_path / "ct")
    assert made == []  # GDCM read none of the intact files before the damaged last one
    last.unlink()
    bad = files[0].with_name("0000.dcm")  # first in order, and no DICOM at all (no preamble)
    bad.write_bytes(b"\0" * 200)
    with pytest.raises(ReadError, match="0000.dcm is not a readable DICOM image"):
        read_phases(tmp_path / "ct")
    assert made == []  # refused by its first element, (0000,0000), before GDCM read any file
