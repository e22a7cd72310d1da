"""lungdeform: real-time, physics-based 3-D breathing lung models (Santhanam et al. 2008).

The method is described equation by equation in docs/METHOD_NOTES.md, the package's layers in docs/ARCHITECTURE.md;
every module names the equations it implements. Heavy optional libraries are imported lazily where they are used.
"""

from lungdeform._compat import install as _install_compat
from lungdeform.errors import (
    ConvergenceError,
    InputError,
    LungdeformError,
    MaskError,
    MeshError,
    ModelFileError,
    ReadError,
    UnitsError,
)
from lungdeform.geometry.mesh import Surface, check_surface

__version__ = "0.7.0"

_install_compat()  # the module names of 0.4 (lungdeform.mesh, …) still import, with a warning

__all__ = [
    "ConvergenceError",
    "InputError",
    "LungdeformError",
    "MaskError",
    "MeshError",
    "ModelFileError",
    "ReadError",
    "Surface",
    "UnitsError",
    "check_surface",
    "__version__",
]
