"""Many subjects: manifests, one job per lung, the Dask runner, population statistics, synthetic cohorts.

Owns: :mod:`~lungdeform.cohort.manifest`, :mod:`~lungdeform.cohort.job` (one lung's fit and its result
record, the resume digest), :mod:`~lungdeform.cohort.runner` (the Dask runner),
:mod:`~lungdeform.cohort.population` (statistics of c1…c9 against Table I),
:mod:`~lungdeform.cohort.synthetic` (cohorts made by the model with known truth),
:mod:`~lungdeform.cohort.recovery` (how well fits recover that truth) and
:mod:`~lungdeform.cohort.default` (a population default learned from fitted lungs, docs/DEFAULTS.md).

May import: :mod:`lungdeform.fit`, :mod:`lungdeform.playback` and everything below them. Dask is optional
(``pip install 'lungdeform[cohort]'``) and imported only where a cohort is run.
"""

from .runner import SUMMARY_SCHEMA, Cluster, CohortResult, clean_stale, run_cohort

__all__ = [
    "Cluster",
    "CohortResult",
    "SUMMARY_SCHEMA",
    "clean_stale",
    "run_cohort",
]
