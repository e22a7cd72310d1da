"""DICOM in and out: every byte lungdeform reads from or writes to a DICOM file goes through here.

Owns: :mod:`~lungdeform.io.dicom.guard` (damaged element headers refused before GDCM parses a
file), :mod:`~lungdeform.io.dicom.attributes` (the one validation walk: a dataset's required
attributes and UIDs checked on read, every value checked against its VR's limits before a write;
decimal strings formatted to 16 bytes), :mod:`~lungdeform.io.dicom.slices` (a series' slice
geometry checked before reading), :mod:`~lungdeform.io.dicom.folder` (a folder as exports come: its
image series told from RTSTRUCT, RTPLAN, RTDOSE, DICOMDIR, localizers and files that are no DICOM,
which are named; the series to read chosen), :mod:`~lungdeform.io.dicom.series` (a CT series found, checked
and read; an image written as a CT series, one per phase of a synthetic 4-D CT),
:mod:`~lungdeform.io.dicom.fourdct` (the phases of a 4-D CT in one folder, told apart and ordered
by their tags), :mod:`~lungdeform.io.dicom.rtstruct` (RT structure sets in and out) and
:mod:`~lungdeform.io.dicom.registration` (a displacement field written as a Deformable Spatial
Registration object). docs/RADIOTHERAPY.md, "DICOM conformance".

May import: :mod:`lungdeform.io.grid` (the image grid and the voxel cap), :mod:`lungdeform.geometry`
and the core modules; never the rest of :mod:`lungdeform.io`, whose only way in is
:func:`lungdeform.io.image.read_image` (import-linter contract in pyproject.toml).
"""
