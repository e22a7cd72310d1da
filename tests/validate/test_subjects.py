"""Two-volume subject folders (lungdeform.validate.subjects): any NAME_exp/insp mask pairs, landmarks optional."""

from __future__ import annotations

import csv
import io

import pytest

from lungdeform.errors import ReadError
from lungdeform.validate.subjects import cohort_manifest, find_subjects, incomplete_subjects


def _touch(folder, *names):
    for n in names:
        (folder / n).write_text("x")


def test_any_format_landmarks_optional_and_incomplete_subjects_named(tmp_path):
    # truth: a subject is a NAME with both masks, in any image format (the two may differ); its landmarks
    # count only when both files are there; a NAME with one mask is no subject, and is named
    _touch(tmp_path, "a_exp_mask.nii.gz", "a_insp_mask.nii.gz", "a_exp_landmarks.txt", "a_insp_landmarks.txt",
           "b.1_exp_mask.mha", "b.1_insp_mask.nrrd",
           "c_exp_mask.nii", "c_insp_mask.nii", "c_exp_landmarks.txt",
           "d_exp_mask.mha", "notes.txt", "e_exp_mask.png", "e_insp_mask.png")
    subjects = {s.name: s for s in find_subjects(tmp_path)}
    assert sorted(subjects) == ["a", "b.1", "c"]
    assert subjects["a"].landmarks == (tmp_path / "a_exp_landmarks.txt", tmp_path / "a_insp_landmarks.txt")
    assert subjects["b.1"].scans == (tmp_path / "b.1_exp_mask.mha", tmp_path / "b.1_insp_mask.nrrd")
    assert subjects["b.1"].landmarks is None and subjects["c"].landmarks is None
    assert all(s.sides is None for s in subjects.values())  # every lung the masks hold
    lacking = incomplete_subjects(tmp_path)
    assert set(lacking) == {"c", "d"}
    assert lacking["d"] == ["its insp mask (d_insp_mask.*)"]
    assert lacking["c"] == ["c_insp_landmarks.txt (its landmarks are not used)"]


def test_the_dirlab_and_itk_layouts_and_empty_folders(tmp_path):
    # truth: the DIR-Lab COPDgene names are such pairs (with landmarks); the ITK pair is one right lung;
    # a folder without any pair, or no folder, is refused naming it
    copd = tmp_path / "copd"
    copd.mkdir()
    _touch(copd, *(f"copd3_{ph}_{kind}" for ph in ("exp", "insp") for kind in ("mask.nii.gz", "landmarks.txt")))
    (s,) = find_subjects(copd)
    assert s.name == "copd3" and s.landmarks is not None
    itk = tmp_path / "itk"
    itk.mkdir()
    _touch(itk, "CT_3D_lung_fixed_mask.mha", "CT_3D_lung_moving_mask.mha", "CT_3D_lung_fixed_point_set_corrected.txt",
           "CT_3D_lung_moving_point_set_corrected.txt")
    (s,) = find_subjects(itk)
    assert (s.name, s.sides) == ("itk", ("right",))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReadError, match="no two-volume subject"):
        find_subjects(tmp_path / "empty")
    with pytest.raises(ReadError, match="not a folder"):
        find_subjects(tmp_path / "nothing")


def test_two_masks_of_one_phase_are_refused(tmp_path):
    # truth: NAME_exp_mask.nii.gz and NAME_exp_mask.mha: which is the scan is not for us to guess
    _touch(tmp_path, "a_exp_mask.nii.gz", "a_exp_mask.mha", "a_insp_mask.mha")
    with pytest.raises(ReadError, match="two exp masks of 'a'"):
        find_subjects(tmp_path)


def test_cohort_manifest_rows(tmp_path):
    # truth: two rows per subject, expiration first, side both (or the subject's side), volumes empty,
    # absolute paths, landmarks empty for a subject without them
    _touch(tmp_path, "a_exp_mask.nii.gz", "a_insp_mask.nii.gz", "a_exp_landmarks.txt", "a_insp_landmarks.txt",
           "b_exp_mask.mha", "b_insp_mask.mha")
    rows = list(csv.reader(io.StringIO(cohort_manifest(find_subjects(tmp_path)))))
    assert rows[0] == ["subject", "side", "volume_ml", "path", "landmarks"]
    assert [r[:3] for r in rows[1:]] == [["a", "both", ""], ["a", "both", ""], ["b", "both", ""], ["b", "both", ""]]
    assert rows[1][3] == str((tmp_path / "a_exp_mask.nii.gz").resolve())
    assert rows[2][4] == str((tmp_path / "a_insp_landmarks.txt").resolve())
    assert rows[3][4] == rows[4][4] == ""
