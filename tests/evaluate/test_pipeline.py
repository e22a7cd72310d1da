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


def test_metrics_json_is_fit_metrics_of_the_run_outcome(tmp_path, monkeypatch):
    # run_fit writes and returns the metrics built once from its typed outcome: the FitRun handed to
    # write_outputs is captured, and fit_metrics of it, through the same strict JSON writer, gives
    # metrics.json byte for byte (every key, value and the order); the builder mutates nothing, so a
    # second call is a fresh, equal dict. Truth for the failure state: 5 evaluations cannot pay for one
    # finite-difference Jacobian of the least-squares search (9), so the fit stops on its budget and
    # metrics.json says success false with that reason as its message.
    import json
    from dataclasses import FrozenInstanceError

    import pytest

    from lungdeform.atomic import write_json, write_text
    from lungdeform.evaluate import pipeline as P
    from lungdeform.evaluate.outcome import FitRun
    from lungdeform.fit.config import FitConfig, FitInputs
    from lungdeform.io.meshfile import write_mesh
    from lungdeform.model.lung import BuildSettings, build_lung
    from tests.cli.test_fit import TRUE
    from tests.conftest import ellipsoid_lung

    lung = ellipsoid_lung("right")
    model = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(200.0, 200.0))
    a = write_mesh(tmp_path / "ee.ply", lung.vertices, lung.faces)
    b = write_mesh(tmp_path / "ei.ply", lung.vertices + model.displacement, lung.faces)
    runs, write_outputs = [], P.write_outputs
    monkeypatch.setattr(P, "write_outputs",
                        lambda out, run, metrics: (runs.append(run), write_outputs(out, run, metrics)))
    # the report (matplotlib, seconds) is tested in tests/cli/test_fit.py; metrics.json is written before it
    monkeypatch.setattr(P, "write_report", lambda path, **_: write_text(path, "<html></html>"))
    out = tmp_path / "out"
    returned = P.run_fit(FitInputs([a, b], "right"), out, FitConfig(max_evaluations=5, baselines=False))

    (run,) = runs
    assert isinstance(run, FitRun)
    with pytest.raises(FrozenInstanceError):
        run.fits = None
    built = P.fit_metrics(run)
    assert built is not returned and built == P.fit_metrics(run)
    write_json(tmp_path / "built.json", built, strict=True, default=P._json)
    assert (tmp_path / "built.json").read_text() == (out / "metrics.json").read_text()
    written = json.loads((out / "metrics.json").read_text())
    assert list(returned) == list(written)
    headline = list(written["targets"][run.placed.targets[-1].name])  # every method, at the top level too
    assert list(written) == ["inputs", "side", "volumes_ml", "volumes_given_ml", "warnings", "notes",
                             "model_mesh_vertices", "alignment", "targets", *headline, "protocols", "headline_fit",
                             "interior_correction", "fit", "bounding_box", "alignment_choice", "interior",
                             "seconds", "baseline_seconds", "baseline_cpu_seconds", "model_seconds"]
    assert list(written["fit"]) == list(run.fits.named()) == ["optimizer"]  # no grid, no landmark fit asked
    fit = written["fit"]["optimizer"]
    assert fit["success"] is False and fit["message"] == run.fits.optimizer.failure
    assert "evaluation budget" in fit["message"]
    assert written["alignment_choice"] == {"asked": "auto", "used": run.config.align, "why": run.alignment.why}
    assert written["model_seconds"] == written["seconds"] - written["baseline_seconds"]
