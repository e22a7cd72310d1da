"""A fit run and its measurement: inputs to a saved model, compared methods, held-out landmarks, reports.

Owns: :mod:`~lungdeform.evaluate.pipeline` (inputs to a saved model and its metrics: read, place,
fit, measure, write), :mod:`~lungdeform.evaluate.outcome` (what a run gave, typed: the fits, the
scores, the run; the metrics are built once from it), :mod:`~lungdeform.evaluate.inputs` (reading and checking the inputs: meshes,
masks, CTs through :mod:`lungdeform.segment`, 4-D CT phases, landmarks),
:mod:`~lungdeform.evaluate.placement` (the model mesh and the targets in its frame),
:mod:`~lungdeform.evaluate.baselines` (the comparison methods, calibrated mask-only maps, and the one
set of metrics every method is measured with), :mod:`~lungdeform.evaluate.scoring` (every method
measured on the targets, crop faces left out), :mod:`~lungdeform.evaluate.heldout` (what landmarks
give, held out), :mod:`~lungdeform.evaluate.workers` (worker processes fitting a subject's lungs at once),
:mod:`~lungdeform.evaluate.crossval` (the k-fold protocol of the landmark-informed
fit), :mod:`~lungdeform.evaluate.folds` (seeded landmark folds; the held-out choice of the landmark
correction's smoothing) and :mod:`~lungdeform.evaluate.report` (the HTML report).

May import: :mod:`lungdeform.fit`, :mod:`lungdeform.segment`, :mod:`lungdeform.data`, :mod:`lungdeform.io`,
:mod:`lungdeform.model`, :mod:`lungdeform.interior`, :mod:`lungdeform.geometry`, :mod:`lungdeform.plot`
and the core modules; not :mod:`lungdeform.playback`, :mod:`lungdeform.cohort` or anything above.
"""
