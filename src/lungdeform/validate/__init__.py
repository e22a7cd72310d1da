"""Validation experiments: the paper's Sec. IV-A, DIR-Lab landmarks, the ITK lung pair, breathing traces.

Owns: :mod:`~lungdeform.validate.paper` and :mod:`~lungdeform.validate.msd` (the transfer model against
a mass–spring–damper run to rest, Figs. 7–9), :mod:`~lungdeform.validate.dirlab` and
:mod:`~lungdeform.validate.dirlab_files` (DIR-Lab 4-D CT landmarks), :mod:`~lungdeform.validate.breathing`
(the PV breathing driver scored on held-out cycles of a folder of recorded traces).

May import: everything below it (:mod:`lungdeform.cohort`, :mod:`lungdeform.fit`, …); never the CLI.
"""
