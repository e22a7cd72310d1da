"""Closed lung surfaces and the geometry on them: no physics, no files.

Owns: :mod:`~lungdeform.geometry.mesh` (the :class:`Surface` bundle, checks and repairs, volume by the
divergence theorem, subdivision, thinning), :mod:`~lungdeform.geometry.moments` (volume, centroid and covariance of the enclosed solid),
:mod:`~lungdeform.geometry.intersect` (self-intersection:
face pairs that cross), :mod:`~lungdeform.geometry.remesh` (Taubin smoothing,
decimation, clean-up), :mod:`~lungdeform.geometry.distance` (exact point-to-triangle distance, surface
distance statistics), :mod:`~lungdeform.geometry.depth` (how far inside a closed surface a point lies,
sampled once on a grid), :mod:`~lungdeform.geometry.contours` (a surface through planar contours,
mesh–plane sections), :mod:`~lungdeform.geometry.frame` (the per-side lung frame of Sec. IV-B, the
side check), :mod:`~lungdeform.geometry.regions` (a lung surface's apex, base, costal and
mediastinal regions) and :mod:`~lungdeform.geometry.dome` (the diaphragm dome's height and its excursion
relative to the apex).

May import: the package root's core modules (``errors``, ``constants``, ``atomic``) only.
"""
