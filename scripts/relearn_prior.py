#!/usr/bin/env python
"""Relearn only the interior prior of the shipped population default (its c1…c9 kept), as
``lungdeform learn-default`` learns it (:func:`lungdeform.cohort.default.pooled_prior`), over the same
training lungs; writes a copy of src/lungdeform/model/population_default.json with the new prior.

    python scripts/relearn_prior.py OUT.json FITS_DIR DATA_DIR...

FITS_DIR keeps each lung's two-scan fit (``validate.single_scan.cached_fit``; the ``fits`` folder of a
``validate single-scan --out`` run is reused). Used when only how the prior is learned changed (0.10:
the prior tapered to zero at the surface, docs/DEFAULTS.md): re-fitting every lung moves c1…c9 by fit
noise, which is not the change.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

from lungdeform.cohort.default import pooled_prior
from lungdeform.model.population import shipped_default
from lungdeform.segment.split import SplitCache
from lungdeform.validate import single_scan as S

SHIPPED = Path(__file__).resolve().parents[1] / "src" / "lungdeform" / "model" / "population_default.json"


def main(out: str, fits: str, *folders: str) -> None:
    samples = []
    for folder in folders:
        for subject in S.find_subjects(Path(folder)):
            splits = SplitCache()
            for side in subject.sides:
                pair = S.read_pair(subject, side, splits=splits)
                samples.append(S.sample_of(pair, S.cached_fit(pair, subject, Path(fits))))
    shipped = shipped_default()
    lungs = [f"{x.subject}/{x.side}" for x in samples]
    if lungs != shipped.provenance["lungs"]:
        raise SystemExit(f"these folders hold {lungs}, the shipped default was learned from {shipped.provenance['lungs']}")
    prior = pooled_prior(samples, replace(shipped, interior_prior=None))
    data = json.loads(SHIPPED.read_text())
    data["interior_prior"] = prior.tolist()
    Path(out).write_text(json.dumps(data, indent=2) + "\n")


if __name__ == "__main__":
    if len(sys.argv) < 4:
        raise SystemExit(__doc__)
    main(*sys.argv[1:])
