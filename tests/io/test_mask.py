"""Mask/label images -> surfaces: analytic shapes with known volume and position, and real masks."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError, MaskError
from lungdeform.geometry.mesh import check_surface
from lungdeform.io.grid import Image, index_to_world
from lungdeform.io.image import read_image
from lungdeform.io.mask import (
    LOBE_LABELS,
    extract_surface,
    label_groups,
    mask_to_surface,
)
from tests.conftest import require_path


def rotation(axis, angle_deg) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


ROTATED = rotation([1, 2, 3], 35.0)
MIRRORED = ROTATED @ np.diag([1.0, -1.0, 1.0])  # det < 0, like the coronacases NIfTI (y flipped)


def sphere_image(direction, radius=12.0, spacing=(0.8, 1.1, 1.5), shape_zyx=(26, 34, 42)):
    """A voxelised ball of ``radius`` mm; its centre is a known world point off the origin."""
    spacing = np.asarray(spacing)
    origin = np.array([-30.0, 20.0, 100.0])
    centre_ijk = (np.array(shape_zyx[::-1]) - 1) / 2.0 + np.array([0.3, -0.2, 0.1])
    centre = index_to_world(centre_ijk[None], spacing, origin, direction)[0]
    k, j, i = np.indices(shape_zyx)
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)
    world = index_to_world(ijk, spacing, origin, direction)
    inside = (np.linalg.norm(world - centre, axis=1) <= radius).reshape(shape_zyx)
    return Image(inside.astype(np.uint8), spacing, origin, direction, "sphere.mha"), centre


def volume_centroid(v, f) -> np.ndarray:
    """Centroid of the enclosed solid (tetrahedra fanned from the origin)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return (vol[:, None] * (a + b + c) / 4.0).sum(axis=0) / vol.sum()


# --------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("direction", [np.eye(3), ROTATED, MIRRORED], ids=["identity", "rotated", "mirrored"])
def test_sphere_volume_and_centre_honour_spacing_origin_direction(direction):
    # a ball of r = 12 mm sampled on an anisotropic, rotated (or mirrored) grid: if spacing,
    # origin or direction were mishandled, the volume or the centre would be off by far more
    image, centre = sphere_image(direction)
    surf = mask_to_surface(image)
    exact = 4.0 / 3.0 * np.pi * 12.0**3
    assert surf.volume > 0  # outward, also when det(direction) < 0
    assert abs(surf.volume / exact - 1) < 0.02
    assert np.linalg.norm(volume_centroid(surf.vertices, surf.faces) - centre) < 0.2
    radii = np.linalg.norm(surf.vertices - centre, axis=1)
    assert np.abs(radii - 12.0).max() < 1.0  # every vertex on the sphere to within a voxel


def test_mask_touching_the_border_gives_a_closed_surface():
    # a 12 x 10 x 8 block filling one corner of the volume touches three faces; without the
    # one-voxel pad marching cubes would leave those sides open
    a = np.zeros((8, 14, 20), np.uint8)
    a[:, :10, :12] = 1
    image = Image(a, (2.0, 2.0, 2.0), (0, 0, 0), np.eye(3), "block.mha")  # 2 mm: lung-sized check
    result = extract_surface(image, smooth_iterations=0)
    v, f, report = check_surface(result.surface.vertices, result.surface.faces)  # closed, manifold
    # level 0.5 puts the faces half-way to the background: exactly the voxel block, minus the
    # chamfers marching cubes cuts along the 12 edges (0.125 voxel² each per voxel of length)
    chamfer = 0.125 * 4 * (12 + 10 + 8)
    assert report.volume_mm3 / 8.0 == pytest.approx(12 * 10 * 8 - chamfer, rel=0.01)


def test_largest_component_kept_and_cavities_filled():
    a = np.zeros((20, 20, 20), np.uint8)
    a[2:14, 2:14, 2:14] = 1
    a[6:9, 6:9, 6:9] = 0  # a cavity: would become an inner surface
    a[17, 17, 17] = 1  # an island: would become a second surface
    image = Image(a, (2.0, 2.0, 2.0), (0, 0, 0), np.eye(3), "blocks.mha")
    result = extract_surface(image, smooth_iterations=0)
    assert result.components_dropped == 1
    assert result.voxels_filled == 27
    assert any("dropped 1" in n for n in result.notes)
    assert result.surface.volume / 8.0 == pytest.approx(12**3 - 0.125 * 4 * 36, rel=0.01)


def test_tiny_mask_is_refused_as_not_lung_sized():
    a = np.zeros((6, 6, 6), np.uint8)
    a[2:4, 2:4, 2:4] = 1
    image = Image(a, (1.0, 1.0, 1.0), (0, 0, 0), np.eye(3), "tiny.mha")
    with pytest.raises(MaskError, match=r"tiny\.mha: .*mm across"):
        mask_to_surface(image)


# --------------------------------------------------------------------------- decimation
def test_decimation_hits_budget_and_stays_closed():
    image, _ = sphere_image(ROTATED, radius=14.0, shape_zyx=(30, 38, 48))
    full = mask_to_surface(image)
    assert full.n_vertices > 3000
    small = mask_to_surface(image, target_vertices=600)
    assert abs(small.n_vertices - 600) <= 30
    check_surface(small.vertices, small.faces)  # closed, manifold, outward, one piece
    assert small.volume == pytest.approx(full.volume, rel=0.01)


# --------------------------------------------------------------------------- errors
def test_no_foreground_names_file_and_labels():
    a = np.zeros((5, 5, 5), np.int16)
    a[1:4, 1:4, 1:4] = 1
    image = Image(a, (1, 1, 1), (0, 0, 0), np.eye(3), "lobes.nii.gz")
    with pytest.raises(MaskError, match=r"lobes\.nii\.gz: no foreground.*\[3, 4, 5\]"):
        mask_to_surface(image, (3, 4, 5))


def test_ct_is_not_a_mask():
    a = np.full((6, 6, 6), -1000, np.int16)
    a[2:4, 2:4, 2:4] = 40
    image = Image(a, (1, 1, 1), (0, 0, 0), np.eye(3), "ct.nii.gz")
    with pytest.raises(MaskError, match=r"ct\.nii\.gz: .*look like a CT"):
        mask_to_surface(image)


def test_a_probability_map_is_not_a_mask():
    # why: a float mask of fractions (a probability map, or a binary mask resampled with linear
    # interpolation) used to count every voxel above 0 as lung: the ball grew by the blur, without a
    # word. Truth: the same ball as 0.0/1.0 floats (whole numbers) gives the uint8 ball's volume; a
    # blurred copy (fractions at its rim) is refused naming the file and the fractions' range
    from scipy.ndimage import gaussian_filter

    image, _ = sphere_image(np.eye(3))
    whole = mask_to_surface(Image(image.array.astype(np.float32), image.spacing, image.origin, image.direction,
                                  "ball.nii.gz"))
    assert whole.volume_ml == pytest.approx(mask_to_surface(image).volume_ml, rel=1e-9)
    blurred = gaussian_filter(image.array.astype(np.float32), 1.5)
    with pytest.raises(MaskError, match=r"^blur\.nii\.gz: \d+ voxel\(s\) hold fractions \(.*\.\..*\), not labels"):
        mask_to_surface(Image(blurred, image.spacing, image.origin, image.direction, "blur.nii.gz"))


# --------------------------------------------------------------------------- label groups
def test_label_groups():
    assert label_groups(None) == {"": None}
    assert label_groups("left,right") == {"left": (1, 2), "right": (3, 4, 5)}
    assert label_groups("lungs") == LOBE_LABELS
    assert label_groups("1,2") == {"labels 1,2": (1, 2)}
    assert label_groups("a=1;b=2,3") == {"a": (1,), "b": (2, 3)}
    assert label_groups([3, 4]) == {"labels 3,4": (3, 4)}
    assert label_groups({"x": 7}) == {"x": (7,)}
    with pytest.raises(InputError, match="labels"):
        label_groups("left,banana")
    with pytest.raises(InputError, match="labels"):
        label_groups([1.5])


# --------------------------------------------------------------------------- real data
@pytest.mark.realdata
@pytest.mark.parametrize("name, litres", [("CT_3D_lung_fixed_mask.mha", 3.36), ("CT_3D_lung_moving_mask.mha", 3.97)])
def test_itk_masks_volumes(data_dir, name, litres):
    # data README: 3.36 L and 3.97 L; the ITK masks touch the cropped medial face (the pad
    # keeps them closed; check_surface inside extract_surface would raise otherwise)
    image = read_image(require_path(data_dir, "itk-right-lung-two-volumes", name))
    surf = mask_to_surface(image, target_vertices=5000)  # decimation keeps volume to 0.1 %; faster check
    assert surf.volume_ml / 1000 == pytest.approx(litres, rel=0.03)


@pytest.mark.realdata
@pytest.mark.slow
def test_coronacases_left_right_volumes_and_sides(coronacases_001):
    # data README: case 001 left/right 1.52 / 1.81 L. In LPS the left lung lies at larger x.
    left = extract_surface(coronacases_001, LOBE_LABELS["left"], target_vertices=3000).surface
    right = extract_surface(coronacases_001, LOBE_LABELS["right"], target_vertices=3000).surface
    assert left.volume_ml / 1000 == pytest.approx(1.52, rel=0.03)
    assert right.volume_ml / 1000 == pytest.approx(1.81, rel=0.03)
    assert left.vertices[:, 0].mean() > right.vertices[:, 0].mean() + 50


# --------------------------------------------------------------------------- lobe maps and flipped NIfTI
def _lobe_map():
    """(z, y, x) int16 lobe map: an ellipsoid 'left lung' (labels 1, 2) at high x index and a bigger
    'right lung' (3, 4, 5) at low x index; with an identity LPS direction left is at larger x."""
    a = np.zeros((48, 64, 96), np.int16)
    zz, yy, xx = np.mgrid[:48, :64, :96]

    def ell(cx, rx):
        return ((xx - cx) / rx) ** 2 + ((yy - 32) / 20) ** 2 + ((zz - 24) / 20) ** 2 < 1

    a[ell(70, 14) & (zz < 24)] = 1
    a[ell(70, 14) & (zz >= 24)] = 2
    a[ell(28, 19) & (zz < 16)] = 3
    a[ell(28, 19) & (zz >= 16) & (zz < 24)] = 4
    a[ell(28, 19) & (zz >= 24)] = 5
    return a


LOBE_SPACING = (2.0, 2.0, 2.5)  # mm, (x, y, z)


def write_lobe_map(path):
    """Write :func:`_lobe_map` with :data:`LOBE_SPACING` and an identity LPS direction; return the array."""
    import SimpleITK as sitk

    a = _lobe_map()
    img = sitk.GetImageFromArray(a)
    img.SetSpacing(LOBE_SPACING)
    img.SetOrigin((-96.0, -64.0, -60.0))
    sitk.WriteImage(img, str(path))
    return a


def test_side_mask_picks_the_side_lobes_also_from_a_ras_nifti(tmp_path):
    import nibabel as nib

    from lungdeform.io.mask import side_mask

    a = write_lobe_map(tmp_path / "lps.nii.gz")
    sp = LOBE_SPACING
    # the same voxels at the same places, stored as a NIfTI with a RAS affine whose i axis is
    # flipped (array reversed along i, affine diag(+2, -2, 2.5)): ITK reports the LPS direction
    # diag(-1, 1, 1), a mirrored (det < 0) non-identity direction. X_RAS = -x_LPS, Y_RAS = -y_LPS.
    data = np.ascontiguousarray(a.transpose(2, 1, 0)[::-1])  # nibabel (i, j, k) order, i reversed
    n0 = data.shape[0]
    aff = np.diag([sp[0], -sp[1], sp[2], 1.0])
    aff[:3, 3] = [96.0 - (n0 - 1) * sp[0], 64.0, -60.0]
    nib.save(nib.Nifti1Image(data, aff), str(tmp_path / "ras.nii.gz"))
    vols, cents = {}, {}
    np.testing.assert_allclose(read_image(tmp_path / "ras.nii.gz").direction, np.diag([-1.0, 1, 1]), atol=1e-6)
    for name in ("lps", "ras"):
        im = read_image(tmp_path / f"{name}.nii.gz")
        for side in ("left", "right"):
            surf = mask_to_surface(side_mask(im, side), smooth_iterations=0)
            vols[name, side] = surf.volume
            cents[name, side] = surf.vertices.mean(axis=0)
    for side, lab in (("left", (1, 2)), ("right", (3, 4, 5))):
        # truth: the voxel count of the side's lobes × voxel volume (marching cubes within a few %)
        truth = np.isin(a, lab).sum() * np.prod(sp)
        assert vols["lps", side] == pytest.approx(truth, rel=0.06)
        # the RAS-stored file is the same lungs in LPS: same volume, same place
        assert vols["ras", side] == pytest.approx(vols["lps", side], rel=1e-6)
        np.testing.assert_allclose(cents["ras", side], cents["lps", side], atol=1e-6)
    assert cents["lps", "left"][0] > 0 > cents["lps", "right"][0]  # LPS: patient left at +x


def test_side_mask_refuses_a_mirrored_convention_and_passes_binary_masks():
    from lungdeform.errors import MaskError
    from lungdeform.io.grid import Image
    from lungdeform.io.mask import side_mask

    a = _lobe_map()
    swapped = np.where(np.isin(a, (1, 2)), a + 2, np.where(a > 2, (a - 2).clip(1, 2), 0)).astype(np.int16)
    im = Image(swapped, np.array([2.0, 2.0, 2.5]), np.zeros(3), np.eye(3), "swapped.nii.gz")
    with pytest.raises(MaskError, match=r"swapped.nii.gz: labels \[1, 2\] \(left lobes .* lie on the other side"):
        side_mask(im, "left")
    only_right = Image(np.where(a > 2, a, 0).astype(np.int16), im.spacing, im.origin, im.direction, "r.nii.gz")
    with pytest.raises(MaskError, match="r.nii.gz: .*none of the left lobes"):
        side_mask(only_right, "left")
    binary = Image((a > 0).astype(np.uint8), im.spacing, im.origin, im.direction, "b.mha")
    assert side_mask(binary, "left") is binary
    with pytest.raises(InputError, match="side must be"):
        side_mask(binary, "up")


@pytest.mark.realdata
def test_side_mask_on_real_coronacases(coronacases_001):
    from lungdeform.io.mask import side_mask

    im = coronacases_001
    vox_ml = float(np.prod(im.spacing)) / 1000.0
    # README: Coronacases_001 left/right 1.52/1.81 L; side_mask must give each side's lobes
    for side, litres in (("left", 1.52), ("right", 1.81)):
        m = side_mask(im, side)
        assert m.array.sum() * vox_ml / 1000.0 == pytest.approx(litres, abs=0.02)


# a 59-voxel random blob (numpy default_rng(0), p = 0.55 in a 5³ box, largest component, filled)
# whose marching-cubes surface has duplicate (fin) faces where one-voxel sheets meet diagonally,
# as real masks have (2 such faces on the POPI left lung)
_FIN_BLOB = [[1, 1, 4], [1, 1, 5], [1, 3, 1], [1, 3, 2], [1, 3, 4], [1, 4, 1], [1, 4, 2], [1, 4, 3], [1, 4, 4],
             [1, 4, 5], [1, 5, 2], [1, 5, 3], [2, 1, 4], [2, 2, 3], [2, 2, 4], [2, 2, 5], [2, 3, 4], [2, 3, 5],
             [2, 4, 2], [2, 4, 3], [2, 4, 5], [2, 5, 1], [2, 5, 2], [2, 5, 3], [2, 5, 5], [3, 1, 1], [3, 1, 4],
             [3, 2, 1], [3, 2, 3], [3, 2, 4], [3, 3, 1], [3, 3, 2], [3, 3, 3], [3, 4, 3], [3, 4, 4], [3, 5, 1],
             [3, 5, 3], [3, 5, 5], [4, 1, 2], [4, 1, 4], [4, 1, 5], [4, 2, 2], [4, 2, 3], [4, 2, 5], [4, 3, 2],
             [4, 3, 5], [4, 4, 2], [4, 5, 2], [5, 1, 5], [5, 2, 4], [5, 2, 5], [5, 3, 2], [5, 3, 3], [5, 4, 2],
             [5, 4, 4], [5, 5, 2], [5, 5, 3], [5, 5, 4], [5, 5, 5]]


def test_full_resolution_surface_is_cleaned_when_needed():
    # without decimation the surface used to skip the cleanup and fail its own check ("2 duplicate
    # faces [after mask_to_surface ...]"), so `lungdeform build` refused segment's own masks
    from skimage.measure import marching_cubes

    a = np.zeros((7, 7, 7), np.uint8)
    a[tuple(np.array(_FIN_BLOB).T)] = 1
    v, f, _, _ = marching_cubes(np.pad(a, 1).astype(np.float32), 0.5, allow_degenerate=False)
    fs = np.sort(f, axis=1)
    assert len(np.unique(fs, axis=0)) < len(fs)  # the premise: raw marching cubes has duplicate faces
    res = extract_surface(Image(a, (10.0, 10.0, 10.0), (0, 0, 0), np.eye(3), "fins.nii.gz"))
    assert any("duplicate (fin) faces removed" in n for n in res.notes)
    check_surface(res.surface.vertices, res.surface.faces)  # closed, manifold, outward: raises otherwise
    # a mask that passes as it is goes through unchanged: no cleanup note
    k, j, i = np.mgrid[:20, :20, :20]
    ball = ((((k - 9.5) / 8) ** 2 + ((j - 9.5) / 6) ** 2 + ((i - 9.5) / 7) ** 2) <= 1).astype(np.uint8)
    res = extract_surface(Image(ball, (10.0, 10.0, 10.0), (0, 0, 0), np.eye(3), "ball.nii.gz"))
    assert not any(n.startswith("cleanup") for n in res.notes)


# --------------------------------------------------------------------------- components and border
def test_two_equal_blobs_refused_naming_file_and_volumes():
    # two 10-voxel cubes of 2 mm (8 mL each) 4 voxels apart: keeping the "largest" would silently
    # drop a whole lung-sized half of the mask (two lungs in one label)
    a = np.zeros((14, 14, 28), np.uint8)
    a[2:12, 2:12, 2:12] = 1
    a[2:12, 2:12, 16:26] = 1
    image = Image(a, (2.0, 2.0, 2.0), (0, 0, 0), np.eye(3), "pair.mha")
    with pytest.raises(MaskError, match=r"pair\.mha: .*kept 8 mL; would drop 8 mL.*two lungs in one label"):
        extract_surface(image, smooth_iterations=0)


def test_small_speck_dropped_with_its_volume_in_a_note():
    # a 2-voxel speck of 8 mm³ each = 0.016 mL next to an 8 mL cube: far under 20 %, dropped and noted
    a = np.zeros((14, 14, 20), np.uint8)
    a[2:12, 2:12, 2:12] = 1
    a[5, 5, 16:18] = 1
    image = Image(a, (2.0, 2.0, 2.0), (0, 0, 0), np.eye(3), "speck.mha")
    result = extract_surface(image, smooth_iterations=0)
    assert result.components_dropped == 1
    assert any("dropped 1 (2 voxels, 0.016 mL in all)" in n for n in result.notes)
    assert result.warnings == ()  # inside the image: no border warning


def test_mask_on_the_border_warns_naming_the_faces():
    # the corner block of test_mask_touching_the_border... touches i-low, j-low and both k faces
    # (it spans all 8 slices); a whole-image mask touches all six and is named as such
    a = np.zeros((8, 14, 20), np.uint8)
    a[:, :10, :12] = 1
    image = Image(a, (2.0, 2.0, 2.0), (0, 0, 0), np.eye(3), "block.mha")
    result = extract_surface(image, smooth_iterations=0)
    assert result.warnings == ("the mask touches the image border on faces i-low, j-low, k-low, k-high; "
                               "the lung may be cropped",)
    assert result.report.warnings == result.warnings
    full = extract_surface(Image(np.ones((8, 14, 20), np.uint8), (2.0, 2.0, 2.0), (0, 0, 0), np.eye(3), "all.mha"))
    assert "faces i-low, i-high, j-low, j-high, k-low, k-high" in full.warnings[0]
    assert "whole image is foreground" in full.warnings[0]
