"""A full breathing cycle as fit inputs: a 4-D CT's phases ordered, its hysteresis measured, its
alignment chosen (docs/FITTING.md, "4-D CT input").

The model is a function of lung volume only, so the phases of one 4-D CT are fitted in the order
of their volume (:func:`volume_order`: the smallest, end-exhale, first; equal volumes allowed, ties
kept in phase order): an inhale and an exhale phase of equal volume are two targets at one volume,
and the fit averages the two branches there. What that average leaves out is measured, not
modelled: :func:`hysteresis` pairs each exhale-branch phase with the inhale-branch phase of the
most similar volume (:func:`branches`, from the phase order) and gives their surface distance.

Alignment (:func:`choose_alignment`): phases that share one DICOM Frame of Reference
(FrameOfReferenceUID, :func:`lungdeform.io.dicom.fourdct.frame_of_reference`) are in one patient frame already, so no rigid
alignment is fitted unless asked; otherwise the apex alignment.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.distance import SurfaceDistance, distance_stats
from lungdeform.geometry.mesh import Surface

#: ``align`` of :class:`lungdeform.fit.config.FitConfig` that lets :func:`choose_alignment` decide.
AUTO = "auto"


def volume_order(keys, volumes_ml) -> list[int]:
    """Indices of phases ``keys : (n,) float`` (phase order) with ``volumes_ml : (n,) float`` mL,
    sorted by volume (smallest first); equal volumes keep their phase order."""
    return sorted(range(len(volumes_ml)), key=lambda i: (float(volumes_ml[i]), float(keys[i])))


def branches(volumes_ml) -> tuple[list[int], list[int]]:
    """``(inhale, exhale)`` indices of phases given in phase order (``volumes_ml : (n,)`` mL, one
    cycle, cyclic): inhale runs from the smallest volume (end-exhale) forward to the largest
    (end-inhale), both ends included; exhale is the rest, from after end-inhale back to before
    end-exhale."""
    v = np.asarray(volumes_ml, float)
    n = len(v)
    if n < 2:
        raise InputError(f"volumes_ml: a cycle needs two or more phases, got {n}")
    e, m = int(np.argmin(v)), int(np.argmax(v))
    inhale = [(e + k) % n for k in range((m - e) % n + 1)]
    exhale = [(m + k) % n for k in range(1, (e - m) % n)]
    return inhale, exhale


@dataclass(frozen=True)
class HysteresisPair:
    """One exhale-branch phase against the inhale-branch phase of the most similar volume.

    Attributes
    ----------
    exhale, inhale : str
        The two phases' labels.
    exhale_ml, inhale_ml : float
        Their volumes (mL).
    mean_mm, p95_mm, max_mm : float
        Symmetric surface distance between them (every vertex of each to the other surface), mm.
    """

    exhale: str
    inhale: str
    exhale_ml: float
    inhale_ml: float
    mean_mm: float
    p95_mm: float
    max_mm: float

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        return (f"exhale {self.exhale} ({self.exhale_ml:.1f} mL) vs inhale {self.inhale} ({self.inhale_ml:.1f} mL): "
                f"mean {self.mean_mm:.2f} mm, 95th percentile {self.p95_mm:.2f} mm")


def surface_gap(a: Surface, b: Surface):
    """:class:`~lungdeform.geometry.distance.DistanceStats` (mm) of the symmetric distance between
    surfaces ``a`` and ``b`` (same frame, mm): every vertex of each to the other surface."""
    d = np.concatenate([SurfaceDistance(b.vertices, b.faces).distance(a.vertices),
                        SurfaceDistance(a.vertices, a.faces).distance(b.vertices)])
    return distance_stats(d)


def hysteresis(labels, surfaces, volumes_ml) -> list[HysteresisPair]:
    """Each exhale-branch phase against the inhale-branch phase of the most similar volume
    (:func:`branches`); ``labels``, ``surfaces`` (one frame, mm) and ``volumes_ml`` (mL) per phase,
    in phase order. Empty when no phase lies on the exhale branch (a monotone series)."""
    inhale, exhale = branches(volumes_ml)
    v = np.asarray(volumes_ml, float)
    pairs = []
    for j in exhale:
        i = min(inhale, key=lambda k: (abs(v[k] - v[j]), k))
        s = surface_gap(surfaces[j], surfaces[i])
        pairs.append(HysteresisPair(str(labels[j]), str(labels[i]), float(v[j]), float(v[i]),
                                    float(s.mean), float(s.p95), float(s.max)))
    return pairs


def choose_alignment(asked: str, frame_uid: str | None) -> tuple[str, str]:
    """``(align, why)``: ``asked`` unless it is :data:`AUTO`; then ``"none"`` when the inputs share
    the Frame of Reference ``frame_uid`` (one patient frame: nothing to align), else ``"apex"``."""
    if asked != AUTO:
        return asked, "asked (--align)"
    if frame_uid:
        return "none", f"every phase shares one DICOM Frame of Reference ({frame_uid}); no alignment fitted"
    return "apex", "the inputs share no DICOM Frame of Reference; rigid alignment on the apex cap"
