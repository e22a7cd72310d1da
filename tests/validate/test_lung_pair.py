"""One lung at two volumes (lungdeform.validate.lung_pair): a cut left out of the surface distance on both sides,
the pair cache, and a generic folder read without landmarks."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.fit.align import CropPlane
from lungdeform.fit.objective import Target
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.io.grid import Image
from lungdeform.validate.lung_pair import LungPair, cached_pair, exclude_cuts, lung_sides, read_pair
from lungdeform.validate.single_scan import isotropic, score
from lungdeform.validate.subjects import find_subjects
from tests.segment.test_split import two_lungs
from tests.validate.test_copd import write_image

#: the inspiration phantom's frame lies this far from the expiration one's (mm), as the Learn2Reg crops do
SHIFT = np.array([0.0, 0.0, 12.0])


def test_exclude_cuts_on_a_sphere_with_a_known_shift():
    # truth: the smaller scan is a sphere whose scan was cut at y = -30 (its face y <= -30 is the crop:
    # normal -y, offset 30); the larger is the same sphere scaled about its centre by 1.1 and moved by a
    # known shift. The isotropic prediction then fits the target exactly at the shift, so the cut plane is
    # carried into the target's frame by exactly that shift (along z: its y unchanged): measured are the
    # rest vertices above y = -25 (5 mm margin) and the target vertices above y = -25, and the isotropic
    # row scores ~0 there
    s = icosphere(4, 1.0)
    rest = Surface(s.vertices * 50.0, s.faces, "rest")
    big = Surface(s.vertices * 55.0 + SHIFT, s.faces, "big")
    pair = LungPair("s", "right", rest, np.ones(rest.n_vertices, bool), Target(big, big.volume_ml), big.volume_ml,
                    cut=("exp j-low",))
    plane = CropPlane(np.array([0.0, -1.0, 0.0]), 30.0, 100, "j-low")
    got = exclude_cuts(pair, [plane], [])
    assert np.array_equal(got.keep, rest.vertices[:, 1] > -25.0)
    assert np.array_equal(got.target.keep, big.vertices[:, 1] > -25.0)
    row = score(got, *isotropic(got))
    assert row["surface_mean_mm"] < 0.05 and np.allclose(row["translation_mm"], SHIFT, atol=0.05)
    assert row["landmark_mean_mm"] is None and "landmark_motion_mm" not in row
    # the larger scan's own crop (its top, z >= 40 in its frame) is left out of the prediction where the
    # prediction reaches it once moved: rest vertices whose isotropic image + shift lies above z = 35
    top = CropPlane(np.array([0.0, 0.0, 1.0]), 40.0, 100, "k-high")
    got = exclude_cuts(pair, [], [top])
    assert np.array_equal(got.keep, rest.vertices[:, 2] * 1.1 + SHIFT[2] < 35.0)
    assert np.array_equal(got.target.keep, big.vertices[:, 2] < 35.0)


def _cut_folder(folder):
    """Subject ``cut`` as .mha masks without landmarks: two ellipsoids, the expiration scan's field of view
    cut at its anterior rows (j < 10: a crop face at the front of both lungs), the inspiration scan whole,
    scaled, its frame moved by SHIFT."""
    exp, _, _ = two_lungs(bridge=False, source="cut_exp_mask.mha")
    a = np.asarray(exp.array)[:, 10:, :]
    exp = Image(a, exp.spacing, exp.origin + [0.0, 10 * exp.spacing[1], 0.0], exp.direction, exp.source)
    insp, _, _ = two_lungs(bridge=False, source="cut_insp_mask.mha", scale=(1.06, 1.06, 1.12))
    insp = Image(insp.array, insp.spacing, insp.origin + SHIFT, insp.direction, insp.source)
    write_image(exp, folder / "cut_exp_mask.mha")
    write_image(insp, folder / "cut_insp_mask.mha")
    return exp


@pytest.mark.slow
def test_a_cut_lung_without_landmarks_from_a_generic_folder(tmp_path):
    # truth: both lungs of a both-lung mask, the left at +x; the expiration mask touches its front border,
    # so each lung is cut there ("exp j-low") and its front (y below the crop face + 5 mm) is not measured,
    # nor the target's front beyond the crop face carried into its frame; no landmarks: None; the cache
    # gives the same pair back without reading the masks
    exp = _cut_folder(tmp_path)
    (subject,) = find_subjects(tmp_path)
    assert subject.landmarks is None and lung_sides(subject) == ("left", "right")
    front = float(exp.origin[1] - exp.spacing[1] / 2)  # the crop face (world y)
    for side in ("left", "right"):
        pair = read_pair(subject, side)
        assert pair.cut == ("exp j-low",) and pair.landmarks_rest is None
        assert (pair.rest.vertices[:, 0].mean() > 0) == (side == "left")
        y = pair.rest.vertices[:, 1]
        assert not pair.keep[y < front + 4.9].any() and pair.keep[y > front + 6.0].all()
        ty = pair.target.surface.vertices[:, 1]
        assert not pair.target.keep[ty < front].any() and pair.target.keep[ty > front + 8.0].all()
    cached = cached_pair(subject, "left", tmp_path / "cache")
    again = cached_pair(subject, "left", tmp_path / "cache")
    assert len(list((tmp_path / "cache" / "pairs").iterdir())) == 1
    for a, b in ((cached.rest.vertices, again.rest.vertices), (cached.keep, again.keep),
                 (cached.target.keep, again.target.keep)):
        assert np.array_equal(a, b)
    assert again.cut == cached.cut and again.landmarks_rest is None and again.volume_ml == cached.volume_ml
