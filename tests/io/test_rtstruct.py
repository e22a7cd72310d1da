"""Tests of lungdeform.io.rtstruct: RTSTRUCT contours read, written on a CT series, read back."""

from __future__ import annotations

import tarfile

import numpy as np
import pydicom
import pytest
import trimesh

from lungdeform.errors import InputError, ReadError
from lungdeform.io.rtstruct import (
    RTSTRUCT_SOP_CLASS,
    pick_structure,
    read_ct_series,
    read_rtstruct,
    structure_mesh,
    structure_points,
    write_rtstruct,
)
from tests.io.dicom_support import write_ct_series

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
