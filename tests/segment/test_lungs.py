"""CT → left/right lung masks (lungdeform.segment.lungs), on an analytic phantom and on the POPI CT."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError, MaskError
from lungdeform.io.grid import Image
from lungdeform.segment import ct as C
from lungdeform.segment import lungs as S
from tests.conftest import require_path

SPACING = np.array([2.0, 2.0, 3.0])  # mm, x y z


def _segment_distance(p, a, b):
    """Distance (mm) from points ``p : (..., 3)`` to the segment a–b."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def phantom(rng, gap_mm=-4.0, flip_x=False):
    """A chest phantom on a (z, y, x) = (50, 96, 112) grid, LPS, head up.

    Body: elliptic cylinder of soft tissue (40 HU) in air (−1000 HU). Lungs: two ellipsoids of
    −850 HU, semi-axes 40 × 30 × 60 mm, centres at x = ±(40 + gap/2) mm; ``gap_mm < 0`` makes them
    overlap, i.e. touch along a thin junction. Each lung holds a 6 mm "vessel" (40 HU) that must be
    filled back. Trachea: a 7 mm radius air tube (−1000 HU) from the top slice to a carina, then two
    main bronchi into the lungs. Noise σ = 10 HU. Returns ``(image, truth)`` with the analytic lung
    masks (vessels included, airways excluded).
    """
    nz, ny, nx = 50, 96, 112
    origin = np.array([-(nx - 1) / 2 * SPACING[0], -(ny - 1) / 2 * SPACING[1], -(nz - 1) / 2 * SPACING[2]])
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    p = np.stack([i * SPACING[0], j * SPACING[1], k * SPACING[2]], -1) + origin  # world mm (identity direction)
    ct = np.full((nz, ny, nx), -1000.0)
    ct[(p[..., 0] / 105) ** 2 + (p[..., 1] / 85) ** 2 <= 1] = 40.0
    cx = 40.0 + gap_mm / 2
    truth = {}
    for side, sgn in (("left", 1.0), ("right", -1.0)):  # LPS: +x = patient left
        c = np.array([sgn * cx, 0.0, -8.0])
        lung = ((p - c) / [40.0, 30.0, 60.0]) ** 2
        lung = lung.sum(-1) <= 1
        truth[side] = lung
    both = truth["left"] | truth["right"]
    ct[both] = -850.0
    for sgn in (1.0, -1.0):
        ct[np.linalg.norm(p - [sgn * 45.0, 5.0, -15.0], axis=-1) <= 6.0] = 40.0
    top = np.array([0.0, -5.0, p[..., 2].max() + 5])
    carina = np.array([0.0, -5.0, 20.0])
    airway = _segment_distance(p, top, carina) <= 7.0
    for sgn in (1.0, -1.0):
        airway |= _segment_distance(p, carina, np.array([sgn * 30.0, -5.0, 5.0])) <= 5.0
    ct[airway] = -1000.0
    truth = {s: m & ~airway for s, m in truth.items()}
    ct += rng.normal(0, 10, ct.shape)
    direction = np.eye(3)
    if flip_x:  # same patient, x index running toward patient right
        ct, truth = ct[:, :, ::-1], {s: m[:, :, ::-1] for s, m in truth.items()}
        origin = origin.copy()
        origin[0] = -origin[0]
        direction = np.diag([-1.0, 1.0, 1.0])
    img = Image(ct.astype(np.int16), SPACING, origin, direction, source="phantom")
    return img, truth


def ndi_dilate(m):
    from scipy import ndimage

    return ndimage.binary_dilation(m, iterations=2)


def _dice(a, b):
    return 2 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


def test_phantom_separate_lungs(rng):
    img, truth = phantom(rng, gap_mm=10.0)
    seg = S.segment_lungs(img)
    # truth: analytic masks; vessels are filled back, the airway tree is out
    assert _dice(seg.left, truth["left"]) > 0.97
    assert _dice(seg.right, truth["right"]) > 0.97
    assert seg.details["split"]["method"] == "two components after airway removal"
    vml = np.prod(SPACING) / 1000
    assert seg.volumes_ml["left"] == pytest.approx(truth["left"].sum() * vml, rel=0.03)
    # the trachea seed is in the top slice and the tree holds the tube (≈ π·7²·(length) mm³)
    assert seg.details["trachea_seed"]["slice"] == img.array.shape[0] - 1
    # trachea and main bronchi (outside the lung ellipsoids) are in neither lung; the bronchi's ends
    # inside the lungs are filled back as lung, like intrapulmonary airways
    lungs = seg.left | seg.right
    outside = seg.airway & ~(truth["left"] | truth["right"])
    outside &= ~ndi_dilate(truth["left"] | truth["right"])
    assert outside.sum() > 100 and not (outside & lungs).any()
    assert 5 < seg.volumes_ml["airway"] < 40
    assert "Trachea seed" in seg.airway_removal


def test_phantom_touching_lungs_are_split(rng):
    img, truth = phantom(rng, gap_mm=-6.0)
    # the lungs overlap by 6 mm: after airway removal they are one component
    seg = S.segment_lungs(img)
    assert seg.details["split"]["method"] == "in-plane erosion"
    assert _dice(seg.left, truth["left"]) > 0.95
    assert _dice(seg.right, truth["right"]) > 0.95
    assert not (seg.left & seg.right).any()
    # the junction goes to the lung it belongs to: almost no left voxel right of the midline
    x = img.index_to_world(np.argwhere(seg.left)[:, ::-1])[:, 0]
    assert np.mean(x < -4.0) < 0.01


def test_minimal_cost_cut_when_erosion_is_not_allowed(rng):
    img, truth = phantom(rng, gap_mm=-6.0)
    seg = S.segment_lungs(img, max_erosions=0)
    assert seg.details["split"]["method"].startswith("minimal-cost cut")
    assert _dice(seg.left, truth["left"]) > 0.93 and _dice(seg.right, truth["right"]) > 0.93


def test_side_comes_from_world_x_not_index(rng):
    # the same phantom stored with the x index reversed: the left lung stays the +x (LPS) one
    img, truth = phantom(rng, gap_mm=10.0, flip_x=True)
    seg = S.segment_lungs(img)
    assert _dice(seg.left, truth["left"]) > 0.97
    assert seg.details["centroid_world_x_mm"][0] > 0


def test_errors_are_clear(rng):
    img, _ = phantom(rng)
    solid = Image(np.full(img.array.shape, 40, np.int16), SPACING, img.origin, img.direction, source="solid.nii.gz")
    with pytest.raises(InputError, match="solid.nii.gz.*air"):
        S.segment_lungs(solid)  # no value below −500: not a CT in HU
    arr = np.full(img.array.shape, 40, np.int16)
    arr[:, :5] = -1000  # air only outside the body, touching the border
    arr[20:22, 40:42, 50:52] = -1000  # a bubble far below lung size
    with pytest.raises(MaskError, match="nolungs.mha.*empty mask"):
        S.segment_lungs(Image(arr, SPACING, img.origin, img.direction, source="nolungs.mha"))


def test_oblique_is_refused(rng):
    # slices tilted 45° from axial (and so from coronal): neither reading holds, resampling needed;
    # a 20° gantry tilt is read as axial
    img, _ = phantom(rng)
    c, s_ = np.cos(np.radians(20)), np.sin(np.radians(20))
    d = np.array([[1.0, 0, 0], [0, c, -s_], [0, s_, c]])
    assert C.axial_axes(Image(img.array, SPACING, img.origin, d)) == (0, 1, 2)
    c, s_ = np.cos(np.radians(45)), np.sin(np.radians(45))
    d = np.array([[1.0, 0, 0], [0, c, -s_], [0, s_, c]])
    with pytest.raises(InputError, match="oblique.mha: slices are not axial"):
        S.segment_lungs(Image(img.array, SPACING, img.origin, d, source="oblique.mha"))


@pytest.mark.parametrize("perm", [(0, 2, 1), (1, 0, 2), (2, 1, 0), (1, 2, 0)])
def test_axis_order_of_the_file_does_not_change_the_masks(rng, perm):
    # truth: the same voxels stored in another array axis order (a coronal or sagittal stack, or
    # swapped in-plane axes, as some NIfTI writers do) are the same CT; the masks must be the same
    # voxels, given on the file's own grid. Before, a coronal stack was refused and swapped in-plane
    # axes silently skipped the airway removal on the POPI CT (0.1 mL of 39 mL found).
    img, _ = phantom(rng, gap_mm=10.0)
    ref = S.segment_lungs(img)
    index_axes = [2 - a for a in perm[::-1]]  # index axes (i, j, k) of the stored image, in axial terms
    stored = Image(np.transpose(img.array, perm), SPACING[index_axes], img.origin,
                   img.direction[:, index_axes], source="stored.nii.gz")
    # the same world point for the same voxel value: a pure reordering
    k = (3, 40, 50)
    k_stored = tuple(k[a] for a in perm)
    assert stored.array[k_stored] == img.array[k]
    np.testing.assert_allclose(stored.index_to_world(np.array([k_stored[::-1]])),
                               img.index_to_world(np.array([k[::-1]])))
    assert C.axial_axes(stored) == tuple(int(a) for a in np.argsort(perm))
    seg = S.segment_lungs(stored)
    back = tuple(int(a) for a in np.argsort(perm))
    for name in ("left", "right", "airway"):
        assert getattr(seg, name).shape == stored.array.shape
        assert np.array_equal(np.transpose(getattr(seg, name), back), getattr(ref, name)), name
    assert seg.volumes_ml == pytest.approx(ref.volumes_ml)
    assert seg.mask_image("left").array.shape == stored.array.shape


def test_overlay_png(tmp_path, rng):
    img, _ = phantom(rng, gap_mm=10.0)
    seg = S.segment_lungs(img)
    path = S.overlay_png(seg, tmp_path / "overlay.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.realdata
def test_popi_phase00(data_dir, tmp_path):
    ct = require_path(data_dir, "popi-ct-phase00", "popi_phase00_dicom_141slices.tar.gz")
    img = C.read_ct(ct, workdir=tmp_path)
    assert img.array.shape == (141, 512, 512)
    seg = S.segment_lungs(C.downsample(img, (1, 2, 2)))  # half resolution in-plane: ~4× faster
    v = seg.volumes_ml
    # README: a plain threshold gives ≈ 5.3 L of lungs plus airways
    assert v["candidate"] == pytest.approx(5300, rel=0.03)
    # left + right + removed airways account for the candidate (plus filled vessels, minus stray bits)
    assert v["left"] + v["right"] + v["removed"] == pytest.approx(v["candidate"], rel=0.02)
    assert 1800 < v["left"] < 3500 and 1800 < v["right"] < 3500
    assert v["right"] > v["left"]  # the right lung is usually larger (three lobes)
    assert 15 < v["airway"] < 150  # trachea + main bronchi, not a leak into parenchyma
    seed = seg.details["trachea_seed"]
    assert seed["slice"] >= 120 and seed["offset_mm"] < 20
    assert seg.details["centroid_world_x_mm"][0] > 0 > seg.details["centroid_world_x_mm"][1]
    S.overlay_png(seg, tmp_path / "popi_overlay.png")
