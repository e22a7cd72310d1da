"""CT to lungs: reading a CT, the lung masks without learned weights, one mask split into two lungs.

Owns: :mod:`~lungdeform.segment.ct` (a CT in HU from an image file, a DICOM folder or an archive;
its grid made axial and downsampled), :mod:`~lungdeform.segment.lungs` (threshold, airway removal,
left/right split of a CT's lungs: :func:`~lungdeform.segment.lungs.segment_lungs`) and
:mod:`~lungdeform.segment.split` (a binary mask holding both lungs in one label → left and right;
each lung's landmarks). Used by ``lungdeform segment``, ``lungdeform build`` and the fit's inputs.

May import: :mod:`lungdeform.io`, :mod:`lungdeform.plot` and the core modules; nothing of the
model, the interior, breathing or fitting (it knows voxels and masks, not lungs that move).
"""
