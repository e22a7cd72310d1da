"""The lung surfaces shipped in lungdeform.data: they load, are valid lungs, and match their sources."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.data import default_lungs, itk_right_lung
from lungdeform.geometry.intersect import self_intersections
from lungdeform.geometry.mesh import check_surface
from lungdeform.io.image import read_image
from lungdeform.io.mask import LOBE_LABELS, extract_surface

from .conftest import require_path


def test_default_lungs_are_valid_lungs():
    lungs = default_lungs()
    assert set(lungs) == {"left", "right"}
    for side, surf in lungs.items():
        _, _, report = check_surface(surf.vertices, surf.faces, source=side)  # closed, manifold, outward, mm
        assert report.repairs == ()
        # marching-cubes lungs have many coplanar neighbours and small folds within a vertex fan:
        # none of them is a crossing of non-adjacent faces
        assert self_intersections(surf.vertices, surf.faces)[0] == 0
        assert 2000 <= surf.n_vertices <= 4000
        assert 1000 < surf.volume_ml < 3000  # an adult lung at one breathing state
        # the paper's lung / bounding-box volume ratio is 0.32–0.40; a lung-like shape, not a blob
        lo, hi = surf.bounds
        assert 0.28 < surf.volume / np.prod(hi - lo) < 0.45
    # LPS: +x is the patient's left, so the left lung lies at larger x than the right one
    assert lungs["left"].vertices[:, 0].mean() > lungs["right"].vertices[:, 0].mean() + 50
    assert lungs["left"].volume < lungs["right"].volume  # the heart takes room on the left


def test_itk_right_lung_is_valid():
    surf = itk_right_lung()
    check_surface(surf.vertices, surf.faces, source="itk_right_lung")
    assert self_intersections(surf.vertices, surf.faces)[0] == 0
    assert 2000 <= surf.n_vertices <= 4000
    assert 2500 < surf.volume_ml < 4000


def test_loaded_once():
    assert default_lungs()["left"] is default_lungs()["left"]  # cached; Surface is immutable
    assert not default_lungs()["left"].vertices.flags.writeable


@pytest.mark.realdata
@pytest.mark.slow
def test_shipped_lungs_match_full_resolution_surfaces(data_dir):
    # the decimated assets keep the volume of the full-resolution marching-cubes surfaces
    image = read_image(require_path(data_dir, "coronacases-lung-lobes", "Coronacases_001_lobes.nii.gz"))
    for side, surf in default_lungs().items():
        full = extract_surface(image, LOBE_LABELS[side]).surface
        assert self_intersections(full.vertices, full.faces)[0] == 0  # 400k faces, no false positive
        assert surf.volume == pytest.approx(full.volume, rel=0.05), side
        np.testing.assert_allclose(surf.vertices.mean(axis=0), full.vertices.mean(axis=0), atol=3.0)
    itk = read_image(require_path(data_dir, "itk-right-lung-two-volumes", "CT_3D_lung_fixed_mask.mha"))
    full = extract_surface(itk).surface
    assert itk_right_lung().volume == pytest.approx(full.volume, rel=0.05)
