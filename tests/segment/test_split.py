"""Masks holding both lungs in one label → left and right (lungdeform.segment.split), on analytic
ellipsoids and on the DIR-Lab COPDgene masks."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError, MaskError
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from lungdeform.io.landmarks import read_elastix_points
from lungdeform.segment import split as L
from tests.conftest import require_path

SPACING = np.array([2.0, 2.0, 2.5])  # mm, x y z
#: centre x (mm) and semi-axes (x, y, z mm) of the two ellipsoids: the right lung (at -x) larger
RIGHT = (-42.0, (38.0, 28.0, 50.0))
LEFT = (42.0, (32.0, 26.0, 48.0))


def world_grid(shape=(48, 40, 100)):
    """``(z, y, x, 3)`` world mm (LPS, identity direction) of a grid centred on 0, and its origin."""
    nz, ny, nx = shape
    origin = -(np.array([nx, ny, nz]) - 1) / 2 * SPACING
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return np.stack([i, j, k], -1) * SPACING + origin, origin


def ellipsoid(p, cx, axes):
    return ((p[..., 0] - cx) / axes[0]) ** 2 + (p[..., 1] / axes[1]) ** 2 + (p[..., 2] / axes[2]) ** 2 <= 1


def two_lungs(bridge=True, speck=False, source="both.nii.gz", scale=(1.0, 1.0, 1.0)):
    """``(binary mask Image, left truth, right truth)``: two ellipsoids 14 mm apart (the right one
    larger), joined by a 6 × 6 mm bar across the gap when ``bridge`` (so they touch: one component);
    ``speck``: a 2 x 2 x 2-voxel cube 7 mm lateral of the left lung, touching nothing; ``scale``
    multiplies the semi-axes (x, y, z) of both (a larger breath)."""
    p, origin = world_grid()
    sc = np.asarray(scale, float)
    right, left = ellipsoid(p, RIGHT[0], RIGHT[1] * sc), ellipsoid(p, LEFT[0], LEFT[1] * sc)
    m = right | left
    if bridge:
        m |= (p[..., 0] > -10) & (p[..., 0] < 14) & (np.abs(p[..., 1]) <= 3) & (np.abs(p[..., 2]) <= 3)
    if speck:
        m |= (p[..., 0] >= 80) & (p[..., 0] < 84) & (np.abs(p[..., 1]) < 2) & (p[..., 2] >= 0) & (p[..., 2] < 5)
    return Image(m.astype(np.uint8), SPACING, origin, np.eye(3), source), left, right


def test_touching_ellipsoids_split_into_the_two(rng):
    # truth: the bar is the narrowest neck, so the cut falls on it and each part is its ellipsoid
    # (plus half of the 6 x 6 x 24 mm bar, ~0.4 mL, < 1 % of either); the left one lies at +x
    image, left_t, right_t = two_lungs()
    left, right, notes = L.split_lungs(image)
    for got, truth in ((left, left_t), (right, right_t)):
        g = np.asarray(got.array) > 0
        assert abs(int(g.sum()) - int(truth.sum())) / truth.sum() < 0.03
        assert (g & truth).sum() / truth.sum() > 0.99
    assert "touch" in notes[0] and "both.nii.gz" in notes[0]
    split = L.find_lungs(image)
    assert split.touching and 1 <= split.erosions <= 3  # a 3-voxel-thick bar goes in 2 erosions
    assert split.volumes_ml["right"] > split.volumes_ml["left"]


def test_separate_lungs_need_no_erosion_and_a_speck_goes_to_the_nearest(rng):
    # truth: without the bar the ellipsoids are the two components; the speck lies 7 mm lateral of
    # the left lung and > 100 mm from the right one, so it is the left lung's, and is said
    image, left_t, right_t = two_lungs(bridge=False, speck=True)
    split = L.find_lungs(image)
    assert not split.touching and split.erosions == 0 and split.n_specks == 1
    speck = (np.asarray(image.array) > 0) & ~left_t & ~right_t
    assert speck.sum() == 8 and np.all(split.labels[speck] == 1)
    assert split.specks_ml == pytest.approx(8 * np.prod(SPACING) / 1000)
    assert any("1 small pieces (0.08 mL) given to the nearest lung" in n for n in split.notes)


def test_one_blob_is_refused_naming_the_file():
    # truth: one ellipsoid has no neck, so no erosion gives two large side-by-side parts
    p, origin = world_grid()
    one = Image(ellipsoid(p, *RIGHT).astype(np.uint8), SPACING, origin, np.eye(3), "one.nii.gz")
    with pytest.raises(MaskError, match=r"one\.nii\.gz: no two-lung split"):
        L.split_lungs(one)
    # the commands' hook leaves a one-lung mask as it is
    image, notes, split = L.one_lung(one, "right")
    assert image is one and notes == () and split is None


def test_parts_one_above_the_other_are_not_two_lungs():
    # truth: two blobs stacked along z (head-feet) are not a left and a right lung
    p, origin = world_grid()
    m = ellipsoid(p - [0, 0, 30], 0.0, (30, 25, 25)) | ellipsoid(p + [0, 0, 30], 0.0, (30, 25, 25))
    with pytest.raises(MaskError, match="no two-lung split"):
        L.split_lungs(Image(m.astype(np.uint8), SPACING, origin, np.eye(3), "stack.nii.gz"))


def test_sides_follow_lps_x_when_the_grid_is_flipped():
    # truth: with direction diag(-1, 1, 1) index x runs to the patient's right; the lung at larger
    # world x is still the left one (the smaller ellipsoid)
    image, left_t, _ = two_lungs()
    flipped = Image(np.asarray(image.array)[:, :, ::-1], SPACING, image.origin * [-1, 1, 1],
                    np.diag([-1.0, 1.0, 1.0]), "flipped")
    split = L.find_lungs(flipped)
    assert np.count_nonzero(split.labels == 1) == pytest.approx(left_t.sum(), rel=0.03)


def test_landmarks_go_to_their_lung_and_outside_ones_to_the_nearest():
    # truth: the two centres lie in their lungs; (82, 0, 0) is 8 mm lateral of the left lung's edge
    # (x = 74), in neither, nearest the left
    image, _, _ = two_lungs()
    split = L.find_lungs(image)
    pts = np.array([[42.0, 0, 0], [-42.0, 0, 0], [82.0, 0, 0]])
    a = L.assign_landmarks(pts, split, "lm.txt")
    assert a.side.tolist() == ["left", "right", "left"] and a.outside.tolist() == [False, False, True]
    assert a.counts() == {"left": 2, "right": 1, "outside": 1}
    assert "lm.txt: 1 of 3 landmarks lie in neither lung" in a.notes[0]
    # corresponding rows over two inputs: the row whose lungs differ between inputs is dropped too
    later = pts.copy()
    later[1] = [30.0, 0, 0]
    rows, notes = L.landmarks_of_side([pts, later], [split, split], "left", ["a.txt", "b.txt"])
    assert rows.tolist() == [0, 2] and "dropped 1 of 3 in the other lung, 1 of them in different lungs" in notes[-1]
    with pytest.raises(InputError, match="none of the 1 landmarks lie in the right lung"):
        L.landmarks_of_side([pts[:1]], [split], "right", ["a.txt"])


def test_not_binary_is_refused():
    # truth: a mask of one non-zero value (3) is one label, whatever the value; two values are not
    # one label (a lobe map: its lungs come from its labels), and are refused
    image, _, _ = two_lungs()
    lobes = Image(np.asarray(image.array) * 3, SPACING, image.origin, np.eye(3), "lobes")
    assert L.find_lungs(lobes) is not None  # one non-zero value (3) is still one label
    two = np.asarray(image.array).copy()
    two[:, :, :30] = 2 * two[:, :, :30]  # the right lung's lateral part
    with pytest.raises(MaskError, match="not a binary mask"):
        L.split_lungs(Image(two, SPACING, image.origin, np.eye(3), "labels"))


def test_copd1_touching_lungs_split(data_dir):
    # truth (DIR-Lab COPDgene case 1, README of the data folder): the two lungs touch (one component);
    # each is 40-60 % of the mask, the left at larger LPS x, and the masks hold ~all expert landmarks
    # (the README: about 0.3 % fall just outside the automatic masks)
    folder = require_path(data_dir, "dirlab-copd-lung-masks")
    image = read_image(folder / "copd1_exp_mask.nii.gz")
    split = L.find_lungs(image)
    assert split is not None and split.touching
    v = split.volumes_ml
    assert min(v.values()) > 0.4 * sum(v.values())
    cx = [image.index_to_world(np.argwhere(split.labels == k)[:, ::-1]).mean(axis=0)[0] for k in (1, 2)]
    assert cx[0] > cx[1]
    a = L.assign_landmarks(read_elastix_points(folder / "copd1_exp_landmarks.txt"), split)
    assert a.counts()["outside"] <= 0.02 * len(a.side)


def test_split_cache_splits_a_mask_once_and_only_through_the_cache(monkeypatch):
    # truth: through one SplitCache the same mask read twice (a new Image, equal voxels) is split once
    # and gives the very same split; another source name, another cache or no cache splits again
    calls = []
    real = L._find_lungs
    monkeypatch.setattr(L, "_find_lungs", lambda *a: calls.append(1) or real(*a))
    image, _, _ = two_lungs(bridge=False)
    again = Image(np.array(image.array), image.spacing, image.origin, image.direction, image.source)
    cache = L.SplitCache()
    first = L.find_lungs(image, cache=cache)
    assert L.find_lungs(again, cache=cache) is first and len(calls) == 1
    assert L.require_split(again, cache=cache) is first and len(calls) == 1
    assert L.one_lung(again, "left", cache)[2] is first and len(calls) == 1
    other = Image(image.array, image.spacing, image.origin, image.direction, "other.nii.gz")
    assert L.find_lungs(other, cache=cache) is not first and len(calls) == 2 and len(cache) == 2
    assert L.find_lungs(image, cache=L.SplitCache()) is not first and len(calls) == 3
    assert L.find_lungs(image) is not first and len(calls) == 4
    np.testing.assert_array_equal(L.find_lungs(image).labels, first.labels)

def test_split_files_splits_each_mask_file_once_ahead(tmp_path, monkeypatch):
    # truth: a mask file split ahead through the cache is not split again when the fit reads it (the
    # same file read anew); it is what one_lung then gets, the same split
    from lungdeform.io.image import write_image

    calls = []
    real = L._find_lungs
    monkeypatch.setattr(L, "_find_lungs", lambda *a: calls.append(1) or real(*a))
    image, _, _ = two_lungs(bridge=False, source="both.nii.gz")
    path = tmp_path / "both.nii.gz"
    write_image(path, np.asarray(image.array), image.spacing, image.origin, image.direction)
    cache = L.SplitCache()
    cache.split_files([path])
    assert len(calls) == 1 and len(cache) == 1
    split = L.one_lung(read_image(path), "left", cache)[2]
    assert split is not None and len(calls) == 1
    np.testing.assert_array_equal(split.labels, real(read_image(path), L.MAX_EROSIONS, L.MIN_PART).labels)
