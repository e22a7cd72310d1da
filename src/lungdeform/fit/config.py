"""What a fit is given: one lung's inputs (:class:`FitInputs`) and how to fit them (:class:`FitConfig`).

Both are frozen and validated once, on construction; an error names the field at fault
(``folds``, ``align``), never a command-line option (the CLI maps field names to its options).
:func:`lungdeform.evaluate.pipeline.run_fit` takes one of each.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Sequence

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.frame import SIDES
from lungdeform.io.dicom.folder import SeriesChoice
from lungdeform.model.direction import MAX_DEGREE
from lungdeform.segment.split import SplitCache

from .direction_correction import DEFAULT_DEGREE
from .fitting import MODES
from .refinement import FINEST_MM

#: Ways of bringing the larger-volume inputs into the end-exhale frame (:mod:`lungdeform.evaluate.placement`);
#: ``"auto"``: ``"none"`` for inputs sharing one DICOM Frame of Reference, else ``"apex"``
#: (:func:`lungdeform.fit.cycle.choose_alignment`).
ALIGN_MODES = ("auto", "apex", "joint", "none")
#: Search modes that can fit a translation per target (``align="joint"``).
JOINT_MODES = ("optimizer", "least_squares")


@dataclass(frozen=True)
class FitInputs:
    """One lung at two or more volumes, end-exhale first.

    Attributes
    ----------
    paths : tuple of path
        Surface meshes, masks or CTs (a DICOM folder or archive), volumes increasing; or one folder
        holding a 4-D CT (every phase, :mod:`lungdeform.io.dicom.fourdct`), whose phases are the inputs.
    side : str
        ``"left"`` or ``"right"``.
    volumes_ml : tuple of float, or None
        Lung volume of each input (mL, e.g. from spirometry); None: measured from the surfaces.
        Only their changes are used: the end-exhale volume is the model mesh's own.
    landmarks : tuple of path, or None
        One elastix point-set file per input, rows corresponding (an empty sequence is None).
    splits : SplitCache, or None
        Where a mask holding both lungs is split (:class:`~lungdeform.segment.split.SplitCache`): a
        caller fitting both lungs of the same masks passes one, so that each mask is split once.
    series : SeriesChoice, or None
        Which CT series to read of an input DICOM folder holding several
        (:class:`~lungdeform.io.dicom.folder.SeriesChoice`, ``fit --series``).
    """

    paths: Sequence[Path | str]
    side: str
    volumes_ml: Sequence[float] | None = None
    landmarks: Sequence[Path | str] | None = None
    splits: SplitCache | None = field(default=None, compare=False, repr=False)
    series: SeriesChoice | None = None

    def __post_init__(self):
        object.__setattr__(self, "paths", tuple(self.paths))
        if not self.paths:
            raise InputError("paths: a fit needs inputs at two or more volumes (end-exhale first), or one 4-D CT "
                             "folder, got none")
        if len(self.paths) == 1 and not Path(self.paths[0]).is_dir():
            raise InputError(f"paths: a fit needs inputs at two or more volumes (end-exhale first), or one 4-D CT "
                             f"folder; {self.paths[0]} is not a folder")
        if len(self.paths) == 1 and (self.volumes_ml is not None or self.landmarks):
            raise InputError(f"paths: {self.paths[0]} is one 4-D CT: its volumes are measured per phase, and "
                             "volumes_ml and landmarks cannot be given with it")
        if self.side not in SIDES:
            raise InputError(f"side must be 'left' or 'right', got {self.side!r}")
        if self.volumes_ml is not None:
            given = tuple(float(v) for v in self.volumes_ml)
            if len(given) != len(self.paths):
                raise InputError(f"volumes_ml has {len(given)} values for {len(self.paths)} inputs")
            if not all(np.isfinite(v) and v > 0 for v in given):
                raise InputError(f"volumes_ml must be positive mL, got {', '.join(f'{v:g}' for v in given)}")
            object.__setattr__(self, "volumes_ml", given)
        landmarks = tuple(self.landmarks) if self.landmarks else None
        if landmarks is not None and len(landmarks) != len(self.paths):
            raise InputError(f"landmarks needs one file per input ({len(self.paths)}), got {len(landmarks)}")
        object.__setattr__(self, "landmarks", landmarks)


#: The surface parts of the interior field a fit can give its model (:class:`FitConfig`).
INTERIORS = ("auto", "correspondence", "sliding")
#: ``interior="auto"`` takes the sliding field when crop faces hold more than this fraction of the
#: vertices of the model mesh or of a target (the ITK pair: 6 % and 5 %; DIR-Lab COPDgene: at most 0.6 %).
CROP_LIMIT = 0.02


@dataclass(frozen=True)
class FitConfig:
    """How :func:`lungdeform.evaluate.pipeline.run_fit` fits (the module docstring there gives the steps).

    Attributes
    ----------
    grid : bool
        Also run the paper's grid search (comparison row ``model_grid``).
    stiffness : bool
        Fit a heterogeneous stiffness field (:mod:`lungdeform.fit.expandability`), kept only if it
        lowers the objective.
    baselines : bool
        Measure the baselines (:mod:`lungdeform.evaluate.baselines`) and, with landmarks, the
        landmark-informed references.
    max_evaluations : int
        Optimiser budget (objective evaluations), ≥ 1.
    landmark_fit : bool
        With landmarks: the headline model carries the interior landmark correction
        (:mod:`lungdeform.interior.field`), scored on held-out landmarks.
    folds : int
        Folds of the landmark cross-validation, ≥ 2 (and at most the number of landmarks).
    landmark_weight : float
        Weight of the landmark term in the landmark-informed fits and references, ≥ 0.
    align : str
        One of :data:`ALIGN_MODES` (:mod:`lungdeform.evaluate.placement`).
    mode : str
        Search mode of the fits (:data:`lungdeform.fit.fitting.MODES`, ``"grid"`` excepted);
        ``align="joint"`` needs one of :data:`JOINT_MODES`.
    direction_degree : int
        Degree of the direction correction (:mod:`lungdeform.fit.direction_correction`), 0…
        :data:`~lungdeform.model.direction.MAX_DEGREE`; 0: the paper's directions only.
    landmark_comparisons : bool
        With landmarks: also the landmark-informed fits of c1…c9
        (:func:`lungdeform.evaluate.crossval.cross_validate_landmarks`; slow) as comparison rows.
    side_check : bool
        Refuse inputs whose shape clearly says the other side
        (:func:`lungdeform.geometry.frame.check_side`).
    interior : str
        The surface part of the interior field (:data:`INTERIORS`): ``"correspondence"``, the smooth
        map of the end-exhale solid onto the largest volume's (:mod:`lungdeform.fit.registration`),
        ``"sliding"``, the sliding interpolation of the fitted surface displacement
        (:mod:`lungdeform.interior.sliding`), or ``"auto"``: the correspondence unless the scans are
        cropped (crop faces on more than :data:`CROP_LIMIT` of a surface's vertices: the field of view
        cuts the lung at different tissue in each scan, so the two solids are not the same tissue).
    refine_mm : float
        Finest Gaussian width (mm) of the surface refinement (:mod:`lungdeform.fit.refinement`), ≥ 1;
        0: no refinement (the displacement is the fitted ``k·F·d``).
    command : str
        What ran the fit, recorded in the model file's provenance.
    """

    grid: bool = False
    stiffness: bool = False
    baselines: bool = True
    max_evaluations: int = 300
    landmark_fit: bool = True
    folds: int = 5
    landmark_weight: float = 1.0
    align: str = "auto"
    mode: str = "optimizer"
    direction_degree: int = DEFAULT_DEGREE
    landmark_comparisons: bool = False
    side_check: bool = True
    interior: str = "auto"
    refine_mm: float = FINEST_MM
    command: str = "fit"

    def __post_init__(self):
        switches = [f.name for f in fields(self) if f.type == "bool"]
        for name in switches:
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if not (_whole(self.max_evaluations) and self.max_evaluations >= 1):
            raise InputError(f"max_evaluations must be a whole number >= 1, got {self.max_evaluations!r}")
        if not (_whole(self.folds) and self.folds >= 2):
            raise InputError(f"folds must be a whole number >= 2, got {self.folds!r}")
        if not (_whole(self.direction_degree) and 0 <= self.direction_degree <= MAX_DEGREE):
            raise InputError(f"direction_degree must be a whole number 0…{MAX_DEGREE}, got {self.direction_degree!r}")
        if not (_real(self.landmark_weight) and np.isfinite(self.landmark_weight) and self.landmark_weight >= 0):
            raise InputError(f"landmark_weight must be a finite number >= 0, got {self.landmark_weight!r}")
        if self.align not in ALIGN_MODES:
            raise InputError(f"align must be one of {', '.join(ALIGN_MODES)}, got {self.align!r}")
        if self.mode not in MODES or self.mode == "grid":
            raise InputError(f"mode must be one of {', '.join(m for m in MODES if m != 'grid')}, got {self.mode!r}")
        if self.align == "joint" and self.mode not in JOINT_MODES:
            raise InputError(f"align 'joint' needs the least-squares optimiser, not mode {self.mode!r}")
        if self.interior not in INTERIORS:
            raise InputError(f"interior must be one of {', '.join(INTERIORS)}, got {self.interior!r}")
        if not (_real(self.refine_mm) and (self.refine_mm == 0 or 1 <= self.refine_mm <= 50)):
            raise InputError(f"refine_mm must be 0 (no surface refinement) or 1…50 mm, got {self.refine_mm!r}")
        if not isinstance(self.command, str):
            raise InputError(f"command must be a string, got {self.command!r}")
        for name in ("max_evaluations", "folds", "direction_degree"):  # plain Python numbers
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "landmark_weight", float(self.landmark_weight))
        object.__setattr__(self, "refine_mm", float(self.refine_mm))
        for name in switches:
            object.__setattr__(self, name, bool(getattr(self, name)))


def _whole(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _real(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))
