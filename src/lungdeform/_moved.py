"""Module paths that no longer exist fail with one line naming the module's path now.

0.5 moved every module from the package root into subpackages (``lungdeform.mesh`` →
``lungdeform.geometry.mesh``); 0.5–0.7 still imported the old paths, with a warning. From 0.8
they fail: ``import lungdeform.mesh`` raises ``ModuleNotFoundError: lungdeform.mesh moved to
lungdeform.geometry.mesh in 0.5`` (docs/CHANGELOG.md lists every path).

``import lungdeform.<path>`` of a module asks the finders of :data:`sys.meta_path` and no hook of
the package, so the one place that can name the new path is a finder there. This one sits last (a
real module of the same name always wins: it is never asked), answers only the names of
:data:`MOVED` and imports nothing: it raises, or returns None for every other name.
"""

from __future__ import annotations

import importlib.abc
import sys

PACKAGE = "lungdeform"

#: Old path → path now, both below ``lungdeform.``, and the version that moved it.
MOVED: dict[str, tuple[str, str]] = {
    # 0.5: modules at the package root moved into subpackages
    **{old: (new, "0.5") for old, new in {
        "mesh": "geometry.mesh", "remesh": "geometry.remesh", "distance": "geometry.distance",
        "frame": "geometry.frame",
        "vtkio": "io.vtk", "image": "io.image", "mask": "io.mask", "modelfile": "io.modelfile",
        "landmarks": "io.landmarks",
        "graph": "model.graph", "stiffness": "model.stiffness", "transfer": "model.transfer",
        "solve": "model.solve", "force": "model.force", "direction": "model.direction",
        "displacement": "model.displacement",
        "interpolate": "interior.interpolate", "sliding": "interior.sliding",
        "inversion": "breathing.inversion", "presets": "breathing.presets", "trace": "breathing.trace",
        "cycles": "breathing.cycles", "holdout": "breathing.holdout", "stream": "breathing.stream",
        "respiration_baselines": "breathing.curve_models",
        "export": "playback.export", "schedule": "playback.schedule", "markers": "playback.markers",
        "server": "playback.server", "demo": "playback.demo", "trajectory": "playback.trajectory",
        "ct": "segment.ct", "align": "fit.align", "correspond": "fit.rays",
        "objective": "fit.objective", "search": "fit.search", "crossval": "evaluate.crossval",
        "expandability": "fit.expandability", "baselines": "evaluate.baselines",
        "direction_correction": "fit.direction_correction", "pipeline": "evaluate.pipeline",
        "report": "evaluate.report",
        "manifest": "cohort.manifest", "job": "cohort.job", "population": "cohort.population",
        "recovery": "cohort.recovery", "synthetic": "cohort.synthetic",
        "paper": "validate.paper", "msd": "validate.msd", "dirlab": "validate.dirlab",
        "dirlab_files": "validate.dirlab_files",
    }.items()},
    # 0.8: fit/ split by concept (segment/, evaluate/), DICOM in io/dicom/, one name per meaning
    **{old: (new, "0.8") for old, new in {
        "fit.ct": "segment.ct",
        "fit.segment": "segment.lungs",
        "fit.lungsplit": "segment.split",
        "fit.baselines": "evaluate.baselines",
        "fit.crossval": "evaluate.crossval",
        "fit.heldout": "evaluate.heldout",
        "fit.inputs": "evaluate.inputs",
        "fit.pipeline": "evaluate.pipeline",
        "fit.placement": "evaluate.placement",
        "fit.report": "evaluate.report",
        "fit.scoring": "evaluate.scoring",
        "fit.correspond": "fit.rays",
        "fit.motion_prior": "interior.motion_prior",
        "interior.correspondence": "interior.surface_map",
        "breathing.baselines": "breathing.curve_models",
        "io.dicomseries": "io.dicom.series",
        "io.fourdct": "io.dicom.fourdct",
        "io.rtstruct": "io.dicom.rtstruct",
        "io.slices": "io.dicom.slices",
        "playback.dvf": "playback.displacement_field",
        "bench.dvf": "bench.displacement_field",
    }.items()},
}


def message(old: str) -> str:
    """The one line for the old path ``old`` (below ``lungdeform.``)."""
    new, version = MOVED[old]
    return f"{PACKAGE}.{old} moved to {PACKAGE}.{new} in {version} (docs/CHANGELOG.md)"


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Raises :class:`ModuleNotFoundError` with :func:`message` for an old path; None otherwise."""

    def find_spec(self, fullname, path=None, target=None):
        package, _, old = fullname.partition(".")
        if package == PACKAGE and old in MOVED:
            # no ``name=``: ``from lungdeform import mesh`` would swallow an error naming the module
            raise ModuleNotFoundError(message(old))
        return None


def install() -> None:
    """Append the finder to :data:`sys.meta_path`, once however often the package is reloaded."""
    if not any(type(f).__name__ == MovedModuleFinder.__name__ for f in sys.meta_path):
        sys.meta_path.append(MovedModuleFinder())
