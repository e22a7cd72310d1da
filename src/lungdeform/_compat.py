"""The module names of lungdeform ≤ 0.4 keep importing, with a ``DeprecationWarning`` naming the new path.

Until 0.4 every module sat at the package root (``lungdeform.mesh``, ``lungdeform.trace``,
``lungdeform.sliding``, …); 0.5 moved them into layered subpackages (docs/ARCHITECTURE.md,
"Compatibility"). :func:`install`, called by ``lungdeform/__init__.py``, appends a finder to
:data:`sys.meta_path` that answers ``import lungdeform.<old>`` with the module at its new path:

- the *same* module object, registered in :data:`sys.modules` under the old name too, so a
  monkeypatch through either name is seen through both;
- one ``DeprecationWarning`` per process and old name (the first import; later imports find the
  name in :data:`sys.modules`), attributed to the importing line;
- names not in :data:`MOVED` (a typo) fall through to the usual ``ModuleNotFoundError``; the finder
  sits last on :data:`sys.meta_path`, so a real module of the same name always wins.

Old names that are a module or package now are not mapped: ``model``, ``io``, ``breathing``,
``interior``, ``fit``, ``cohort`` and ``bench`` are subpackages that re-export their old modules'
public names (``from lungdeform.model import build_model``). The new module is imported by name at
import time, never by an import statement here, so import-linter sees no dependency of this module
and the package's own code (which uses the new paths only) never triggers the warning.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

PACKAGE = "lungdeform"
#: Old module name (below ``lungdeform.``) → new path (below ``lungdeform.``), as moved in 0.5.
MOVED: dict[str, str] = {
    # geometry
    "mesh": "geometry.mesh", "remesh": "geometry.remesh", "distance": "geometry.distance",
    "frame": "geometry.frame",
    # io (``io`` itself is the package, which re-exports the old ``lungdeform.io``'s names)
    "vtkio": "io.vtk", "image": "io.image", "mask": "io.mask", "modelfile": "io.modelfile",
    "landmarks": "io.landmarks",
    # model (``model`` itself is the package, which re-exports the old ``lungdeform.model``'s names)
    "graph": "model.graph", "stiffness": "model.stiffness", "transfer": "model.transfer",
    "solve": "model.solve", "force": "model.force", "direction": "model.direction",
    "displacement": "model.displacement",
    # interior
    "interpolate": "interior.interpolate", "sliding": "interior.sliding",
    # breathing
    "inversion": "breathing.inversion", "presets": "breathing.presets", "trace": "breathing.trace",
    "cycles": "breathing.cycles", "holdout": "breathing.holdout", "stream": "breathing.stream",
    "respiration_baselines": "breathing.curve_models",
    # playback
    "export": "playback.export", "schedule": "playback.schedule", "markers": "playback.markers",
    "server": "playback.server", "demo": "playback.demo",
    "trajectory": "playback.trajectory",
    # fit
    "ct": "segment.ct", "align": "fit.align", "correspond": "fit.rays",
    "objective": "fit.objective", "search": "fit.search", "crossval": "evaluate.crossval",
    "expandability": "fit.expandability", "baselines": "evaluate.baselines",
    "direction_correction": "fit.direction_correction", "pipeline": "evaluate.pipeline", "report": "evaluate.report",
    # cohort
    "manifest": "cohort.manifest", "job": "cohort.job", "population": "cohort.population",
    "recovery": "cohort.recovery", "synthetic": "cohort.synthetic",
    # validate
    "paper": "validate.paper", "msd": "validate.msd", "dirlab": "validate.dirlab",
    "dirlab_files": "validate.dirlab_files",
}

def _internal(filename: str) -> bool:
    """The rule by which :func:`warnings.warn` skips frames when it counts ``stacklevel``."""
    return "importlib" in filename and "_bootstrap" in filename


def _stacklevel() -> int:
    """``stacklevel`` for a warning issued in :meth:`_AliasLoader.create_module`: the first frame
    outside the import machinery (the line with the ``import`` statement). ``warnings.warn`` does
    not count importlib's bootstrap frames, so neither does this."""
    frame, level = sys._getframe(2), 1  # the caller of create_module
    while frame is not None:
        name = frame.f_code.co_filename
        if not _internal(name):
            level += 1
            if not name.startswith((importlib.__file__, __file__)):
                break
        frame = frame.f_back
    return level


class _AliasLoader(importlib.abc.Loader):
    """Loads an old name as the module at its new path (imported, never executed twice)."""

    def __init__(self, old: str, new: str):
        self.old, self.new = old, new
        self._spec = None

    def create_module(self, spec):
        module = importlib.import_module(self.new)
        self._spec = module.__spec__
        warnings.warn(f"{self.old} is deprecated since lungdeform 0.5; import {self.new} instead "
                      "(docs/ARCHITECTURE.md)", DeprecationWarning, stacklevel=_stacklevel())
        return module

    def exec_module(self, module) -> None:
        # importlib set the old name's spec on the module; it keeps its own (reload, pickling).
        module.__spec__ = self._spec


class _RenamedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds ``lungdeform.<old>`` for the names of :data:`MOVED`; None for everything else."""

    def find_spec(self, fullname, path=None, target=None):
        package, _, old = fullname.partition(".")
        if package != PACKAGE or old not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, _AliasLoader(fullname, f"{PACKAGE}.{MOVED[old]}"))


def install() -> None:
    """Append the finder to :data:`sys.meta_path` (once, however often the package is reloaded)."""
    if not any(type(f).__name__ == _RenamedModuleFinder.__name__ for f in sys.meta_path):
        sys.meta_path.append(_RenamedModuleFinder())
