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
        "lungdeform.fit.config, lungdeform.fit.inputs, lungdeform.fit.placement, lungdeform.fit.heldout, "
        "lungdeform.fit.scoring, "
        "lungdeform.fit.fitting, lungdeform.geometry.frame, lungdeform.atomic, lungdeform.io.landmarks, lungdeform.model.lung, "
        "lungdeform.io.modelfile, lungdeform.fit.report, lungdeform.io.meshfile, lungdeform.io.mask, lungdeform.fit.segment, "
        "lungdeform.geometry.mesh\n"
        "bad = sorted(m for m in sys.modules if m == 'typer' or m.startswith('lungdeform.cli'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"CLI modules imported by library code: {out.stdout.strip()}"
