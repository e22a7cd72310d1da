"""A 4-D CT in one DICOM folder (lungdeform.io.dicom.fourdct): phases told apart by SeriesDescription
percentages or TemporalPositionIndex, ordered, and refused when they cannot be told apart."""

from __future__ import annotations

import warnings

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from lungdeform.errors import InputError, ReadError
from lungdeform.io.dicom.fourdct import _number, _percent, frame_of_reference, read_phases
from tests.fourdct_phantom import SHAPE, STUDY, phase_ct, write_4dct, write_cycle, write_slices


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
    with pytest.raises(ReadError, match="no DICOM CT images"):
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


def _retag(files, **tags) -> None:
    """Set DICOM attributes (pydicom keywords → value, or a function of the slice index) in ``files``."""
    import pydicom

    for n, f in enumerate(files):
        ds = pydicom.dcmread(f)
        for key, value in tags.items():
            setattr(ds, key, value(n) if callable(value) else value)
        ds.save_as(f)


def _phase_files(folder, p):
    return sorted((folder / f"phase{p}").glob("*.dcm"))


@pytest.mark.parametrize("keyword, name", [("PatientID", "PatientID"), ("StudyInstanceUID", "StudyInstanceUID"),
                                           ("FrameOfReferenceUID", "FrameOfReferenceUID")])
def test_two_patients_studies_or_frames_in_one_folder_refused(tmp_path, rng, keyword, name):
    # why: a folder holding the phases of two patients (or two studies, or two frames of reference)
    # was fitted as one lung; the folder must hold one of each, and the error names both values
    write_4dct(tmp_path, rng, 3)
    _retag(_phase_files(tmp_path, 0) + _phase_files(tmp_path, 1), **{keyword: "1.2.3.4"})
    _retag(_phase_files(tmp_path, 2), **{keyword: "1.2.3.5"})
    with pytest.raises(ReadError, match=rf"{tmp_path}: holds more than one {name}: '1\.2\.3\.4' in .* and '1\.2\.3\.5' in "):
        read_phases(tmp_path)


def test_uneven_missing_or_tilted_slices_refused(tmp_path, rng):
    # why: ITK reads any series onto an evenly spaced, untilted grid (spacing = extent / (n - 1)):
    # slices 6 mm then 3 mm apart, a missing slice or a 20 degree gantry tilt gave lungs of the
    # wrong volume without a word; each is refused naming the phase and the files
    write_4dct(tmp_path, rng, 2)
    files = _phase_files(tmp_path, 1)
    z0 = -(SHAPE[0] - 1) / 2 * 6.0
    _retag(files[12:], ImagePositionPatient=lambda n: [-94.0, -94.0, z0 + 11 * 6.0 + 3.0 * (n + 1)])
    with pytest.raises(ReadError, match=r"phase 10%: uneven slice spacing: .* from 3 to 6 mm"):
        read_phases(tmp_path)
    _retag(files[12:], ImagePositionPatient=lambda n: [-94.0, -94.0, z0 + 6.0 * (n + 12)])  # even again
    assert len(read_phases(tmp_path)) == 2
    files[5].unlink()
    with pytest.raises(ReadError, match=r"phase 10%: 1 slice\(s\) missing: .* 12 mm between s0005\.dcm"):
        read_phases(tmp_path)
    write_slices(tmp_path / "phase1", phase_ct(1.06, rng)[5:6], {"0008|103e": "Gated 10%"}, f"{STUDY}.2",
                 first_instance=6)  # the slice back
    import math

    tilt = math.tan(math.radians(20))
    _retag(files, ImagePositionPatient=lambda n: [-94.0, -94.0 + tilt * 6.0 * n, z0 + 6.0 * n])
    with pytest.raises(ReadError, match=r"phase 10%: the slices are stacked 20 degrees off their normal \(gantry tilt\)"):
        read_phases(tmp_path)
    _retag(files, ImagePositionPatient=lambda n: [-94.0, -94.0, z0 + 6.0 * n], GantryDetectorTilt="20")
    with pytest.raises(ReadError, match=r"phase 10%: .*s0001\.dcm: GantryDetectorTilt is 20 degrees"):
        read_phases(tmp_path)


def _set_raw(path, tag: int, vr: str, value: bytes) -> None:
    """Set one element of a DICOM file to raw bytes (no conversion: values pydicom would refuse)."""
    import pydicom
    from pydicom.dataelem import RawDataElement
    from pydicom.tag import Tag

    ds = pydicom.dcmread(path)
    value += b" " * (len(value) % 2)
    ds[tag] = RawDataElement(Tag(tag), vr, len(value), value, 0, False, True)
    ds.save_as(path)


@pytest.mark.parametrize("tag, value, why", [
    (0x00200037, b"0\\0\\0\\0\\0\\0", r"ImageOrientationPatient '0\\0\\0\\0\\0\\0' is not two orthogonal unit vectors"),
    (0x00200037, b"1\\0\\0\\0\\1", r"ImageOrientationPatient is '1\\0\\0\\0\\1', not 6 finite numbers"),
    (0x00200037, b"1\\0\\0\\0.5\\0.5\\0", r"ImageOrientationPatient .* is not two orthogonal unit vectors"),
    (0x00200037, b"0\\1\\0\\1\\0\\0", r"ImageOrientationPatient differs from that of .*s0001\.dcm"),
    (0x00200032, b"a\\b\\c", r"ImagePositionPatient is 'a\\b\\c', not 3 finite numbers"),
    (0x00280030, b"4\\2", r"PixelSpacing '4\\2' differs from that of .*s0001\.dcm \('4\\4'\)"),
    (0x00280030, b"0\\4", r"PixelSpacing '0\\4' is not two positive numbers"),
])
def test_degenerate_orientation_or_position_refused(tmp_path, rng, tag, value, why):
    # why: an all-zero, five-value, skewed or odd-one-out orientation, or a position that is not
    # numbers, gave no grid at all (a traceback) or a wrong one, and ITK gives every slice the first
    # one's pixel size; the error names the file
    write_4dct(tmp_path, rng, 2)
    bad = _phase_files(tmp_path, 0)[3]
    _set_raw(bad, tag, "DS", value)
    with pytest.raises(ReadError, match=rf"{bad}: {why}"):
        read_phases(tmp_path)


def test_grid_cap_refuses_a_phase_before_reading_it(tmp_path, rng, monkeypatch):
    # why: a grid over the cap is refused from the headers, before ITK allocates it; the cap comes
    # from the argument, else $LUNGDEFORM_MAX_VOXELS
    write_4dct(tmp_path, rng, 2)
    with pytest.raises(ReadError, match=r"phase 0%: the image grid 48 x 48 x 24 is 55,296 voxels, over the limit of 50,000"):
        read_phases(tmp_path, max_voxels=50_000)
    monkeypatch.setenv("LUNGDEFORM_MAX_VOXELS", "5e4")
    with pytest.raises(ReadError, match="over the limit of 50,000"):
        read_phases(tmp_path)
    monkeypatch.setenv("LUNGDEFORM_MAX_VOXELS", "many")
    with pytest.raises(InputError, match="LUNGDEFORM_MAX_VOXELS must be a positive whole number of voxels, got 'many'"):
        read_phases(tmp_path)


def test_frame_of_reference_shared_by_every_phase(tmp_path, rng):
    # truth: the UID written into every slice is the one read back; a folder without it has none
    write_cycle(tmp_path / "a", rng, [1.0, 1.1], frame_uid="1.2.3.4.5")
    files = [sorted(str(f) for f in (tmp_path / "a" / f"phase{p}").iterdir()) for p in range(2)]
    assert frame_of_reference(files) == "1.2.3.4.5"
    write_cycle(tmp_path / "b", rng, [1.0, 1.1])
    files = [sorted(str(f) for f in (tmp_path / "b" / f"phase{p}").iterdir()) for p in range(2)]
    assert frame_of_reference(files) is None


@pytest.mark.parametrize("keyword", ["StudyInstanceUID", "FrameOfReferenceUID", "SeriesInstanceUID"])
def test_a_slice_whose_uid_is_no_dicom_uid_is_refused_by_the_one_walk(tmp_path, rng, keyword):
    # why: the folder's UIDs go into the fitted model's record of its scans and into every series
    # derived from it; a value that is no DICOM UID (letters; a leading zero) is refused on read, as
    # the other readers refuse it (lungdeform.io.dicom.attributes.require), naming the file
    write_4dct(tmp_path, rng, 3)
    files = _phase_files(tmp_path, 0) + _phase_files(tmp_path, 1) + _phase_files(tmp_path, 2)
    with warnings.catch_warnings():  # pydicom's warning on writing it: the bad value is on purpose
        warnings.simplefilter("ignore")
        _retag(files, **{keyword: "1.2.03.abc"})
    with pytest.raises(ReadError, match=rf"phase0[/\\]\S+\.dcm: {keyword} '1\.2\.03\.abc' is not a DICOM UID"):
        read_phases(tmp_path)


def test_a_phase_exported_twice_is_refused_naming_both(tmp_path, rng):
    # issue 36: a 4-D CT whose 0 % and 50 % phases were byte-identical was fitted with only an
    # "optimizer did not converge" warning. Truth: the same voxels under another series (new UIDs),
    # or one SOP instance in two phases, are one phase twice: refused naming both; phases that only
    # look alike (one voxel differs) are different phases and read
    cts = [phase_ct(1.0 + 0.06 * p, rng) for p in range(4)]
    cts[2] = cts[0].copy()
    for p, ct in enumerate(cts):
        write_slices(tmp_path / "twice" / f"p{p}", ct, {"0008|103e": f"CT {25 * p}%"}, f"1.2.3.{p + 1}")
    with pytest.raises(ReadError, match=r"twice: phase 50% repeats phase 0%: identical pixel data .*a phase exported twice"):
        read_phases(tmp_path / "twice")
    cts[2][5, 10, 10] += 1  # one voxel differs: phases that look alike
    for p, ct in enumerate(cts):
        write_slices(tmp_path / "alike" / f"p{p}", ct, {"0008|103e": f"CT {25 * p}%"}, f"1.2.3.{p + 1}")
    assert [ph.label for ph in read_phases(tmp_path / "alike")] == ["0%", "25%", "50%", "75%"]
    # the same SOP instances under a second series (a phase copied into another series): refused before reading
    for p in range(2):
        write_slices(tmp_path / "shared" / f"p{p}", cts[p], {"0008|103e": f"CT {50 * p}%"}, f"1.2.3.{p + 1}")
    for p in range(2):  # each slice's own SOP instance UID, the same in both phases
        for n, f in enumerate(sorted((tmp_path / "shared" / f"p{p}").iterdir())):
            ds = pydicom.dcmread(f)
            ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = f"1.2.3.9.{n + 1}"
            ds.save_as(f)
    with pytest.raises(ReadError, match=r"shared: phase 50% repeats phase 0%: .* are one SOP instance \(1\.2\.3\.9\.1\)"):
        read_phases(tmp_path / "shared")


def test_each_header_is_read_once(tmp_path, rng, monkeypatch):
    # why: the survey parses each file's header once (pydicom's element reader, up to the last tag it
    # needs) and keeps the tags the phases are told apart and checked by; GDCM then reads the pixels of
    # each phase (one series read), never a header on its own. Counted: the files the survey opens,
    # pydicom's whole-file reader (left to files that are not the common case: none here) and GDCM
    # single-file readers; the phases still the phantom's (one per series, in order, full volumes)
    import builtins

    import lungdeform.io.dicom.folder as folder

    write_4dct(tmp_path, rng, 3, "description")
    opened: dict[str, int] = {}

    def counting_open(path, *args, **kwargs):
        opened[str(path)] = opened.get(str(path), 0) + 1
        return builtins.open(path, *args, **kwargs)

    made, whole = [], []
    real_reader, real_read = sitk.ImageFileReader, folder.pydicom.dcmread
    monkeypatch.setattr(folder, "open", counting_open, raising=False)
    monkeypatch.setattr(folder.pydicom, "dcmread", lambda *a, **k: whole.append(a[0]) or real_read(*a, **k))
    monkeypatch.setattr(sitk, "ImageFileReader", lambda: made.append(1) or real_reader())
    phases = read_phases(tmp_path)
    files = sorted(str(f) for f in tmp_path.rglob("*.dcm"))
    assert sorted(opened) == files and set(opened.values()) == {1}
    assert made == [] and whole == []
    assert [p.label for p in phases] == ["0%", "10%", "20%"]
    assert all(p.image.array.shape == SHAPE for p in phases)
