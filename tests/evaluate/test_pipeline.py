"""lungdeform.evaluate.pipeline: the fit pipeline is library code (its behaviour is tested through
``lungdeform fit`` in tests/cli/test_fit.py and the cohort runner in tests/cohort/test_runner.py)."""

import subprocess
import sys


def test_pipeline_and_cohort_import_nothing_from_the_cli():
    # Dask workers run job.fit_job → pipeline.run_fit: neither may pull in the CLI (typer).
    # A fresh interpreter, so that modules other tests imported do not hide an import; every
    # module run_fit imports where used is imported too.
    code = (
        "import sys\n"
        "import lungdeform.evaluate.pipeline, lungdeform.cohort.runner, lungdeform.cohort.job\n"
        "lungdeform.cohort.job.FitOptions()\n"
        "import lungdeform.evaluate.baselines, lungdeform.fit.align, lungdeform.evaluate.crossval, lungdeform.geometry.distance, "
        "lungdeform.fit.config, lungdeform.evaluate.inputs, lungdeform.evaluate.placement, lungdeform.evaluate.heldout, "
        "lungdeform.evaluate.scoring, "
        "lungdeform.fit.fitting, lungdeform.geometry.frame, lungdeform.atomic, lungdeform.io.landmarks, lungdeform.model.lung, "
        "lungdeform.io.modelfile, lungdeform.evaluate.report, lungdeform.io.meshfile, lungdeform.io.mask, lungdeform.segment.lungs, "
        "lungdeform.geometry.mesh\n"
        "bad = sorted(m for m in sys.modules if m == 'typer' or m.startswith('lungdeform.cli'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"CLI modules imported by library code: {out.stdout.strip()}"


def test_auto_interior_is_sliding_only_for_cropped_scans():
    # "auto": the correspondence map is between two solids, which a field of view cutting the lung at
    # different tissue breaks; up to CROP_LIMIT of crop-face vertices (DIR-Lab COPDgene: ≤ 0.6 %) the
    # correspondence stays, beyond it (the ITK pair: 6 % and 5 %) the sliding field
    from types import SimpleNamespace

    import numpy as np

    from lungdeform.evaluate.pipeline import interior_kind
    from lungdeform.fit.config import CROP_LIMIT, FitConfig

    def placed(rest_cropped, target_cropped):
        keep = lambda f: np.arange(1000) >= int(round(1000 * f))  # noqa: E731
        return SimpleNamespace(keep=keep(rest_cropped), targets=[SimpleNamespace(keep=keep(target_cropped))])

    auto = FitConfig()
    assert auto.interior == "auto"
    assert interior_kind(placed(0.0, 0.006), auto) == "correspondence"
    assert interior_kind(placed(0.0, CROP_LIMIT + 0.01), auto) == "sliding"
    assert interior_kind(placed(0.064, 0.048), auto) == "sliding"
    assert interior_kind(placed(0.064, 0.048), FitConfig(interior="correspondence")) == "correspondence"
    assert interior_kind(placed(0.0, 0.0), FitConfig(interior="sliding")) == "sliding"


def test_prior_refused_with_a_sliding_interior_asked_or_resolved():
    # truth: a motion prior adds to the correspondence field, so it cannot go with the sliding one,
    # whether asked for (refused before reading: kind None) or resolved from "auto" on cropped scans
    import pytest

    from lungdeform.errors import InputError
    from lungdeform.evaluate.pipeline import check_prior
    from lungdeform.fit.config import FitConfig

    prior = object()
    with pytest.raises(InputError, match="not 'sliding'"):
        check_prior(FitConfig(interior="sliding"), prior)
    check_prior(FitConfig(), prior)  # "auto": not known before the scans are read
    with pytest.raises(InputError, match="these scans are cropped"):
        check_prior(FitConfig(), prior, "sliding")
    check_prior(FitConfig(), prior, "correspondence")
    check_prior(FitConfig(interior="sliding"), None, "sliding")  # no prior: nothing to refuse


def test_fit_outcome_scale_at_is_the_volume_in_units():
    # truth: s = (V - V_EE) / unit_ml, and positions_at moves by s times the displacement
    from types import SimpleNamespace

    import numpy as np

    from lungdeform.fit.fitting import FitOutcome

    fit = SimpleNamespace(volume_ee_ml=2000.0, unit_ml=400.0, displacement=np.ones((2, 3)))
    assert FitOutcome.scale_at(fit, 2600.0) == 1.5 and FitOutcome.scale_at(fit, 2000.0) == 0.0
    fit.scale_at = lambda v: FitOutcome.scale_at(fit, v)
    surface = SimpleNamespace(vertices=np.zeros((2, 3)))
    np.testing.assert_array_equal(FitOutcome.positions_at(fit, surface, 2200.0), np.full((2, 3), 0.5))
