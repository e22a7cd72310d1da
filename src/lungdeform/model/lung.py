"""A lung model: everything playback needs, precomputed once (docs/METHOD_NOTES.md §2–7).

:func:`build_lung` runs the pipeline on one closed surface:

1. lung frame and normalised coordinates (``frame``);
2. spring-node graph and local transfer ``T_e`` with the stiffness field, and
3. the elastostatic responses to the four force fields ``1, x̂, ŷ, ẑ`` (``force``, ``response``);
4. the applied force for the chosen gravity (a 4-term combination) and its response ``F``;
5. the directions (15)–(17) (``direction``);
6. the calibrated displacement per unit volume ``u = k·F·d`` (``displacement``).

A :class:`Model` bundles one or two lungs with provenance; :mod:`lungdeform.io.modelfile` stores it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from lungdeform.constants import TIDAL_VOLUME_ML, gravity_vector
from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.frame import LungFrame, lung_frame
from lungdeform.geometry.mesh import Surface
from lungdeform.interior.field import KINDS, LandmarkCorrection, interior_field
from lungdeform.interior.prior import TaperedPrior, lung_normaliser, prior_affine
from lungdeform.interior.surface_map import SurfaceMapField, surface_extension
from lungdeform.progress import Progress, silent

from .direction import corrected_directions, polynomial_basis
from .direction import directions as direction_field
from .displacement import Playback, calibrate, calibration_units, scale_for_volume, volume_polynomial
from .dome import DomeRequest, check_feasible, dome_split, split_record
from .force import field_basis, force_weights
from .population import PopulationDefault, resolve_default
from .response import ResponseSolver
from .scan_state import ScanState
from .solve import LinearSolver
from .stiffness import as_moduli, uniform
from .tidal import split_rule, tidal_split


@dataclass(frozen=True, eq=False)
class LungModel:
    """One lung's precomputed model.

    Attributes
    ----------
    side : 'left' | 'right'
    surface : Surface
        End-exhale surface p, mm LPS.
    constants : (9,) float
        c1…c9.
    stiffness : (n,) float
        Young's modulus per vertex (relative units).
    frame : LungFrame
    directions : (n, 3) float
        Unit displacement directions d, LPS, for :attr:`gravity` (origins on the supported side).
    force_basis : (4, n) float
        Elastostatic force F (kept force on mass nodes) for the fields 1, x̂, ŷ, ẑ.
    gravity : (3,) float
        Unit gravity direction (LPS) that :attr:`displacement` was built for.
    displacement : (n, 3) float
        u, mm per ``unit_ml`` of volume, LPS.
    unit_ml : float
        ΔV, mL per unit.
    calibration_ml : float
        Volume change at which the calibration is exact (mL).
    d_min : float
        Minimum transfer distance, mm.
    landmarks : (m, 3) float or None
        End-exhale interior landmarks of the fit, mm LPS, when the fit had them.
    landmark_correction : (m, 3) float or None
        The landmarks' motion the surface cannot see, mm per unit (:mod:`lungdeform.interior.field`).
    landmark_smoothing : float
        Smoothing of that correction: the surface smoothing of the sliding correction, mm (kind
        ``"sliding"``), or the thin-plate smoothing, mm² (the older kinds).
    interior_vertices : (n,) bool or None
        The vertices whose motion drives the interior field; None: all. A fit leaves out the
        vertices on the crop faces of its scans (an image boundary, not lung surface: the model's
        motion there was never fitted).
    interior_kind : str
        How the surface displacement and the landmark correction extend inside
        (:data:`lungdeform.interior.field.KINDS`): ``"sliding"`` (the surface's normal motion,
        :mod:`lungdeform.interior.sliding`, and a correction that keeps it; model files of schema 3),
        ``"sliding_thin_plate"`` (the same surface part, a thin-plate correction; schema-2 files) or
        ``"thin_plate"`` (the thin-plate spline of the whole displacement; schema-1 files). Older
        files play back as they were made.
    interior_map : SurfaceMapField or None
        When set, the surface part of the interior field is this surface-to-surface map
        (:mod:`lungdeform.interior.surface_map`, fitted by :mod:`lungdeform.fit.registration`)
        instead of the sliding interpolation of :attr:`displacement`; kind ``"sliding"`` only.
    """

    side: str
    surface: Surface
    constants: np.ndarray
    stiffness: np.ndarray
    frame: LungFrame
    directions: np.ndarray
    force_basis: np.ndarray
    gravity: np.ndarray
    displacement: np.ndarray
    unit_ml: float = 1.0
    calibration_ml: float = TIDAL_VOLUME_ML
    d_min: float = 1.0
    landmarks: np.ndarray | None = None
    landmark_correction: np.ndarray | None = None
    landmark_smoothing: float = 0.0
    interior_vertices: np.ndarray | None = None
    interior_kind: str = "sliding"
    interior_map: SurfaceMapField | None = None

    def __post_init__(self):
        if self.interior_kind not in KINDS:
            raise InputError(f"interior_kind must be one of {', '.join(KINDS)}, got {self.interior_kind!r}")
        if self.interior_map is not None and self.interior_kind != "sliding":
            raise InputError(f"an interior_map goes with interior_kind 'sliding', got {self.interior_kind!r}")
        iv = self.interior_vertices
        if iv is not None:
            iv = np.asarray(iv)
            if iv.dtype != bool or iv.shape != (self.surface.n_vertices,) or int(iv.sum()) < 13:
                raise InputError(f"interior_vertices must be ({self.surface.n_vertices},) bool with at least 13 set, "
                                 f"got {iv.dtype} {iv.shape} with {int(np.count_nonzero(iv))} set")

    @property
    def n_vertices(self) -> int:
        return self.surface.n_vertices

    @property
    def volume_ee_ml(self) -> float:
        """Volume of the rest surface (the scan the lung was built from), mL: the end-exhale volume V_EE
        of the paper and of every fit; for a model whose scan lies above end-exhale
        (:attr:`Model.scan`) the volume at that scan."""
        return self.surface.volume_ml

    @cached_property
    def volume_poly(self) -> np.ndarray:
        """``(4,)`` mm³: V(p + s·u) = a0 + a1 s + a2 s² + a3 s³, s in units."""
        return volume_polynomial(self.surface.vertices, self.surface.faces, self.displacement)

    @cached_property
    def force_weights(self) -> np.ndarray:
        """``(4,)`` weights of the four fields for :attr:`gravity`."""
        return force_weights(self.frame, self.gravity, self.constants)

    @property
    def force(self) -> np.ndarray:
        """Elastostatic force ``F : (n,)`` for :attr:`gravity`."""
        return self.force_weights @ self.force_basis

    def applied_force(self, gravity=None) -> np.ndarray:
        """Applied force ``f : (n,)`` (18) for ``gravity`` (default: the model's)."""
        g = self.gravity if gravity is None else gravity
        w = force_weights(self.frame, g, self.constants)
        return w @ field_basis(self.frame.normalized(self.surface.vertices))

    @property
    def basis_displacement(self) -> np.ndarray:
        """``(4, n, 3) float``: ``F_k · d`` per field (unscaled), for engines that re-orient."""
        return self.force_basis[:, :, None] * self.directions[None, :, :]

    def scale_for(self, volume_ml: float, exact: bool = False) -> float:
        """Units ``s`` for an absolute lung volume (mL): linear ``(V − V_EE)/ΔV`` or exact."""
        delta = float(volume_ml) - self.volume_ee_ml
        if exact:
            return scale_for_volume(self.volume_poly, delta)
        return delta / self.unit_ml

    def positions_at(self, scale: float) -> np.ndarray:
        """``x = p + s·u : (n, 3) float`` mm LPS."""
        return self.surface.vertices + float(scale) * self.displacement

    def surface_at(self, volume_ml: float | None = None, *, scale: float | None = None,
                   exact: bool = False) -> Surface:
        """The surface at an absolute volume (mL) or at ``scale`` units above end-exhale."""
        if (volume_ml is None) == (scale is None):
            raise InputError("give exactly one of volume_ml or scale")
        s = self.scale_for(volume_ml, exact) if scale is None else float(scale)
        return Surface(self.positions_at(s), self.surface.faces, f"{self.side} at s={s:.4g}")

    @cached_property
    def interior(self):
        """The :class:`~lungdeform.interior.field.InteriorField` of this lung: displacement per unit of any
        point inside it (surface-driven, plus the landmark correction when the model has one)."""

        on = slice(None) if self.interior_vertices is None else np.asarray(self.interior_vertices, bool)
        correction = LandmarkCorrection(self.landmarks, self.landmark_correction, self.landmark_smoothing)
        return interior_field(self.surface.vertices[on], self.displacement[on], correction,
                              normals=self.surface.vertex_normals[on], kind=self.interior_kind,
                              correspondence=self.interior_map)

    @cached_property
    def surface_interior(self) -> np.ndarray:
        """``(n, 3) float`` mm per unit: :attr:`interior`'s displacement at this lung's own surface vertices,
        computed once (every displacement field of the lung starts from its largest,
        :func:`lungdeform.playback.displacement_field.surface_peak`: 8 ms CPU a lung each time)."""
        return self.interior.displacement(self.surface.vertices)

    def points_at(self, points, volume_ml: float | None = None, *, scale: float | None = None,
                  exact: bool = False) -> np.ndarray:
        """Interior ``points : (q, 3)`` mm LPS (end-exhale) moved to an absolute volume (mL) or to
        ``scale`` units: ``q + s·v(q) : (q, 3) float`` mm LPS (:attr:`interior`)."""
        if (volume_ml is None) == (scale is None):
            raise InputError("give exactly one of volume_ml or scale")
        s = self.scale_for(volume_ml, exact) if scale is None else float(scale)
        return self.interior.positions(points, s)

    def playback(self, dtype=np.float32) -> Playback:
        """A :class:`Playback` over this lung (float32 by default, as a GPU buffer)."""
        return Playback(self.surface.vertices, self.displacement, dtype=dtype)

    def oriented(self, gravity) -> "LungModel":
        """A new model for another gravity direction (name or LPS vector): 4-term recombination of
        the precomputed responses, directions with their origins on the supported side
        (:meth:`LungFrame.supported`), then exact volume calibration. No new solve. A fitted
        direction correction (:mod:`lungdeform.fit.direction_correction`) and landmark correction
        belong to the scans' posture: the new directions are the paper's (15)–(17) and the
        landmark correction and the interior map are dropped. So is a dome split
        (:attr:`BuildSettings.dome_mm`): the new displacement is the default's."""
        g = gravity_vector(gravity)
        w = force_weights(self.frame, g, self.constants)
        d = direction_field(self.frame.supported(g), self.surface.vertices, self.constants)
        raw = (w @ self.force_basis)[:, None] * d
        u = _calibrated(self.surface, raw, self.calibration_ml, self.unit_ml, gravity)
        # the landmark correction was observed in the scan's posture: it does not carry over
        return replace(self, gravity=g, directions=d, displacement=u, landmarks=None,
                       landmark_correction=None, landmark_smoothing=0.0, interior_map=None)


@dataclass(frozen=True)
class BuildSettings:
    """How :func:`build_lung` computes a lung.

    calibration_ml : volume change (mL) at which the displacement's volume is exact.
    unit_ml : ΔV: the displacement is mm per this many mL.
    solver : 'bicgstab' | 'gmres' | 'direct' | callable, the linear solver of the force fixed point.
    d_min : the smallest distance (mm) of the force response.
    dome_mm : the diaphragm dome's excursion relative to the apex (mm) at ``calibration_ml``
        (:mod:`lungdeform.model.dome`); None: the default's own.
    """

    calibration_ml: float = TIDAL_VOLUME_ML
    unit_ml: float = 1.0
    solver: str | LinearSolver = "bicgstab"
    d_min: float = 1.0
    dome_mm: float | None = None


def build_lung(
    surface: Surface,
    side: str,
    *,
    constants=None,
    stiffness=None,
    gravity="supine",
    settings: BuildSettings = BuildSettings(),
    default: PopulationDefault | str | None = None,
    progress: Progress | None = None,
) -> LungModel:
    """Precompute a lung model from its end-exhale surface.

    Parameters
    ----------
    surface : Surface
        Closed, outward, mm LPS (check it first with :meth:`Surface.checked`).
    side : 'left' | 'right'
    constants : (9,) float, optional
        c1…c9; default those of ``default`` for ``side``. Given constants take the paper's
        directions (no direction correction).
    stiffness : (n,) float, optional
        Young's modulus per vertex; default uniform 1.
    gravity : str or (3,) float
        'supine', 'prone', 'upright', 'left-decubitus', 'right-decubitus' or an LPS vector.
    settings : BuildSettings
        Calibration volume, displacement unit (mL), linear solver, d_min, and the dome excursion: given,
        the displacement is split between the default's pattern and a head–foot stretch so that the dome
        descends that far at the calibration volume (:func:`lungdeform.model.dome.dome_split`).
    default : PopulationDefault, 'population', 'paper', path or None
        Where c1…c9 and the direction correction come from when ``constants`` is not given
        (:mod:`lungdeform.model.population`; None: the shipped population default).
    """
    say = progress or silent
    solver, d_min, calibration_ml, unit_ml = settings.solver, settings.d_min, settings.calibration_ml, settings.unit_ml
    chosen = resolve_default(default) if constants is None else None
    c = chosen.constants_for(side) if chosen is not None else np.asarray(constants, dtype=float)
    if c.shape != (9,) or not np.all(np.isfinite(c)):
        raise InputError(f"constants must be 9 finite values c1…c9, got shape {c.shape}")
    if settings.dome_mm is not None:  # an excursion the volume cannot produce: said before the slow part
        check_feasible(surface.vertices, surface.faces, settings.dome_mm, calibration_ml, f"{side} lung")
    n = surface.n_vertices
    e = uniform(n) if stiffness is None else as_moduli(stiffness, n)
    g = gravity_vector(gravity)
    p = surface.vertices
    frame = lung_frame(p, side)
    xyz = frame.normalized(p)
    say(f"{side}: spring graph and transfer ({n} vertices)")
    responses = ResponseSolver.from_surface(surface, e, d_min=d_min, method=solver)
    say(f"{side}: force responses ({responses.graph.n_nodes} graph nodes, 4 fields)")
    basis = responses.responses(field_basis(xyz))
    d = direction_field(frame.supported(g), p, c)  # origins on the supported side (frame.py)
    corr = None if chosen is None else chosen.correction_for(side, g)
    if corr is not None:  # the default's smooth correction of the paper's directions (population.py)
        d = corrected_directions(d, polynomial_basis(xyz, chosen.direction_degree), corr)
    raw = (force_weights(frame, g, c) @ basis)[:, None] * d
    u = _calibrated(surface, raw, calibration_ml, unit_ml, gravity)
    if settings.dome_mm is not None:
        say(f"{side}: splitting the breath for a dome excursion of {settings.dome_mm:g} mm")
        units = calibration_units(calibration_ml, unit_ml)
        u = dome_split(p, surface.faces, u * units, settings.dome_mm, calibration_ml,
                       name=f"{side} lung").displacement / units
    inner = None if chosen is None else default_interior(surface, side, u, chosen, unit_ml, g)
    return LungModel(side, surface, c, e, frame, d, basis, g, u, float(unit_ml),
                     float(calibration_ml), float(d_min), interior_map=inner)


def default_interior(surface: Surface, side: str, displacement: np.ndarray, default: PopulationDefault,
                     unit_ml: float, gravity) -> SurfaceMapField | None:
    """The interior of a lung built with ``default``: its ``displacement (n, 3)`` (mm per unit) carried
    inside (:func:`lungdeform.interior.surface_map.surface_extension`) plus the default's interior
    prior (mm per mL × ``unit_ml``) tapered to zero at the surface
    (:class:`lungdeform.interior.prior.TaperedPrior`), so that the lung the interior carries has the
    surface's shape and volume; None (the sliding interior) when the default has no prior or
    ``gravity`` is not the posture it was learned in."""
    prior = default.prior_for(gravity)
    if prior is None:
        return None
    inner = surface_extension(surface.vertices, displacement)
    affine = prior_affine(prior, *lung_normaliser(surface), side) * float(unit_ml)
    return inner.with_prior(TaperedPrior(affine, surface.vertices, surface.faces))


def unfolded_prior(field: SurfaceMapField, surface: Surface, displacement) -> SurfaceMapField:
    """The interior map of a lung read from a model file older than schema 6, made as it is now.

    A lung built with a population default had its interior prior folded into the affine part of the
    surface extension of its ``displacement (n, 3)`` (mm per unit), where it moved the lung's own
    surface (the warped lung breathed about 56 % of the model's volume, docs/MODEL_FORMAT.md). When
    ``field`` is that extension (an identity warp, the extension's centres, width and weights), the
    same map with the folded part split off and tapered (:class:`~lungdeform.interior.prior.TaperedPrior`);
    any other map (a fit's registration of two surfaces) is returned unchanged."""
    if field.prior is not None or not np.array_equal(field.warp, np.c_[np.eye(3), np.zeros(3)]):
        return field
    ext = surface_extension(surface.vertices, displacement)
    scale = float(np.abs(ext.weights).max(initial=0.0))
    same = (ext.centers.shape == field.centers.shape and np.allclose(ext.centers, field.centers, rtol=0, atol=1e-9)
            and ext.width_mm == field.width_mm
            and np.allclose(ext.weights, field.weights, rtol=1e-6, atol=1e-9 * scale))
    if not same:
        return field
    folded = field.linear - ext.linear
    if not np.any(np.abs(folded) > 1e-9 * max(float(np.abs(ext.linear).max()), 1e-300)):
        return field
    return ext.with_prior(TaperedPrior(folded, surface.vertices, surface.faces))


def _calibrated(surface: Surface, raw: np.ndarray, calibration_ml: float, unit_ml: float, gravity):
    """:func:`calibrate`, with a message that says why a field may not expand the lung."""
    try:
        return calibrate(surface.vertices, surface.faces, raw, calibration_ml=calibration_ml,
                         unit_ml=unit_ml)
    except LungdeformError as exc:
        if isinstance(exc, InputError):
            raise
        raise LungdeformError(
            f"{surface.name}: with gravity {gravity!r} the applied force and the directions "
            "(c1…c6) do not expand the lung (the force is largest where the directions run inward). "
            "Table I's directions were fitted supine; fit directions for this orientation "
            "(lungdeform fit) or give constants that suit it"
        ) from exc


@dataclass(frozen=True, eq=False)
class Model:
    """One or two lungs with provenance (what was built from what, with which settings) and the
    breathing state of the scan their rest surfaces are (``scan``, :mod:`lungdeform.model.scan_state`;
    default end-exhale)."""

    lungs: dict[str, LungModel]
    provenance: dict = field(default_factory=dict)
    scan: ScanState = field(default_factory=ScanState)

    def __post_init__(self):
        if not self.lungs:
            raise InputError("a model needs at least one lung")

    @property
    def names(self) -> list[str]:
        return list(self.lungs)

    def oriented(self, gravity) -> "Model":
        return Model({k: v.oriented(gravity) for k, v in self.lungs.items()}, dict(self.provenance), self.scan)


def build_model(
    surfaces: dict[str, Surface],
    *,
    tidal_ml: float = TIDAL_VOLUME_ML,
    constants: dict[str, np.ndarray] | None = None,
    stiffness: dict[str, np.ndarray] | None = None,
    provenance: dict | None = None,
    progress: Progress | None = None,
    settings: BuildSettings = BuildSettings(),
    **kwargs,
) -> Model:
    """Build one model per side from ``{side: surface}``.

    The tidal volume (mL, both lungs together) is split between the lungs by
    :func:`lungdeform.model.tidal.tidal_split`: two lungs in proportion to their end-exhale volumes,
    a lone lung its side's usual share of both (right 53.6 %, left 46.4 %); each lung is calibrated
    exactly at its part (which replaces ``settings.calibration_ml``; ``settings``:
    :class:`BuildSettings`). The provenance records ``tidal_ml`` (both lungs), which playback
    divides by (:func:`lungdeform.model.tidal.played_shares`). Other keyword arguments go
    to :func:`build_lung` (``gravity``, ``default``). The
    provenance records the default the lungs were built with (``"default"``: name and digest).
    The model's scan is end-exhale (``dataclasses.replace(model, scan=…)`` says otherwise).
    A keyword ``dome`` (:class:`lungdeform.model.dome.DomeRequest`): each lung's dome excursion over the
    breath; the provenance records it (``"dome"``: asked, where it came from, measured on the built lungs).
    Without it the lungs are built as before and the provenance has no ``"dome"``.
    """
    parts = tidal_split({side: s.volume_ml for side, s in surfaces.items()}, tidal_ml)
    chosen = resolve_default(kwargs.pop("default", None))
    dome: DomeRequest | None = kwargs.pop("dome", None)
    domes = {} if dome is None else dome.per_lung(surfaces, parts)
    lungs = {}
    for side, surface in surfaces.items():
        lungs[side] = build_lung(
            surface, side,
            constants=None if constants is None else constants.get(side),
            stiffness=None if stiffness is None else stiffness.get(side),
            settings=replace(settings, calibration_ml=parts[side], dome_mm=domes.get(side, settings.dome_mm)),
            default=chosen, progress=progress, **kwargs,
        )
    prov = dict(provenance or {})
    if dome is not None:
        prov.setdefault("dome", split_record(dome, domes, lungs))
    prov.setdefault("tidal_ml", tidal_ml)
    prov.setdefault("tidal_split", split_rule(list(surfaces)))
    if constants is None or len(constants) < len(surfaces):
        prov.setdefault("default", chosen.record())
    return Model(lungs, prov)
