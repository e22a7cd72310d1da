"""lungdeform: real-time, physics-based 3-D breathing lung models (Santhanam et al. 2008).

The method is described equation by equation in docs/METHOD_NOTES.md, the package's layers in docs/ARCHITECTURE.md;
every module names the equations it implements. Heavy optional libraries are imported lazily where they are used.
"""

from lungdeform._moved import install as _install_moved
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

__version__ = "0.8.0"

_install_moved()  # a module path of before 0.8 (lungdeform.mesh, …) fails naming its path now

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
