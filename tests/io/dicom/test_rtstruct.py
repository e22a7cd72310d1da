"""Tests of lungdeform.io.dicom.rtstruct: RTSTRUCT contours read, written on a CT series, read back."""

from __future__ import annotations

import tarfile
import time

import numpy as np
import pydicom
import pytest
import trimesh

from lungdeform.errors import InputError, ReadError
from lungdeform.geometry.contours import MAX_CONTOURS, MAX_SLICES
from lungdeform.io.dicom.rtstruct import (
    RTSTRUCT_SOP_CLASS,
    Structure,
    check_structure_on_ct,
    pick_structure,
    read_ct_series,
    read_rois,
    read_rtstruct,
    structure_mesh,
    structure_points,
    write_rtstruct,
)
from tests.io.dicom_support import circle, patch_element, rtstruct_bytes, write_ct_series

CENTRE = np.array([1.0, 0.5, 0.3])
RADIUS = 12.0


@pytest.fixture(scope="module")
def ct(tmp_path_factory):
    """32 x 32 x 20 axial slices of 2 mm, z from -19 to 19 mm."""
    return read_ct_series(write_ct_series(tmp_path_factory.mktemp("ct") / "series"))


def _sphere(centre=CENTRE, radius=RADIUS):
    s = trimesh.creation.icosphere(4, radius=radius)
    return np.asarray(s.vertices) + centre, np.asarray(s.faces)


def test_round_trip_within_half_a_voxel(ct, tmp_path):
    # a sphere cut by each slice plane: points on the sphere up to the chords of the icosphere
    # (<0.02 mm) and the DS formatting (0.0005 mm), far within half a voxel (1 mm); 12 slices
    # (z = -11 … 11) cut a sphere spanning z = -11.7 … 12.3
    v, f = _sphere()
    path = tmp_path / "rs.dcm"
    assert write_rtstruct(path, ct, [("GTV", v, f, "GTV"), ("Lung", v * 0.5, f)]) == {"GTV": 12, "Lung": 6}
    structures = read_rtstruct(path)
    assert list(structures) == ["GTV", "Lung"] and structures["GTV"].kind == "GTV"
    gtv = structures["GTV"]
    pts = structure_points(gtv)
    assert np.abs(np.linalg.norm(pts - CENTRE, axis=1) - RADIUS).max() < 1.0
    slice_z = ct.origins[:, 2]
    for c in gtv.contours:  # every contour lies on one slice of the series
        assert np.ptp(c[:, 2]) == 0 and np.abs(slice_z - c[0, 2]).min() < 1e-6
    assert structures["Lung"].colour != gtv.colour


def test_written_file_references_the_series(ct, tmp_path):
    # the RTSTRUCT names the CT's study and frame of reference, every slice of the series, and per
    # contour the slice whose z it lies on
    v, f = _sphere()
    write_rtstruct(tmp_path / "rs.dcm", ct, [("GTV", v, f)])
    ds = pydicom.dcmread(tmp_path / "rs.dcm")
    assert ds.SOPClassUID == RTSTRUCT_SOP_CLASS and ds.Modality == "RTSTRUCT"
    assert ds.file_meta.MediaStorageSOPClassUID == RTSTRUCT_SOP_CLASS
    assert ds.StudyInstanceUID == ct.header.StudyInstanceUID and ds.FrameOfReferenceUID == ct.header.FrameOfReferenceUID
    series = ds.ReferencedFrameOfReferenceSequence[0].RTReferencedStudySequence[0].RTReferencedSeriesSequence[0]
    assert series.SeriesInstanceUID == ct.header.SeriesInstanceUID
    assert [r.ReferencedSOPInstanceUID for r in series.ContourImageSequence] == ct.sop_uids
    z_of = dict(zip(ct.sop_uids, ct.origins[:, 2]))
    for c in ds.ROIContourSequence[0].ContourSequence:
        assert c.ContourGeometricType == "CLOSED_PLANAR"
        assert float(c.ContourData[2]) == pytest.approx(z_of[c.ContourImageSequence[0].ReferencedSOPInstanceUID])


def test_identity_rewrite_returns_the_same_contours(ct, tmp_path):
    # read, made a surface through its contours, cut by the same slices again: the same polygons
    # up to the signed-distance grid (0.5 mm pixels: a quarter pixel, far within half a voxel)
    v, f = _sphere()
    write_rtstruct(tmp_path / "a.dcm", ct, [("GTV", v, f)])
    first = read_rtstruct(tmp_path / "a.dcm")["GTV"]
    mv, mf = structure_mesh(first)
    write_rtstruct(tmp_path / "b.dcm", ct, [("GTV", mv, mf)])
    again = read_rtstruct(tmp_path / "b.dcm")["GTV"]
    assert len(again.contours) == len(first.contours)
    for a in again.contours:
        b = next(c for c in first.contours if c[0, 2] == a[0, 2])
        ra, rb = np.linalg.norm(a[:, :2] - CENTRE[:2], axis=1), np.linalg.norm(b[:, :2] - CENTRE[:2], axis=1)
        assert np.abs(ra - rb.mean()).max() < 1.0


def test_missing_structure_lists_the_names(ct, tmp_path):
    # the message names the file and every ROI name there is
    v, f = _sphere()
    write_rtstruct(tmp_path / "rs.dcm", ct, [("GTV", v, f), ("ITV", v, f)])
    with pytest.raises(InputError, match=r"rs.dcm: no structure 'CTV' \(structures: 'GTV', 'ITV'\)"):
        pick_structure(read_rtstruct(tmp_path / "rs.dcm"), "CTV", str(tmp_path / "rs.dcm"))


def test_not_an_rtstruct(ct, tmp_path):
    # a CT slice is DICOM but not a structure set; a text file is not DICOM at all
    with pytest.raises(ReadError, match="not an RTSTRUCT"):
        read_rtstruct(ct.source + "/slice000.dcm")
    (tmp_path / "x.dcm").write_text("x_mm,y_mm,z_mm\n")
    with pytest.raises(ReadError, match="x.dcm: not a DICOM file"):
        read_rtstruct(tmp_path / "x.dcm")


@pytest.mark.realdata
def test_popi_gtv_rtstruct(data_dir, tmp_path):
    # a 12 mm spherical "GTV" in the right lung of the POPI phase-00 CT (lung at (-90, 80, -50) mm
    # LPS: -857 HU there), written on the real series: pydicom reads it, and every referenced SOP
    # Instance UID is a slice of the series (2 mm slices: 12 contours, z within 12 mm of -50)
    archive = data_dir / "popi-ct-phase00" / "popi_phase00_dicom_141slices.tar.gz"
    if not archive.is_file():
        pytest.skip(f"{archive} missing")
    with tarfile.open(archive) as tar:
        tar.extractall(tmp_path, filter="data")
    ct = read_ct_series(tmp_path / "popi00")
    assert len(ct.sop_uids) == 141
    v, f = _sphere(np.array([-90.0, 80.0, -50.0]), 12.0)
    write_rtstruct(tmp_path / "gtv.dcm", ct, [("GTV", v, f, "GTV")])
    ds = pydicom.dcmread(tmp_path / "gtv.dcm")
    refs = {c.ContourImageSequence[0].ReferencedSOPInstanceUID for c in ds.ROIContourSequence[0].ContourSequence}
    assert len(refs) == 12 and refs <= set(ct.sop_uids)
    assert ds.FrameOfReferenceUID == ct.header.FrameOfReferenceUID
    pts = structure_points(read_rtstruct(tmp_path / "gtv.dcm")["GTV"])
    assert np.abs(np.linalg.norm(pts - [-90.0, 80.0, -50.0], axis=1) - 12.0).max() < 0.5


# --- bad structures, bad reference CTs, names (issue: no silent wrong answers) --------------------

def _rs(tmp_path, rois, **kw):
    path = tmp_path / "rs.dcm"
    path.write_bytes(rtstruct_bytes(rois, **kw))
    return path


def _mesh_of(path, name="GTV"):
    return structure_mesh(pick_structure(read_rois(path), name, str(path)), str(path))


def test_a_nan_contour_is_named_not_dropped(tmp_path):
    # a NaN in contour 3 used to be dropped without a word (and the stack then called "not evenly
    # spaced"): it is refused, naming the file, the contour and the structure
    contours = [circle(z) for z in (-4.0, -2.0, 0.0, 2.0, 4.0)]
    contours[2] = contours[2].astype(object)
    contours[2][0, 1] = "nan"
    path = _rs(tmp_path, [(1, "GTV", contours)])
    assert len(read_rois(path)[0].contours) == 5
    with pytest.raises(InputError, match=r"rs.dcm: contour 3 of structure 'GTV' has non-finite coordinates$"):
        _mesh_of(path)


@pytest.mark.parametrize("z, message", [
    ((-12.0, -6.0, 12.0), r"not evenly spaced: gaps 6.00 to 18.00 mm"),  # passed the old median-based check
    ((-4.0, -2.0, 0.0, 4.0, 6.0), r"not evenly spaced: gaps 2.00 to 4.00 mm \(4.00 mm between the slices at 0.00"),
])
def test_a_stack_with_gaps_is_refused(tmp_path, z, message):
    # contours missing on a slice inside the structure: the surface would bridge the gap; refused,
    # naming the structure and where the gap is
    path = _rs(tmp_path, [(1, "GTV", [circle(level) for level in z])])
    with pytest.raises(InputError, match=r"rs.dcm: structure 'GTV': contour slices " + message):
        _mesh_of(path)


def test_a_degenerate_contour_names_file_and_structure(tmp_path):
    # "contour: degenerate polygon" named neither the file nor the structure
    line = np.column_stack([np.linspace(-5, 5, 24), np.zeros(24), np.zeros(24)])
    path = _rs(tmp_path, [(1, "GTV", [line, line + [0, 0, 2.0]])])
    with pytest.raises(InputError, match=r"rs.dcm: contour 1 of structure 'GTV': degenerate polygon"):
        _mesh_of(path)
    path = _rs(tmp_path, [(1, "GTV", [circle(0.0), line + [0, 0, 2.0]])])
    with pytest.raises(InputError, match=r"rs.dcm: contour 2 of structure 'GTV' is degenerate \(no area\)"):
        _mesh_of(path)


def test_contours_enclosing_no_area_are_skipped_and_named(tmp_path):
    # issue 36: rt-utils' GTV on a real CT was refused for "contour 8 … has 2 point(s)"; planning
    # systems and Slicer skip a contour that encloses no area. Truth: with the tips (1 and 2 points),
    # a repeated-point contour and a collinear one removed, the surface is that of the five circles
    # alone; each removed contour is named once (structure, its number in the file, its slice);
    # what is broken (NaN) is still refused, and a structure of tips only is refused
    from lungdeform.io.dicom.rtstruct import enclosing_contours

    rings = [circle(z) for z in (-4.0, -2.0, 0.0, 2.0, 4.0)]
    tip2 = np.array([[90.0, 0.0, 6.0], [90.5, 0.0, 6.0]])
    tip1 = np.array([[95.0, 0.0, 0.0]])
    repeated = np.array([[90.0, 2.0, 2.0], [91.0, 2.0, 2.0], [90.0, 2.0, 2.0]])
    collinear = np.array([[90.0 + t, -3.0, -2.0] for t in (0.0, 0.5, 1.0)])
    path = _rs(tmp_path, [(1, "GTV", [rings[0], tip2, rings[1], tip1, rings[2], repeated, rings[3], collinear, rings[4]])])
    s, lines = enclosing_contours(pick_structure(read_rois(path), "GTV", str(path)), str(path))
    assert s.numbers == (1, 3, 5, 7, 9) and len(s.contours) == 5
    assert lines == [f"{path}: structure 'GTV': contour 2 (2 point(s)) on the slice at z = 6.00 mm encloses no area: skipped",
                     f"{path}: structure 'GTV': contour 4 (1 point(s)) on the slice at z = 0.00 mm encloses no area: skipped",
                     (f"{path}: structure 'GTV': contour 6 (3 points, 2 distinct) on the slice at z = 2.00 mm encloses no "
                      "area: skipped"),
                     (f"{path}: structure 'GTV': contour 8 (3 points on a line) on the slice at z = -2.00 mm encloses no "
                      "area: skipped")]
    v, f = structure_mesh(s, str(path))
    (tmp_path / "clean").mkdir()
    clean_v, clean_f = _mesh_of(_rs(tmp_path / "clean", [(1, "GTV", rings)]))
    assert np.allclose(v, clean_v) and np.array_equal(f, clean_f)
    bad = [rings[0], tip2 * np.array([1.0, np.nan, 1.0]), rings[1]]
    with pytest.raises(InputError, match=r"rs.dcm: contour 2 of structure 'GTV' has non-finite coordinates$"):
        enclosing_contours(pick_structure(read_rois(_rs(tmp_path, [(1, "GTV", bad)])), "GTV", "rs.dcm"), "rs.dcm")
    with pytest.raises(InputError, match=r"rs.dcm: structure 'GTV': none of its 2 contour\(s\) encloses an area"):
        enclosing_contours(pick_structure(read_rois(_rs(tmp_path, [(1, "GTV", [tip1, tip2])])), "GTV", "rs.dcm"), "rs.dcm")


def test_duplicate_roi_names_are_ambiguous(tmp_path):
    # two ROIs named GTV: the dict reader silently took the second; picking the name now fails,
    # naming both ROI numbers; the other names stay usable
    path = _rs(tmp_path, [(3, "GTV", [circle(0.0), circle(2.0)]), (7, "GTV", [circle(0.0, 4.0), circle(2.0, 4.0)]),
                          (9, "ITV", [circle(0.0), circle(2.0)])])
    with pytest.raises(InputError, match=r"rs.dcm: 2 ROIs are named 'GTV' \(ROI numbers 3 and 7\)"):
        pick_structure(read_rois(path), "GTV", str(path))
    assert pick_structure(read_rois(path), "ITV", str(path)).number == 9


def test_contour_density_is_bounded(tmp_path):
    # 4000 contours 0.01 mm apart took more than 120 s and 3.2 GB; such stacks (and stacks over the
    # count bounds) are refused before any grid is allocated, in well under a few seconds each
    tri = [circle(0.01 * k, 8.0, n=3) for k in range(4000)]
    many = [circle(0.5 * k, 8.0, n=3) for k in range(MAX_CONTOURS + 1)]
    tall = [circle(0.5 * k, 8.0, n=3) for k in range(MAX_SLICES + 1)]
    for contours, message in ((tri, f"contours on 4000 slices, more than {MAX_SLICES}"),
                              (tri[:1000], "contours 0.01 mm apart"), (many, f"more than {MAX_CONTOURS}"),
                              (tall, f"more than {MAX_SLICES}")):
        start = time.monotonic()
        with pytest.raises(InputError, match=message):
            structure_mesh(Structure("GTV", 1, contours), "rs.dcm")
        assert time.monotonic() - start < 5.0


def _ct_with(tmp_path, drop=(), patch=None, shape=(10, 8, 8)):
    """The synthetic series of 2 mm slices, z = -19 … -1, without the slices ``drop``, slice 4 patched."""
    folder = write_ct_series(tmp_path / "ct", shape=shape)
    for k in drop:
        (folder / f"slice{k:03d}.dcm").unlink()
    if patch is not None:
        patch_element(folder / "slice004.dcm", *patch)
    return folder


@pytest.mark.parametrize("drop, patch, message", [
    ((4, 5, 6), None, r"ct: 3 slice\(s\) missing: the gaps between slices run from 2 to 8 mm \(median 2 mm\); "
                      r"8 mm between slice003.dcm at -13.000 mm and slice007.dcm at -5.000 mm"),
    ((), (0x0020, 0x0037, b"0\\0\\0\\0\\0\\0"), r"slice004.dcm: ImageOrientationPatient \[0.0, 0.0, 0.0, 0.0, 0.0, 0.0\] "
                                              "is not two orthogonal unit vectors"),
    ((), (0x0020, 0x0037, b"1\\0\\0\\0\\1"), r"slice004.dcm: ImageOrientationPatient must be 6 finite numbers"),
    ((), (0x0020, 0x0032, b"left\\up\\-11"), r"slice004.dcm: ImagePositionPatient is not numeric"),
    ((), (0x0020, 0x0032, b"-31\\nan\\-11"), r"slice004.dcm: ImagePositionPatient must be 3 finite numbers"),
    ((), (0x0020, 0x0032, b"-31\\-31\\-13"), r"ct: two slices at one position \(-13.000 mm along the slice normal\)"),
    ((), (0x0020, 0x0037, b"0\\1\\0\\1\\0\\0"), r"slice004.dcm: ImageOrientationPatient differs from"),
])
def test_bad_reference_ct_geometry_is_refused(tmp_path, drop, patch, message):
    # a CT missing slices got a structure written with contours lost; an all-zero orientation gave
    # no contours and no error; a 5-value orientation or a non-numeric position raised a traceback
    with pytest.raises(ReadError, match=message):
        read_ct_series(_ct_with(tmp_path, drop, patch))


def test_structure_against_the_reference_ct(tmp_path):
    # the same series but for 3 slices the GTV is drawn on (the end of the series: still evenly
    # spaced), or a structure of another frame of reference, or reaching beyond the slices: refused
    ct = read_ct_series(write_ct_series(tmp_path / "ct", shape=(10, 8, 8)))
    v, f = _sphere(np.array([0.0, 0.0, -6.0]), 4.0)  # z = -10 … -2: slices 5 … 8
    write_rtstruct(tmp_path / "rs.dcm", ct, [("GTV", v, f)])
    gtv = read_rois(tmp_path / "rs.dcm")[0]
    check_structure_on_ct(gtv, ct, "rs.dcm")
    for k in (7, 8, 9):
        (tmp_path / "ct" / f"slice{k:03d}.dcm").unlink()
    short = read_ct_series(tmp_path / "ct")
    with pytest.raises(InputError, match=r"rs.dcm: structure 'GTV' is drawn on 2 slice\(s\) that --reference-ct .* lacks"):
        check_structure_on_ct(gtv, short, "rs.dcm")
    other = Structure("GTV", 1, gtv.contours, frame_uid="1.2.3.4", study_uid="1.2.3")
    with pytest.raises(InputError, match=r"rs.dcm: structure 'GTV' is in Frame of Reference 1.2.3.4, --reference-ct .* "
                                         r"in 1.2.826.0.1.3680043.8.498.77.3; study 1.2.3 against"):
        check_structure_on_ct(other, ct, "rs.dcm")
    with pytest.raises(InputError, match=r"ROI 'GTV' reaches .* beyond the slices of --reference-ct"):
        write_rtstruct(tmp_path / "far.dcm", ct, [("GTV", v + [0, 0, 12.0], f)])
    assert not (tmp_path / "far.dcm").exists()


def test_names_round_trip_or_are_fitted(ct, tmp_path):
    # a non-ASCII ROI name was written without SpecificCharacterSet and read back mangled; it is
    # written as UTF-8 (ISO_IR 192) now, and an ASCII file stays without the attribute. A name DICOM's
    # ROI Name (LO, 64 bytes) cannot hold is never a refusal (issue 36): a name over 64 bytes is cut
    # on a character boundary, its state tag kept whole, its whole kept in ROIDescription; a
    # backslash (DICOM's value separator) becomes "_"; two names cut alike are kept apart
    v, f = _sphere()
    write_rtstruct(tmp_path / "a.dcm", ct, [("Tumör é 肺", v, f)])
    assert pydicom.dcmread(tmp_path / "a.dcm").SpecificCharacterSet == "ISO_IR 192"
    assert list(read_rtstruct(tmp_path / "a.dcm")) == ["Tumör é 肺"]
    write_rtstruct(tmp_path / "b.dcm", ct, [("GTV", v, f)])
    assert "SpecificCharacterSet" not in pydicom.dcmread(tmp_path / "b.dcm")
    long_tag = "肺" * 30 + "@phase03"  # 98 bytes of UTF-8
    counts = write_rtstruct(tmp_path / "c.dcm", ct, [("G" * 65, v, f), ("G" * 66, v, f), ("GTV\\2", v, f),
                                                    (long_tag, v, f)])
    rois = pydicom.dcmread(tmp_path / "c.dcm").StructureSetROISequence
    names = [str(r.ROIName) for r in rois]
    assert names == ["G" * 64, "G" * 62 + "~2", "GTV_2", "肺" * 18 + "@phase03"] == list(counts)
    assert all(len(n.encode()) <= 64 for n in names)
    assert [r.get("ROIDescription") for r in rois] == ["G" * 65, "G" * 66, "GTV\\2", long_tag]


def test_a_latin1_patient_name_is_rewritten_as_utf8(tmp_path):
    # the patient's name is copied from the CT: a Latin-1 (ISO_IR 100) name must not be written as
    # bytes of no declared character set; the structure set declares UTF-8 and the name reads back
    folder = write_ct_series(tmp_path / "ct", shape=(10, 8, 8))
    for f in folder.iterdir():
        ds = pydicom.dcmread(f)
        ds.SpecificCharacterSet, ds.PatientName = "ISO_IR 100", "Müller^Jörg"
        ds.save_as(f)
    v, f = _sphere(np.array([0.0, 0.0, -10.0]), 4.0)
    write_rtstruct(tmp_path / "rs.dcm", read_ct_series(folder), [("GTV", v, f)])
    ds = pydicom.dcmread(tmp_path / "rs.dcm")
    assert ds.SpecificCharacterSet == "ISO_IR 192" and str(ds.PatientName) == "Müller^Jörg"


def test_a_truncated_structure_set_says_so(tmp_path):
    # cut where the ROIs begin, pydicom reads the rest without complaint: the error said "no
    # structure 'GTV' (structures: none)", a wrong cause; it names the missing sequence now
    whole = rtstruct_bytes([(1, "GTV", [circle(0.0), circle(2.0)])])
    (tmp_path / "cut.dcm").write_bytes(whole[:whole.index(b"\x06\x30\x20\x00")])
    with pytest.raises(ReadError, match=r"cut.dcm: no StructureSetROISequence: not a complete structure set"):
        read_rois(tmp_path / "cut.dcm")


def test_another_patient_is_refused_and_another_study_said(tmp_path):
    # a structure set of another patient (PatientID) is refused, naming both; the same frame of
    # reference in another study is written, with a warning to check the CT (it was silent before)
    from dataclasses import replace

    ct = read_ct_series(write_ct_series(tmp_path / "ct", shape=(10, 8, 8)))
    v, f = _sphere(np.array([0.0, 0.0, -6.0]), 4.0)
    write_rtstruct(tmp_path / "rs.dcm", ct, [("GTV", v, f)])
    gtv = read_rois(tmp_path / "rs.dcm")[0]
    assert gtv.patient_id == str(ct.header.get("PatientID", "")).strip()
    assert check_structure_on_ct(gtv, ct, "rs.dcm") == []
    with pytest.raises(InputError, match=r"rs.dcm: structure 'GTV' belongs to patient 'SOMEONE-ELSE'.*not the same patient"):
        check_structure_on_ct(replace(gtv, patient_id="SOMEONE-ELSE"), ct, "rs.dcm")
    (warning,) = check_structure_on_ct(replace(gtv, study_uid="1.2.3"), ct, "rs.dcm")
    assert "rs.dcm: structure 'GTV' is in study 1.2.3" in warning and "same Frame of Reference" in warning
