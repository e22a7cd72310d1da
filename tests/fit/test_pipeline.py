"""lungdeform.fit.pipeline: the fit pipeline is library code (its behaviour is tested through
``lungdeform fit`` in tests/cli/test_fit.py and the cohort runner in tests/cohort/test_runner.py)."""

import subprocess
import sys


def test_pipeline_and_cohort_import_nothing_from_the_cli():
    # Dask workers run job.fit_job → pipeline.run_fit: neither may pull in the CLI (typer).
    # A fresh interpreter, so that modules other tests imported do not hide an import; every
    # module run_fit imports where used is imported too.
    code = (
        "import sys\n"
        "import lungdeform.fit.pipeline, lungdeform.cohort.runner, lungdeform.cohort.job\n"
        "lungdeform.cohort.job.FitOptions()\n"
        "import lungdeform.fit.baselines, lungdeform.fit.align, lungdeform.fit.crossval, lungdeform.geometry.distance, "
        "lungdeform.fit.fitting, lungdeform.geometry.frame, lungdeform.atomic, lungdeform.io.landmarks, lungdeform.model.lung, "
        "lungdeform.io.modelfile, lungdeform.fit.report, lungdeform.io.meshfile, lungdeform.io.mask, lungdeform.fit.segment, "
        "lungdeform.geometry.mesh\n"
        "bad = sorted(m for m in sys.modules if m == 'typer' or m.startswith('lungdeform.cli'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"CLI modules imported by library code: {out.stdout.strip()}"


def test_landmarks_outside_their_own_mask_are_reported(tmp_path):
    # a 20 mm cube of lung in a 1 mm grid: landmarks inside give no warning; a set shifted by 15 mm
    # (another frame, or the other scan's file) has most of its points outside and is reported
    import numpy as np

    from lungdeform.fit.pipeline import landmark_mask_warnings
    from lungdeform.io.image import Image
    from lungdeform.io.mask import extract_surface

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

    from lungdeform.fit.pipeline import landmark_mask_warnings
    from lungdeform.io.image import read_image
    from lungdeform.io.landmarks import read_elastix_points
    from tests.conftest import require_path

    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    from lungdeform.io.mask import extract_surface

    fixed, moving = (read_image(folder / f"CT_3D_lung_{k}_mask.mha") for k in ("fixed", "moving"))
    sf, sm = (extract_surface(img).surface for img in (fixed, moving))
    lf, lm = (read_elastix_points(folder / f"CT_3D_lung_{k}_point_set_corrected.txt") for k in ("fixed", "moving"))
    assert landmark_mask_warnings(lf, fixed, sf, "f") == [] and landmark_mask_warnings(lm, moving, sm, "m") == []
    assert landmark_mask_warnings(lm, fixed, sf, "m") and landmark_mask_warnings(lf, moving, sm, "f")
