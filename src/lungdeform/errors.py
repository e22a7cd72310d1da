"""Exceptions raised by lungdeform.

Library code raises these; only the CLI turns them into exit codes (2 for bad input).
Every message should name the parameter or file at fault and what was expected.
"""

from __future__ import annotations

import importlib
from pathlib import Path


class LungdeformError(Exception):
    """Base class of every error lungdeform raises on purpose."""


class InputError(LungdeformError, ValueError):
    """A value given at a public boundary is of the wrong shape, type or range."""


class ReadError(LungdeformError):
    """A file is missing, empty, truncated or not of the expected format."""


class MeshError(LungdeformError):
    """A surface fails a check: open, non-manifold, mis-oriented, NaN, several components."""


class UnitsError(MeshError):
    """A surface's size shows it is not in millimetres."""


class MaskError(LungdeformError):
    """A mask or label image cannot give a surface (no foreground, bad labels)."""


class ConvergenceError(LungdeformError):
    """An iterative solver did not reach its tolerance."""


class FoldError(LungdeformError):
    """A displacement field folds: its Jacobian determinant is zero or negative somewhere."""


class ModelFileError(ReadError):
    """A model file has the wrong schema version, missing keys or inconsistent shapes."""


class MissingDependencyError(LungdeformError, ImportError):
    """An optional dependency needed for this feature is not installed."""


def require(module: str, feature: str, package: str | None = None):
    """Import an optional module or raise :class:`MissingDependencyError` naming the feature."""

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        pkg = package or module.split(".")[0]
        raise MissingDependencyError(
            f"{feature} needs the optional package '{pkg}': pip install {pkg}"
        ) from exc


def require_file(path, what: str, hint: str = "", error: type[ReadError] = ReadError) -> Path:
    """``path`` as a :class:`~pathlib.Path` when it names an existing file; else ``error`` naming it:
    a folder (``PATH: is a folder, not a WHAT file (HINT)``) or nothing there (``PATH: no such WHAT
    file``)."""
    p = Path(path)
    if p.is_dir():
        raise error(f"{p}: is a folder, not a {what} file" + (f" ({hint})" if hint else ""))
    if not p.is_file():
        raise error(f"{p}: no such {what} file")
    return p
