"""Validation experiments: the paper's Sec. IV-A, DIR-Lab landmarks, the ITK lung pair, breathing traces.

Owns: :mod:`~lungdeform.validate.paper` and :mod:`~lungdeform.validate.msd` (the transfer model against
a mass–spring–damper run to rest, Figs. 7–9), :mod:`~lungdeform.validate.dirlab`,
:mod:`~lungdeform.validate.dirlab_files` and :mod:`~lungdeform.validate.dirlab_experiment` (DIR-Lab 4-D
CT landmarks: the models, finding the files, the experiment of ``lungdeform validate dirlab``),
:mod:`~lungdeform.validate.itk_pair` (the model fitted to the ITK right lung at two volumes and measured
against baselines), :mod:`~lungdeform.validate.copd` (both lungs of the DIR-Lab COPDgene lung masks, fitted per
lung, with calibrated mask-only baselines), :mod:`~lungdeform.validate.breathing` (the PV breathing driver scored on held-out
cycles of a folder of recorded traces), :mod:`~lungdeform.validate.prediction` (live breathing
prediction and its intervals scored on recorded traces), :mod:`~lungdeform.validate.gating` (amplitude
gating of a beam simulated on recorded traces), :mod:`~lungdeform.validate.single_scan` (the defaults scored
from one scan, leave one subject out; learning a default from data folders; its report:
:mod:`~lungdeform.validate.single_scan_report`; its rows given the dome excursion:
:mod:`~lungdeform.validate.dome_rows`), :mod:`~lungdeform.validate.subjects` (two-volume subject
folders, their cohort manifest), :mod:`~lungdeform.validate.lung_pair` (one lung at two volumes, a cut
left out), :mod:`~lungdeform.validate.fitted_lung` (its two-scan fit, cached),
:mod:`~lungdeform.validate.translation` (the best translation a prediction is scored after) and
:mod:`~lungdeform.validate.physiology` (a tidal breath's motion: base SI against AP, diaphragm per litre).

May import: everything below it (:mod:`lungdeform.cohort`, :mod:`lungdeform.fit`, …); never the CLI.
"""
