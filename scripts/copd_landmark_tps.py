"""The landmarks' own thin-plate spline (``landmarks_tps`` of ``lungdeform validate copd``) on every
COPDgene lung, without the model's fit: its held-out mean landmark error per lung and the median.

Why (issue 39): since 0.8 the spline's smoothing is chosen inside each fold's training landmarks
(:func:`lungdeform.evaluate.baselines.landmark_tps_cv`), as the model's landmark correction's is,
and the full ``validate copd`` run takes hours on a loaded machine. This runs the same function on
the same landmarks and the same folds (:func:`lungdeform.evaluate.folds.landmark_folds`, 5 folds,
seed 0), in minutes. The spline has a free affine part, so it is unchanged by a rigid motion of the
inspiration landmarks: the alignment of the fit (apex, then the translation fitted with the model)
does not enter, and the figures are ``validate copd``'s ``landmarks_tps`` row (checked on all ten lungs:
equal to the printed precision).

Usage (from the repository root)::

    LUNGDEFORM_DATA=/work/shared/data .venv/bin/python scripts/copd_landmark_tps.py \\
        --data $LUNGDEFORM_DATA/dirlab-copd-lung-masks [--cases 1,2,3,4,5]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lungdeform.evaluate.baselines import landmark_tps_cv
from lungdeform.evaluate.folds import landmark_folds
from lungdeform.evaluate.inputs import read_inputs
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.segment.split import SIDES, SplitCache
from lungdeform.validate.copd import find_cases


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--cases", default=None, help="comma-separated case numbers (default: all)")
    args = ap.parse_args(argv)
    cases = None if args.cases is None else [int(c) for c in args.cases.split(",")]
    errors = []
    for name, (exp, insp, exp_lm, insp_lm) in find_cases(args.data, cases).items():
        splits = SplitCache()
        for side in SIDES:
            read = read_inputs(FitInputs([exp, insp], side, landmarks=[exp_lm, insp_lm], splits=splits))
            a, b = read.landmarks
            _, held = landmark_tps_cv(read.surfaces[0], a, b, landmark_folds(len(a), FitConfig().folds))
            errors.append(float(np.linalg.norm(held - b, axis=1).mean()))
            print(f"{name} {side}: {len(a)} landmarks, landmarks_tps {errors[-1]:.2f} mm", flush=True)
    print(f"median over {len(errors)} lungs: {np.median(errors):.2f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
