"""lungdeform.evaluate.inputs: reading and checking a fit's inputs (the whole step runs through
``lungdeform fit`` in tests/cli/test_fit.py)."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.evaluate.inputs import check_landmarks, landmark_mask_warnings, read_input
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from lungdeform.io.landmarks import read_elastix_points
from lungdeform.io.mask import extract_surface
from tests.conftest import require_path
from tests.io.test_mask import LOBE_SPACING as sp
from tests.io.test_mask import write_lobe_map


def test_landmarks_outside_image():
    # a 10-voxel cube of 1 mm voxels centred on index 0 spans −0.5…9.5 mm: a point at 9.4 mm is
    # inside, one at 12 mm (row 2) is not
    img = Image(np.zeros((10, 10, 10), np.uint8), np.ones(3), np.zeros(3), np.eye(3), "img.mha")
    check_landmarks(np.array([[0.0, 0, 0], [9.4, 9.4, 9.4]]), img, "lm.txt")
    with pytest.raises(InputError, match="lm.txt: 1 landmarks lie outside the image img.mha"):
        check_landmarks(np.array([[0.0, 0, 0], [0, 0, 12.0]]), img, "lm.txt")


def test_read_input_takes_the_requested_side_of_a_lobe_map(tmp_path):
    # A lobe label map (coronacases convention: 1-2 left, 3-5 right) holds both lungs; the larger
    # right lung used to win for --side left. Truth: the side's lobe voxels lie at LPS x > 0 (left)
    # or x < 0 (right), and its surface volume matches their voxel count.
    path = tmp_path / "lobes.nii.gz"
    a = write_lobe_map(path)
    for side, labels, sign in (("left", (1, 2), 1.0), ("right", (3, 4, 5), -1.0)):
        surface = read_input(path, side)[0]
        assert sign * surface.vertices[:, 0].mean() > 0
        assert surface.volume == pytest.approx(np.isin(a, labels).sum() * np.prod(sp), rel=0.06)


def test_landmarks_outside_their_own_mask_are_reported(tmp_path):
    # a 20 mm cube of lung in a 1 mm grid: landmarks inside give no warning; a set shifted by 15 mm
    # (another frame, or the other scan's file) has most of its points outside and is reported
    a = np.zeros((40, 40, 40), np.uint8)
    a[10:30, 10:30, 10:30] = 1
    img = Image(a, np.ones(3), np.array([-5.0, 0, 0]), np.eye(3), "mask.mha")
    surface = extract_surface(img).surface
    pts = np.random.default_rng(4).uniform(6, 23, size=(30, 3))  # world x = index − 5: all inside the cube
    assert landmark_mask_warnings(pts, img, surface, "ee.txt") == []
    w = landmark_mask_warnings(pts + np.array([0, 0, 15.0]), img, surface, "ee.txt")
    assert len(w) == 1 and w[0].startswith("ee.txt: ") and "outside the lung mask of mask.mha" in w[0]
    assert landmark_mask_warnings(pts, None, None, "ee.txt") == []  # a mesh input: nothing to check
    # a hole in the mask (a vessel left out of a user's mask) is inside the lung: landmarks there
    # are not outside, although their voxels are off the mask
    holed = a.copy()
    holed[16:24, 16:24, 16:24] = 0
    img2 = Image(holed, np.ones(3), np.array([-5.0, 0, 0]), np.eye(3), "holed.mha")
    in_hole = np.random.default_rng(5).uniform(12, 18, size=(10, 3))  # world = index (y, z); x index − 5
    assert landmark_mask_warnings(np.vstack([pts, in_hole]), img2, extract_surface(img2).surface, "ee.txt") == []


def test_swapped_itk_landmark_files_are_reported(data_dir):
    # real data: each ITK landmark set lies inside its own lung mask, and the swapped files do not
    # (8-12 % of them land outside the other scan's mask), so a swap is reported
    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    fixed, moving = (read_image(folder / f"CT_3D_lung_{k}_mask.mha") for k in ("fixed", "moving"))
    sf, sm = (extract_surface(img).surface for img in (fixed, moving))
    lf, lm = (read_elastix_points(folder / f"CT_3D_lung_{k}_point_set_corrected.txt") for k in ("fixed", "moving"))
    assert landmark_mask_warnings(lf, fixed, sf, "f") == [] and landmark_mask_warnings(lm, moving, sm, "m") == []
    assert landmark_mask_warnings(lm, fixed, sf, "m") and landmark_mask_warnings(lf, moving, sm, "f")
