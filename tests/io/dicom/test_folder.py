"""A DICOM folder as exports come (lungdeform.io.dicom.folder): the image series told from the rest."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest

from lungdeform.errors import ReadError
from lungdeform.io.dicom.folder import SeriesChoice, candidates, ignored_line, pick, survey
from lungdeform.io.dicom.fourdct import is_fourdct, read_phases
from lungdeform.io.dicom.rtstruct import read_ct_series
from lungdeform.io.dicom.series import dicom_series_files
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from tests.fourdct_phantom import phase_ct, write_slices
from tests.vendor_dicom import (
    EXTRAS,
    SERIES_UID,
    THICK_UID,
    write_dicomdir_export,
    write_export_extras,
    write_vendor_ct,
)


def _image(rng, shape=(12, 16, 20)) -> Image:
    """A small CT (HU within the vendor writer's 12 unsigned bits at slope 0.5)."""
    a = np.rint(rng.uniform(-1000, 400, shape)).astype(np.int16)
    return Image(a, np.array([1.5, 1.5, 3.0]), np.array([-15.0, -12.0, -18.0]), np.eye(3))


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """A planning system's export in one folder: the CT, a second (thicker) reconstruction, a
    localizer, an RTSTRUCT, an RTPLAN, an RTDOSE, a REG, a KO, a README and a Thumbs.db."""
    rng = np.random.default_rng(3601)
    d = tmp_path_factory.mktemp("export")
    image = _image(rng)
    ct = write_vendor_ct(d / "flat", image, rng)
    write_export_extras(d / "flat", image, ct, rng, gtv=((0.0, 0.0, 0.0), 6.0))
    return {"dir": d, "image": image, "ct": ct, "flat": d / "flat"}


def test_an_export_folder_reads_as_its_ct_and_names_what_else_it_holds(export):
    # truth: the CT's voxels (the vendor's slope and intercept applied) whatever else lies beside it;
    # each object that is not the CT named once, by file name and kind; only the two reconstructions
    # are candidates (the localizer is not), and choosing one by UID or description reads it
    flat = export["flat"]
    found = survey(flat)
    assert [s.uid for s in candidates(found)] == [SERIES_UID, THICK_UID]
    with pytest.raises(ReadError, match=r"holds 2 CT series \(.*2\.1 'Thorax 3\.0 Br40 Planning' \(12 CT image\(s\)\); "
                                        r".*2\.2 'Thorax 6\.0 Br40' \(6 CT image\(s\)\)\).*--series UID or "
                                        r"--series-description TEXT"):
        read_image(flat)
    ignored: list[str] = []
    img = read_image(flat, series=SeriesChoice(description="thorax 3.0 br40 planning"), ignored=ignored)
    assert np.array_equal(img.array.astype(float), export["image"].array.astype(float))
    assert len(ignored) == 1
    for name, what in EXTRAS.items():
        assert f"{name} ({what})" in ignored[0], name
    assert "'Topogram 0.6 T20f' (1 CT image(s), a localizer)" in ignored[0]
    assert "'Thorax 6.0 Br40' (6 CT image(s), another series)" in ignored[0]
    thick = read_image(flat, series=SeriesChoice(uid=THICK_UID))
    assert thick.array.shape == (6, 16, 20) and thick.spacing[2] == pytest.approx(6.0)
    assert len(read_ct_series(flat, SeriesChoice(description="Planning")).sop_uids) == 12  # the one that contains it
    for choice, message in ((SeriesChoice(uid="1.2.3"), "no image series matches --series 1.2.3"),
                            (SeriesChoice(description="Thorax"), "--series-description 'Thorax' matches 2 series")):
        with pytest.raises(ReadError, match=message):
            read_image(flat, series=choice)


def test_one_file_of_an_export_names_its_own_series_or_what_it_is(export):
    # a file of the export names its series; the RTSTRUCT beside it is said to be one
    flat = export["flat"]
    files = dicom_series_files(export["ct"]["files"][3])
    assert sorted(files) == sorted(export["ct"]["files"])
    with pytest.raises(ReadError, match=r"RS_plan.dcm: not a readable DICOM image slice \(it is RTSTRUCT\)"):
        dicom_series_files(flat / "RS_plan.dcm")


def test_a_dicomdir_is_followed(export, tmp_path):
    # truth: pydicom's File-set wrote the media export (files renamed into PT*/ST*/SE*/ under a
    # DICOMDIR); the CT read through it equals the volume, and a file the DICOMDIR names that is
    # missing is named among the ignored (the rest still read)
    flat = export["flat"]
    files = [f for f in flat.iterdir() if f.name not in ("README.txt", "Thumbs.db")]
    write_dicomdir_export(files, tmp_path / "cd")
    shutil.rmtree(tmp_path / "cd" / next(p.name for p in (tmp_path / "cd").iterdir() if p.is_dir()) / "ST000000" /
                  _series_folder(tmp_path / "cd", "RTPLAN"))
    ignored: list[str] = []
    img = read_image(tmp_path / "cd", series=SeriesChoice(uid=SERIES_UID), ignored=ignored)
    assert np.array_equal(img.array.astype(float), export["image"].array.astype(float))
    assert ignored[0].startswith(f"{tmp_path / 'cd'}: followed its DICOMDIR (") and "README.TXT (no DICOM)" in ignored[0]
    assert "(named in the DICOMDIR, missing)" in ignored[0] and "(RTSTRUCT)" in ignored[0] and "(RTDOSE grid)" in ignored[0]


def _series_folder(cd, modality: str) -> str:
    """The SE* folder of the media export ``cd`` that holds the object of ``modality``."""
    for f in cd.rglob("*"):
        if (f.is_file() and f.name not in ("DICOMDIR", "README.TXT")
                and pydicom.dcmread(f, stop_before_pixels=True).Modality == modality):
            return f.parent.name
    raise AssertionError(modality)


def test_a_damaged_dicomdir_is_said_and_the_folder_read(export, tmp_path):
    # a DICOMDIR whose records cannot be read: the folder's own files are read instead, and said
    shutil.copytree(export["flat"], tmp_path / "f")
    (tmp_path / "f" / "DICOMDIR").write_bytes(b"\0" * 128 + b"DICM" + b"\x02\x00\x10\x00UI\x04\x001.2\0")
    ignored: list[str] = []
    read_image(tmp_path / "f", series=SeriesChoice(uid=SERIES_UID), ignored=ignored)
    assert "its DICOMDIR could not be followed" in ignored[0]


def test_a_4dct_folder_with_an_export_around_it(export, tmp_path):
    # ten phases in one folder, beside an RTSTRUCT, an RTPLAN, a README and an average CT without a
    # phase: the ten phases read, in order; the rest named (the average as set aside)
    rng = np.random.default_rng(3602)
    d = tmp_path / "4d"
    for p in range(10):
        write_slices(d, phase_ct(1.0 + 0.04 * min(p, 10 - p), rng), {"0008|103e": f"CT {10 * p}%"}, f"1.2.3.{p + 10}",
                     name=f"p{p}_")
    write_slices(d, phase_ct(1.1, rng), {"0008|103e": "Average CT"}, "1.2.3.99", name="avg_")
    for name in ("RS_plan.dcm", "RP_plan.dcm", "README.txt"):
        shutil.copy(export["flat"] / name, d / name)
    assert is_fourdct(d)
    ignored: list[str] = []
    phases = read_phases(d, ignored=ignored)
    assert [ph.label for ph in phases] == [f"{10 * p}%" for p in range(10)]
    assert "RS_plan.dcm (RTSTRUCT)" in ignored[0] and "README.txt (no DICOM)" in ignored[0]
    assert any("set aside 1 series that carry no phase (1.2.3.99 'Average CT'" in line for line in ignored)


def test_pick_refuses_a_folder_without_images(tmp_path):
    (tmp_path / "README.txt").write_text("nothing here")
    with pytest.raises(ReadError, match=r"no DICOM image series \(found: README.txt \(no DICOM\)\)"):
        pick(survey(tmp_path))
    assert ignored_line(survey(tmp_path)) == f"{tmp_path}: ignored 1 object(s) that are not the images read: README.txt (no DICOM)"


def _gdcm_tags(path: str, tags) -> dict[str, str]:
    """``tags`` of one file as GDCM reads them (SimpleITK, header only, stripped), and ``""`` when absent."""
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetFileName(path)
    reader.SetImageIO("GDCMImageIO")
    reader.ReadImageInformation()
    return {t: reader.GetMetaData(t).strip().strip("\0") if reader.HasMetaDataKey(t) else "" for t in tags}


def test_the_tags_the_survey_keeps_are_what_gdcm_reads(export, tmp_path, rng):
    # truth: an independent reader, GDCM (what the 4-D CT reader asked for each file before the survey
    # kept these tags in its own pass): decimal strings, times and UIDs as written (padding stripped),
    # binary numbers (Rows US, TemporalPositionIndex UL) written out, a tag absent from the file "";
    # on the vendor export (every third slice implicit VR, a private block, ISO_IR 100) and on
    # GDCM-written slices carrying TemporalPositionIndex and TriggerTime
    tags = ("0020|000e", "0008|0018", "0020|0032", "0020|0037", "0018|1120", "0028|0030", "0028|0010", "0028|0011",
            "0028|0008", "0020|9128", "0020|0100", "0018|1060", "0008|0032", "0020|000d", "0020|0052")
    write_slices(tmp_path / "gdcm", phase_ct(1.0, rng),
                 {"0020|9128": "7", "0018|1060": "350.5 ", "0008|0032": "101502.25"}, "1.2.826.0.1.3680043.2.1125.7.41")
    flat = tmp_path / "flat"
    shutil.copytree(export["flat"], flat)  # the module's export is left as it is
    compared = 0
    for folder in (flat, tmp_path / "gdcm"):
        for series in survey(folder, tags).series:
            assert len(series.tags) == len(series.files)
            for f, kept in zip(series.files, series.tags):
                assert kept == _gdcm_tags(f, tags), f
                compared += 1
    assert compared > 24 + 12  # every slice of both CTs (and the localizer) compared
    # a file without the 128-byte preamble and "DICM" (GDCM and pydicom read such files) is read by
    # pydicom's whole-file reader instead: the same tags as its twin with the preamble
    twin = survey(flat, tags).series[0]
    (tmp_path / "bare").mkdir()
    (tmp_path / "bare" / "x.dcm").write_bytes(Path(twin.files[0]).read_bytes()[132:])
    bare = survey(tmp_path / "bare", tags).series[0]
    assert bare.tags[0] == twin.tags[0] == _gdcm_tags(bare.files[0], tags)
    gdcm = survey(tmp_path / "gdcm", tags).series[0].tags[0]
    assert (gdcm["0020|9128"], gdcm["0018|1060"], gdcm["0008|0032"]) == ("7", "350.5", "101502.25")
    # text is decoded with the file's SpecificCharacterSet (GDCM gives its bytes undecoded): a
    # Latin-1 description reads as written
    f = survey(flat).series[0].files[0]
    ds = pydicom.dcmread(f)
    ds.SeriesDescription = "Thorax Übersicht 30%"
    ds.save_as(f)
    kept = {s.uid: s for s in survey(flat, ("0008|103e",)).series}[ds.SeriesInstanceUID]
    assert kept.tags[list(kept.files).index(f)]["0008|103e"] == "Thorax Übersicht 30%"
    assert all(t == {} for t in survey(flat).series[0].tags)  # none asked for, none kept
