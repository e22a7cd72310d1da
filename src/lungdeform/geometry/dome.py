"""The diaphragm dome of a lung and its excursion relative to the apex (docs/DEFAULTS.md, "Dome excursion").

Heights are along +z of LPS (toward the head), mm. A face's **shadow** is its area projected on a
horizontal plane, ``|n_z|·area``. On a closed, outward lung surface:

- **underside**: the faces of the lower half of the lung's height whose outward normal points down
  (``n_z < 0``): where the lung rests on the diaphragm, seen from below;
- **dome height** ``h_d``: the mean height of the underside weighted by shadow, i.e. the mean height of
  the lung's floor over its footprint. Weighting by shadow makes it blind to the steps a binary mask
  leaves on a sloping wall (the treads of a staircase have the shadow of the slope they replace; the
  risers none) and to the choice of an angle where floor turns into wall (a steep wall has little
  shadow). A diaphragm that descends by δ everywhere lowers it by δ, and the volume it adds is
  ``δ × footprint``;
- **apex height** ``h_a``: the mean height, weighted by shadow, of the highest upward-facing faces whose
  shadows add up to :data:`APEX_SHARE` of the footprint (the last one counted in part);
- **apex-to-dome height** ``L = h_a − h_d``;
- **dome excursion** from a smaller-volume surface ``S0`` to a larger-volume surface ``S1`` of the same
  lung: ``E = L(S1) − L(S0)``, mm, positive when the dome descends relative to the apex (inspiration).
  A translation of either surface cancels (the unknown shift between two breath-hold scans). Scaling
  along the axes by ``(s_x, s_y, s_z)`` multiplies every shadow by ``s_x·s_y`` and keeps the order of
  heights, so the same faces are chosen and ``E = (s_z − 1)·L(S0)`` exactly.

(The highest point of the floor was tried first: on real masks the crest of a flattened COPD dome lies
where a chosen angle happens to cut the floor off, and it jumped between scans; the mean over the
footprint is stable. docs/DEFAULTS.md.)

Two readings of the same definition:

- :func:`dome_excursion` (Eulerian, what is measured): from two surfaces without correspondence (two
  masks); the underside of each is its own;
- :class:`DomeWeights` (Lagrangian): per-vertex weights on one surface, so that a displacement field
  ``u (n, 3)`` on it moves the dome relative to the apex by ``e(u) = Σ w_apex·u_z − Σ w_dome·u_z``, linear
  in ``u``. Both readings agree exactly for any scaling along the axes; where a motion also slides the
  floor sideways (a recess that opens) they differ, and a model asked for a measured excursion measures
  its own surface the Eulerian way (:mod:`lungdeform.model.dome`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungdeform.errors import InputError

from .mesh import as_vertices, face_normals

#: Share of the footprint (the underside's shadow) that the apex cap's shadow covers (3 %: about 5 cm² on
#: a lung whose footprint is 170 cm², a disc of ~13 mm radius).
APEX_SHARE = 0.03
#: Largest share of the apex cap's shadow, and of the underside's, that may lie on faces not measured
#: (crop faces) before the surface is refused.
CROP_SHARE_MAX = {"apex": 0.1, "dome": 0.25}


@dataclass(frozen=True)
class DomeWeights:
    """The apex cap and the underside of one surface as vertex weights (module docstring).

    Attributes
    ----------
    apex, dome : (n,) float
        Each sums to 1: the shadows of the apex cap's faces and of the underside's, shared among their
        corners (a third each).
    apex_height_mm, dome_height_mm : float
        ``h_a``, ``h_d`` of the surface, mm (+z LPS).
    footprint_mm2 : float
        The underside's shadow, mm².
    """

    apex: np.ndarray
    dome: np.ndarray
    apex_height_mm: float
    dome_height_mm: float
    footprint_mm2: float

    @property
    def height_mm(self) -> float:
        """``L = h_a − h_d``, mm."""
        return self.apex_height_mm - self.dome_height_mm

    def excursion(self, displacement) -> float:
        """``e(u)`` mm: how far ``displacement (n, 3)`` mm moves the dome down relative to the apex
        (Lagrangian: the faces of this surface followed)."""
        uz = np.asarray(displacement, float)[:, 2]
        return float(self.apex @ uz - self.dome @ uz)


def _cap(order: np.ndarray, shadow: np.ndarray, budget: float) -> np.ndarray:
    """``(m,) float``: the share of each face counted in the cap: faces in ``order`` (highest first)
    taken whole until their shadows reach ``budget`` mm², the last one in part."""
    share = np.zeros(len(shadow))
    cum = np.cumsum(shadow[order])
    whole = int(np.searchsorted(cum, budget))
    share[order[:whole]] = 1.0
    if whole < len(order):
        rest = budget - (cum[whole - 1] if whole else 0.0)
        share[order[whole]] = rest / shadow[order[whole]] if shadow[order[whole]] > 0 else 0.0
    return share


def underside(vertices, faces) -> np.ndarray:
    """``(m,) float`` mm²: each face's shadow if it belongs to the underside (module docstring), else 0."""
    v = as_vertices(vertices)
    f = np.asarray(faces)
    nz = face_normals(v, f, normalize=False)[:, 2] / 2.0  # signed shadow, mm²
    z = v[f].mean(axis=1)[:, 2]
    lo, hi = float(v[:, 2].min()), float(v[:, 2].max())
    return np.where(z <= 0.5 * (lo + hi), np.maximum(-nz, 0.0), 0.0)


def dome_weights(vertices, faces, keep=None, *, name: str = "surface") -> DomeWeights:
    """:class:`DomeWeights` of a closed outward surface ``vertices (n, 3)`` mm LPS, ``faces (m, 3)``.

    ``keep (n,) bool``: the vertices measured (False: on a crop face, not lung surface). An apex cap or an
    underside more than :data:`CROP_SHARE_MAX` (by shadow) on faces with a vertex not kept is refused
    (:class:`InputError` naming ``name``): the scan cut the apex or the dome off, so its height is
    unknown. Below that share the cut faces count at their height: the lung reached at least that far
    (on COPDgene case 1, inspiration, left lung, the field of view cuts the lowest 13 % of the floor).
    """
    v = as_vertices(vertices)
    f = np.asarray(faces)
    nz = face_normals(v, f, normalize=False)[:, 2] / 2.0  # signed shadow, mm²
    z = v[f].mean(axis=1)[:, 2]  # face centroid heights, mm
    under = underside(v, f)
    footprint = float(under.sum())
    up = np.maximum(nz, 0.0)
    if not footprint > 0 or not up.sum() > 0:
        raise InputError(f"{name}: no underside or no top (a flat or open surface?): no dome to measure")
    apex = _cap(np.argsort(-z), up, APEX_SHARE * footprint) * up
    if keep is not None:
        cut = ~np.all(np.asarray(keep, bool)[f], axis=1)
        for what, shadow in (("apex", apex), ("dome", under)):
            if shadow[cut].sum() > CROP_SHARE_MAX[what] * shadow.sum():
                raise InputError(f"{name}: the {what} lies on a crop face (the scan cut it off): its height, and the "
                                 "dome excursion, cannot be measured")
    out = []
    for shadow in (apex, under):
        wf = shadow / float(shadow.sum())
        out.append(np.bincount(f.ravel(), weights=np.repeat(wf / 3.0, 3), minlength=len(v)))
    return DomeWeights(out[0], out[1], float(out[0] @ v[:, 2]), float(out[1] @ v[:, 2]), footprint)


def dome_excursion(smaller, larger, *, keep_smaller=None, keep_larger=None) -> float:
    """``E = L(larger) − L(smaller)`` mm (module docstring): how far the dome descends relative to the apex
    from the surface ``smaller`` to ``larger`` (each with ``vertices``, ``faces`` and ``name``, mm LPS, no
    correspondence needed); ``keep_*``: the vertices measured on each (crop faces not)."""
    a = dome_weights(smaller.vertices, smaller.faces, keep_smaller, name=smaller.name)
    b = dome_weights(larger.vertices, larger.faces, keep_larger, name=larger.name)
    return b.height_mm - a.height_mm
