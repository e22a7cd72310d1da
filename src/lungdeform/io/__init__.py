"""Files in and out: meshes, medical images, masks, point sets and the model file.

Owns: :mod:`~lungdeform.io.meshfile` (STL, OBJ, PLY, VTK, VTP, OFF, glTF/GLB surfaces),
:mod:`~lungdeform.io.vtk` (the VTK legacy and VTP XML readers and the one VTP writer),
:mod:`~lungdeform.io.grid` (the image grid: :class:`~lungdeform.io.grid.Image`, voxel → world, the
voxel cap), :mod:`~lungdeform.io.image` (NIfTI, MHA/MHD, NRRD, DICOM in LPS; writing images and
displacement fields, resampling through a field), :mod:`~lungdeform.io.dicom` (everything DICOM:
the byte guard, series, 4-D CT, RT structure sets, the registration object, conformance),
:mod:`~lungdeform.io.mask` (masks → surfaces by marching cubes in world mm),
:mod:`~lungdeform.io.landmarks` (DIR-Lab and elastix point files) and
:mod:`~lungdeform.io.modelfile` (the versioned model file, docs/MODEL_FORMAT.md).

May import: :mod:`lungdeform.model`, :mod:`lungdeform.interior`, :mod:`lungdeform.geometry` and the
core modules. Every reader normalises to ``(n, 3)`` C-contiguous float64 mm once, here, and raises
:class:`~lungdeform.errors.ReadError` (or a subclass) naming the file.
"""

from .meshfile import (
    MESH_SUFFIXES,
    UNITS_MM,
    WRITE_SUFFIXES,
    load,
    load_surface,
    merge_duplicate_vertices,
    read_mesh,
    write_mesh,
)

__all__ = [
    "MESH_SUFFIXES",
    "UNITS_MM",
    "WRITE_SUFFIXES",
    "load",
    "load_surface",
    "merge_duplicate_vertices",
    "read_mesh",
    "write_mesh",
]
