"""The paper's model (Santhanam et al. 2008), equation by equation, and the run-time lung model.

Owns: :mod:`~lungdeform.model.graph` (spring-node graph, Sec. III-E), :mod:`~lungdeform.model.stiffness`
(Young's modulus fields), :mod:`~lungdeform.model.transfer` (local transfer (8)–(9), Green's matrix
(10)–(11)), :mod:`~lungdeform.model.solve` (the push loop (12)–(14) and the sparse fixed point),
:mod:`~lungdeform.model.response` (force → response, the one entry point every caller uses),
:mod:`~lungdeform.model.force` (applied force (18)), :mod:`~lungdeform.model.direction` (directions
(15)–(17)), :mod:`~lungdeform.model.displacement` (``u = k·F·d``, (1), exact volume calibration,
playback), :mod:`~lungdeform.model.dome` (a displacement split so that the diaphragm dome moves as
told), :mod:`~lungdeform.model.population` (the default an unfitted model takes its constants
from: Table I or the shipped population default, docs/DEFAULTS.md) and :mod:`~lungdeform.model.lung`
(:class:`LungModel` and :class:`Model`, the bundles a viewer or exporter plays).

May import: :mod:`lungdeform.interior`, :mod:`lungdeform.geometry` and the core modules. Never the
fitting code (:mod:`lungdeform.fit`), files (:mod:`lungdeform.io`) or playback.
"""

from .lung import BuildSettings, LungModel, Model, build_lung, build_model

__all__ = [
    "BuildSettings",
    "LungModel",
    "Model",
    "build_lung",
    "build_model",
]
