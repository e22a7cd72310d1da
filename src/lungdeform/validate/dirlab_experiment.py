"""The DIR-Lab experiment behind ``lungdeform validate dirlab``: every usable case under a folder
evaluated (:func:`lungdeform.validate.dirlab.evaluate_case`), the paper's hypotheses summarised
(:func:`lungdeform.validate.dirlab.hypothesis_summary`), and ``metrics.json``.

:func:`run_dirlab` runs it and returns a :class:`DirlabRun`; :meth:`DirlabRun.metrics` is the
content of ``metrics.json`` and :func:`write_metrics` writes it. The models, the protocol and the
frames are described in :mod:`lungdeform.validate.dirlab`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from lungdeform.atomic import write_bytes
from lungdeform.errors import InputError

from .dirlab import (
    PUBLISHED_SOURCE,
    CaseResult,
    Discovery,
    default_models,
    discover,
    evaluate_case,
    hypothesis_summary,
    load_case,
    pooled_choice,
)

#: A case's 300-pair mean farther than this from the published one (mm) gets a note.
PUBLISHED_TOLERANCE_MM = 0.05
#: The frame, phases and protocol, as recorded in ``metrics.json`` (``{folds}``: the landmark folds).
CONVENTIONS = {
    "frame": "mm = (1-based voxel index - 1) * spacing (voxel_spacing.csv), index-aligned, not LPS",
    "phases": "T00 end-inhale, T50 end-exhale; T10-T40 on the exhale branch (no inhale samples)",
    "one_scalar": "x_p = x_T50 + s_p (x_T00 - x_T50), s_p least squares per phase, in-sample",
    "heldout": "leave one of T10-T40 out; drivers fitted on other landmark folds ({folds})",
    "rounding_floor": "mean error of a perfect model given whole-voxel landmark positions",
    "best_model": "diagnostic (also best_model_diagnostic): chosen on the case's own held-out phases, optimistic",
    "default_model": "leave-one-case-out: the model with the lowest mean of the per-case held-out means over "
                     "the OTHER cases of the run; default_model_heldout_mean_mm is its held-out mean on this case "
                     "(null for a run of one case); model_selection.pooled is the choice on all cases",
}


@dataclass(frozen=True, eq=False)
class DirlabRun:
    """One run of the DIR-Lab experiment.

    discovery : what :func:`lungdeform.validate.dirlab_files.discover` found (cases, skipped, notes).
    results : one :class:`~lungdeform.validate.dirlab.CaseResult` per usable case, case order.
    summary : :func:`~lungdeform.validate.dirlab.hypothesis_summary` of ``results``.
    notes : discovery's notes, each case's notes, the skipped cases' reasons, then cases whose
        300-pair mean differs from the published one (one line each).
    folds : landmark folds of the held-out fits; elapsed_s : seconds from discovery to summary.
    """

    discovery: Discovery
    results: tuple[CaseResult, ...]
    summary: dict
    notes: tuple[str, ...]
    folds: int
    elapsed_s: float

    def metrics(self) -> dict:
        """The content of ``metrics.json``: per case its results, its default model (leave-one-case-out,
        :func:`~lungdeform.validate.dirlab.default_models`), spacing and spacing source; the skipped
        cases; the model chosen on all cases; the hypotheses; the notes; the conventions; the data folder; the time (s)."""
        cases = self.discovery.cases
        defaults = default_models(list(self.results))
        return {
            "cases": {
                str(r.case): {**r.to_dict(), "default_model": defaults[r.case][0],
                              "default_model_heldout_mean_mm": defaults[r.case][1],
                              "spacing_mm": cases[r.case].spacing.tolist(),
                              "spacing_source": cases[r.case].spacing_source}
                for r in self.results
            },
            "skipped": {str(c): why for c, why in sorted(self.discovery.skipped.items())},
            "model_selection": {"protocol": CONVENTIONS["default_model"], "pooled": pooled_choice(list(self.results))},
            "hypotheses": self.summary,
            "notes": list(self.notes),
            "conventions": {k: v.format(folds=self.folds) for k, v in CONVENTIONS.items()},
            "source": str(Path(self.discovery.root).resolve()),
            "elapsed_s": self.elapsed_s,
        }


def run_dirlab(data, *, folds: int = 5, published_fallback: bool = True) -> DirlabRun:
    """Find the DIR-Lab cases under ``data`` (:func:`~lungdeform.validate.dirlab_files.discover`,
    ``published_fallback`` as there), evaluate each with ``folds`` landmark folds and summarise.

    Raises :class:`InputError` for ``folds`` < 2 and what discovery and reading raise
    (:class:`~lungdeform.errors.ReadError` naming the file).
    """
    if folds < 2:
        raise InputError(f"folds must be ≥ 2, got {folds}")
    t0 = time.perf_counter()
    found = discover(data, published_fallback=published_fallback)
    results = tuple(evaluate_case(load_case(f), f.dims, folds=folds) for f in found.cases.values())
    summary = hypothesis_summary(list(results))
    elapsed = time.perf_counter() - t0
    return DirlabRun(found, results, summary, tuple(run_notes(found, results)), folds, elapsed)


def run_notes(found: Discovery, results) -> list[str]:
    """What a reader of the results should know, one line each: ``found``'s notes, each case's notes,
    the skipped cases' reasons, and each case of ``results`` whose 300-pair mean differs from the
    published one by more than :data:`PUBLISHED_TOLERANCE_MM` (with what to check)."""
    cases = found.cases
    notes = list(found.notes) + [n for f in cases.values() for n in f.notes] + list(found.skipped.values())
    for r in results:
        if r.mean_displacement_300_mm is not None and r.published_300_mm is not None and \
                abs(r.mean_displacement_300_mm - r.published_300_mm) > PUBLISHED_TOLERANCE_MM:
            src = cases[r.case].spacing_source
            check = "check its landmark files" if src == PUBLISHED_SOURCE else f"check its row in {src}"
            notes.append(f"case {r.case}: 300-pair mean {r.mean_displacement_300_mm:.2f} mm differs from the "
                         f"published {r.published_300_mm:.2f} mm: {check}")
    return notes


def write_metrics(run: DirlabRun, folder) -> Path:
    """Write ``folder/metrics.json`` (:meth:`DirlabRun.metrics`, indent 2) atomically; return its path."""
    path = Path(folder) / "metrics.json"
    return write_bytes(path, (json.dumps(run.metrics(), indent=2) + "\n").encode())
