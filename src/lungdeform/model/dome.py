"""A lung whose diaphragm dome moves as told (docs/DEFAULTS.md, "Dome excursion").

A clinician may know how far the diaphragm moves (ultrasound or fluoroscopy of the dome, a 4-D CT), an AR
scene may want "chest" or "belly" breathing. Given the dome excursion ``E`` (mm, relative to the apex, as
:mod:`lungdeform.geometry.dome` defines and measures it) for the lung's calibration volume ``ΔV`` (mL), the
displacement at ``ΔV`` is

    ``u = a·u_d + b·s``

- ``u_d`` (n, 3) mm: the default's displacement at ``ΔV`` (c1…c9 of (18) with the directions (15)–(17): the
  learned pattern the rest of the lung follows);
- ``s`` (n, 3) mm per mm: the **head–foot stretch** (:func:`stretch_mode`), a volume-neutral (divergence-free)
  field that lowers the lung below its apex in proportion to ``h²`` (``h`` = depth below the apex over the
  height: 0 at the apex, 1 at the lowest point), the other two axes giving the volume back equally;
- ``(a, b)``: fixed by two conditions: the volume of ``p + u`` is ``V(p) + ΔV`` exactly (the cubic of
  :mod:`lungdeform.model.displacement`), and the dome of ``p + u``, measured as two masks are measured
  (:func:`lungdeform.geometry.dome.dome_weights`), has descended ``E`` relative to the apex (to
  :data:`TOLERANCE_MM`, or :data:`ACCEPT_MM` where the measurement jumps). The Lagrangian reading of the
  excursion (linear in ``(a, b)``) gives the first split; each further step moves its target by what the
  measurement still misses, then bisects.

So the stretch takes the difference between the excursion asked for and the one the default would give,
and the default's pattern carries the volume. Leave one subject out on the COPDgene lungs, given the
excursion measured from the two masks, this split scored about 0.8 × isotropic scaling on the surface (other
splits tried, and the scores: docs/DEFAULTS.md).

An excursion the volume cannot produce is refused (:class:`InputError`, :func:`check_feasible`): seen from the
apex, the floor descending ``E`` over the lung's footprint ``F`` (the underside's shadow) sweeps ``E·F``; more
than ``ΔV`` would leave the rest of the lung shrinking (on the COPDgene lungs ``E·F`` was 0.27–0.69 of
``ΔV``). So is a split that folds the surface.

The shorthand ``--breathing`` (:data:`BREATHING`): the diaphragm's share ``κ`` of each lung's volume change,
``E = κ·ΔV/F``: always producible (``κ < 1``), and scaled to the lung's own footprint. Values and sources in
docs/DEFAULTS.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.dome import dome_weights
from lungdeform.geometry.mesh import face_areas, face_normals
from lungdeform.geometry.moments import solid_moments

from .displacement import MM3_PER_ML, volume_tensors

#: Power of the depth below the apex in the head–foot stretch (:func:`stretch_mode`; 1: an affine
#: stretch. Scored 1, 1.5, 2, 3: 3.82, 3.80, 3.79, 3.79 mm, docs/DEFAULTS.md).
STRETCH_POWER = 2.0
#: How close (mm) the measured excursion of the built lung comes to the one asked for, where the
#: measurement allows (it jumps by up to ~0.1 mm as faces enter and leave the underside).
TOLERANCE_MM = 0.05
#: The split is refused (does not converge) when the nearest it comes is farther than this, mm.
ACCEPT_MM = 0.25
#: Fixed-point steps of the split before bisection; steps in all before it gives up.
FIXED_STEPS = 6
MAX_STEPS = 40
#: ``--breathing``: the share of each lung's volume change its floor sweeps, ``κ = E·F/ΔV`` (docs/DEFAULTS.md,
#: "Dome excursion": chest the lowest measured on the shared subjects, mixed the abdominal share of quiet
#: breathing, belly nearly all of the breath).
BREATHING = {"chest": 0.3, "mixed": 0.64, "belly": 0.9}
#: Share of the surface's area that may turn over beyond what turns over under the default alone.
FOLDED_SHARE = 0.01
#: Largest ``--dome-mm`` taken at all, mm: a diaphragm moves up to about 10 cm in a maximal breath.
MAX_DOME_MM = 150.0


@dataclass(frozen=True)
class DomeSplit:
    """The split of one lung's displacement (module docstring).

    Attributes
    ----------
    displacement : (n, 3) float
        ``u`` mm at the volume change asked for, LPS.
    weights : (2,) float
        ``(a, b)``: of the default's displacement (1: as it is) and of the stretch (mm at the lowest point).
    excursion_mm : float
        The dome excursion of ``p + u`` as measured (:func:`lungdeform.geometry.dome.dome_weights`), mm.
    default_excursion_mm : float
        The one the default alone gives, mm.
    steps : int
    """

    displacement: np.ndarray
    weights: np.ndarray
    excursion_mm: float
    default_excursion_mm: float
    steps: int


def stretch_mode(vertices, faces, power: float = STRETCH_POWER) -> np.ndarray:
    """``s : (n, 3) float``, mm per mm: the head–foot stretch of a surface ``vertices (n, 3)`` mm LPS.

    With ``h = (z_top − z)/H`` (``H`` the height), ``s_z = −h^p`` (the lowest point descends 1 mm per unit
    weight, the apex not at all) and ``s_x, s_y = −(x − c)·p·h^(p−1)/(2H)`` about the solid's centroid ``c``:
    its divergence is zero, so it changes the volume only at second order."""
    v = np.asarray(vertices, float)
    top, height = float(v[:, 2].max()), float(np.ptp(v[:, 2]))
    if not height > 0:
        raise InputError("the surface is flat along z: no head–foot stretch")
    h = (top - v[:, 2]) / height
    _, centre, _ = solid_moments(v, np.asarray(faces))
    across = -(v[:, :2] - centre[:2]) * (power * h ** (power - 1.0) / (2.0 * height))[:, None]
    return np.ascontiguousarray(np.c_[across, -(h ** power)])


def check_excursion(value, name: str = "dome excursion") -> float:
    """``value`` as a float mm, or :class:`InputError` naming ``name``: finite, ≥ 0 (a rising dome, a
    paralysed hemidiaphragm, is not modelled) and at most :data:`MAX_DOME_MM`."""
    try:
        e = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number of mm, got {value!r}") from None
    if math.isfinite(e) and e < 0:
        raise InputError(f"{name} must be ≥ 0 mm (a dome that rises on inspiration, paradoxical motion, is not "
                         f"modelled), got {value!r}")
    if not (math.isfinite(e) and e <= MAX_DOME_MM):
        raise InputError(f"{name} must be a number of mm in [0, {MAX_DOME_MM:g}] (a maximal breath moves the "
                         f"diaphragm about 10 cm), got {value!r}")
    return e


def check_feasible(vertices, faces, excursion_mm: float, delta_ml: float, name: str = "lung"):
    """The :class:`~lungdeform.geometry.dome.DomeWeights` of the surface, or :class:`InputError` naming ``name``
    when the volume cannot produce ``excursion_mm``: seen from the apex, a floor descending ``E`` over the
    lung's footprint ``F`` sweeps ``E·F``; more than ``delta_ml`` would leave the rest of the lung (chest wall,
    mediastinal face, apex) shrinking. Checked before a build's slow part."""
    e_mm = check_excursion(excursion_mm)
    if not (math.isfinite(delta_ml) and delta_ml > 0):
        raise InputError(f"{name}: the volume change must be > 0 mL, got {delta_ml!r}")
    w0 = dome_weights(vertices, faces, name=name)
    most = delta_ml * MM3_PER_ML / w0.footprint_mm2
    if e_mm > most:
        raise InputError(f"{name}: a dome excursion of {e_mm:g} mm cannot come with +{delta_ml:.0f} mL: the floor "
                         f"(footprint {w0.footprint_mm2 / 100:.0f} cm²) would sweep {e_mm * w0.footprint_mm2 / MM3_PER_ML:.0f}"
                         f" mL, more than the whole breath; at most {most:.1f} mm for that volume")
    return w0


def dome_split(vertices, faces, default_displacement, excursion_mm: float, delta_ml: float, *,
               name: str = "lung") -> DomeSplit:
    """:class:`DomeSplit` of a closed outward surface ``vertices (n, 3)`` mm LPS, ``faces (m, 3)``, whose default
    displacement at ``+delta_ml`` mL is ``default_displacement (n, 3)`` mm, so that its dome descends
    ``excursion_mm`` relative to the apex (module docstring). :class:`InputError` naming ``name`` when the
    volume cannot produce that excursion; :class:`LungdeformError` when the split does not converge."""
    e_mm = check_excursion(excursion_mm)
    v, f = np.asarray(vertices, float), np.asarray(faces)
    w0 = check_feasible(v, f, e_mm, delta_ml, name)
    modes = np.stack([np.asarray(default_displacement, float), stretch_mode(v, f)])
    slopes = np.array([w0.excursion(m) for m in modes])  # Lagrangian excursion per unit weight
    tensors = volume_tensors(v, f, modes)
    measured = _measure(v, f, modes[0], w0.height_mm, name)

    def trial(goal: float):
        x = _on_volume(tensors, slopes, goal, delta_ml * MM3_PER_ML, name)
        u = np.tensordot(x, modes, axes=1)
        return _measure(v, f, u, w0.height_mm, name), x, u

    got, x, u, steps = _search(trial, e_mm)
    if abs(got - e_mm) > ACCEPT_MM:
        raise LungdeformError(f"{name}: the split for a dome excursion of {e_mm:g} mm did not converge in {steps} "
                              f"steps (nearest {got:.2f} mm)")
    _check_unfolded(v, f, u, modes[0], e_mm, name)
    return DomeSplit(np.ascontiguousarray(u), x, got, measured, steps)


def _search(trial, e_mm: float):
    """``(got, x, u, steps)``: the trial (``trial(goal) -> (measured mm, weights, displacement)``) whose measured
    excursion is nearest ``e_mm``. First fixed-point steps (each goal moved by what the last measurement
    missed); where the measurement jumps (faces entering and leaving the underside) and they do not settle
    within :data:`TOLERANCE_MM`, bisection between the nearest goals measured below and above."""
    seen = []  # (goal, got, x, u)
    goal = e_mm
    for _ in range(FIXED_STEPS):
        seen.append((goal, *trial(goal)))
        if abs(seen[-1][1] - e_mm) <= TOLERANCE_MM:
            return (*seen[-1][1:], len(seen))
        goal += e_mm - seen[-1][1]
    while len(seen) < MAX_STEPS:
        below = [t for t in seen if t[1] < e_mm]
        above = [t for t in seen if t[1] > e_mm]
        if not below or not above:  # not bracketed yet: step on past the target
            goal = seen[-1][0] + 2.0 * (e_mm - seen[-1][1])
        else:
            goal = 0.5 * (max(below, key=lambda t: t[1])[0] + min(above, key=lambda t: t[1])[0])
        seen.append((goal, *trial(goal)))
        if abs(seen[-1][1] - e_mm) <= TOLERANCE_MM:
            break
    best = min(seen, key=lambda t: abs(t[1] - e_mm))
    return (*best[1:], len(seen))


def _measure(v, f, u, height0: float, name: str) -> float:
    """The dome excursion (mm) of ``v + u`` from ``v`` whose apex-to-dome height is ``height0``."""
    return dome_weights(v + u, f, name=name).height_mm - height0


def _on_volume(tensors, slopes, goal: float, target_mm3: float, name: str) -> np.ndarray:
    """``(a, b)`` on the line ``slopes·(a, b) = goal`` whose volume change is ``target_mm3``: the root of the
    volume cubic along that line nearest ``a = 1`` (the default's displacement as calibrated)."""
    _, a1, a2, a3 = tensors
    if abs(slopes[1]) < 1e-12:
        raise LungdeformError(f"{name}: the head–foot stretch does not move the dome")
    x0 = np.array([0.0, goal / slopes[1]])
    q = np.array([1.0, -slopes[0] / slopes[1]])
    cubic = [np.einsum("ijk,i,j,k->", a3, q, q, q),
             q @ a2 @ q + 3.0 * np.einsum("ijk,i,j,k->", a3, x0, q, q),
             a1 @ q + 2.0 * x0 @ a2 @ q + 3.0 * np.einsum("ijk,i,j,k->", a3, x0, x0, q),
             a1 @ x0 + x0 @ a2 @ x0 + np.einsum("ijk,i,j,k->", a3, x0, x0, x0) - target_mm3]
    roots = np.roots(cubic)
    real = roots[np.abs(roots.imag) <= 1e-9 * max(1.0, float(np.abs(roots).max()))].real
    if len(real) == 0:
        raise InputError(f"{name}: no split of the breath gives that dome excursion at that volume")
    return x0 + real[np.argmin(np.abs(real - 1.0))] * q


def _check_unfolded(v, f, u, u_default, e_mm: float, name: str) -> None:
    """:class:`InputError` when the faces of ``v + u`` that have turned over cover :data:`FOLDED_SHARE` more of
    the area than those of ``v + u_default`` (the split folds the surface where the default does not; a
    decimated mesh's slivers may turn over under either)."""
    before = face_normals(v, f)
    area = face_areas(v, f)
    folded = [float(area[np.einsum("ij,ij->i", before, face_normals(v + w, f)) <= 0.0].sum()) for w in (u, u_default)]
    if folded[0] - folded[1] > FOLDED_SHARE * float(area.sum()):
        raise InputError(f"{name}: a dome excursion of {e_mm:g} mm folds the surface at this volume: the rest of the "
                         "lung cannot follow it; give a value nearer the default's")


@dataclass(frozen=True)
class DomeRequest:
    """What a build is told of the dome (``build``/``demo`` ``--dome-mm``, ``--breathing``).

    Attributes
    ----------
    mm : dict side → float or None
        Each lung's dome excursion over the breath, mm (a key ``"both"`` for every lung); None with ``share``.
    share : float or None
        ``κ`` of :data:`BREATHING` (``--breathing``): each lung's floor sweeps this share of its volume change.
    source : str
        Where the number came from, as the provenance records it.
    """

    mm: dict | None = None
    share: float | None = None
    source: str = "given"

    def __post_init__(self):
        if (self.mm is None) == (self.share is None):
            raise InputError("a dome request needs exactly one of mm and share")
        if self.mm is not None:
            object.__setattr__(self, "mm", {k: check_excursion(v, f"dome excursion ({k})") for k, v in self.mm.items()})
        elif not (math.isfinite(self.share) and 0.0 <= self.share < 1.0):
            raise InputError(f"the diaphragm's share of the breath must be in [0, 1), got {self.share!r}")

    @classmethod
    def breathing(cls, name: str) -> DomeRequest:
        """The shorthand ``name`` of :data:`BREATHING` (InputError listing them for another name)."""
        if name not in BREATHING:
            raise InputError(f"breathing must be one of {', '.join(BREATHING)}, got {name!r}")
        return cls(share=BREATHING[name], source=f"breathing {name} (the floor sweeps {BREATHING[name]:.0%} of the breath)")

    def per_lung(self, surfaces: dict, delta_ml: dict) -> dict:
        """``{side: mm}`` for the lungs ``surfaces`` (side → surface, mm LPS) whose volume changes over the breath
        are ``delta_ml`` (side → mL)."""
        if self.mm is None:
            return {s: self.share * delta_ml[s] * MM3_PER_ML / dome_weights(x.vertices, x.faces, name=x.name).footprint_mm2
                    for s, x in surfaces.items()}
        missing = [s for s in surfaces if s not in self.mm and "both" not in self.mm]
        if missing:
            raise InputError(f"no dome excursion given for the {missing[0]} lung (give it as {missing[0]}=MM)")
        return {s: self.mm.get(s, self.mm.get("both")) for s in surfaces}


def split_record(request: DomeRequest, asked: dict, lungs: dict) -> dict:
    """What a model's provenance records of a dome request: the excursion asked of each lung, where it came
    from, and the one measured on each built lung (``lungs``: side → a lung model with ``surface``,
    ``displacement``, ``calibration_ml``, ``unit_ml``)."""
    measured = {}
    for side, lung in lungs.items():
        rest = lung.surface
        moved = rest.vertices + lung.displacement * (lung.calibration_ml / lung.unit_ml)
        measured[side] = round(dome_weights(moved, rest.faces).height_mm
                               - dome_weights(rest.vertices, rest.faces).height_mm, 3)
    return {"source": request.source, "share": request.share, "asked_mm": {k: round(v, 3) for k, v in asked.items()},
            "measured_mm": measured, "definition": "lungdeform.geometry.dome (docs/DEFAULTS.md, Dome excursion)"}
