"""lungdeform.pipeline: the fit pipeline is library code (its behaviour is tested through
``lungdeform fit`` in tests/cli/test_fit.py and the cohort runner in tests/test_cohort.py)."""

import subprocess
import sys


def test_pipeline_and_cohort_import_nothing_from_the_cli():
    # Dask workers run cohort.fit_job → pipeline.run_fit: neither may pull in the CLI (typer).
    # A fresh interpreter, so that modules other tests imported do not hide an import; every
    # module run_fit imports where used is imported too.
    code = (
        "import sys\n"
        "import lungdeform.pipeline, lungdeform.cohort\n"
        "lungdeform.cohort.FitOptions()\n"
        "import lungdeform.baselines, lungdeform.align, lungdeform.crossval, lungdeform.distance, "
        "lungdeform.fit, lungdeform.frame, lungdeform.atomic, lungdeform.landmarks, lungdeform.model, "
        "lungdeform.modelfile, lungdeform.report, lungdeform.io, lungdeform.mask, lungdeform.segment, "
        "lungdeform.mesh\n"
        "bad = sorted(m for m in sys.modules if m == 'typer' or m.startswith('lungdeform.cli'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"CLI modules imported by library code: {out.stdout.strip()}"
