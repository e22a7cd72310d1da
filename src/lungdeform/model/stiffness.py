"""Stiffness (Young's modulus) fields over the mass nodes (paper Sec. III-E; docs/METHOD_NOTES.md §2).

The model only uses ratios of moduli, so units are relative (1 = the reference tissue). Every field
here returns ``E : (n,) float`` per mass node (mesh vertex), strictly positive. Spring nodes take
the mean of their two mass nodes (:func:`node_moduli`).
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import as_vertices


def uniform(n: int, modulus: float = 1.0) -> np.ndarray:
    """``E : (n,) float``, the same modulus everywhere."""
    _check_positive(modulus, "modulus")
    return np.full(int(n), float(modulus))


def gravity_gradient(
    vertices: np.ndarray,
    gravity: np.ndarray,
    dependent: float = 1.0,
    nondependent: float = 1.0,
) -> np.ndarray:
    """``E : (n,) float`` varying linearly with height along gravity.

    ``dependent`` is the modulus at the lowest point (along ``gravity``), ``nondependent`` at the
    highest, linear in between. ``vertices : (n, 3) float`` mm; ``gravity : (3,) float`` any length,
    same frame as the vertices (LPS: supine gravity is ``(0, 1, 0)``).
    """
    v = as_vertices(vertices)
    g = np.asarray(gravity, dtype=float)
    if g.shape != (3,) or not np.linalg.norm(g) > 0:
        raise InputError(f"gravity must be a non-zero (3,) vector, got {gravity!r}")
    _check_positive(dependent, "dependent")
    _check_positive(nondependent, "nondependent")
    depth = v @ (g / np.linalg.norm(g))
    span = np.ptp(depth)
    t = (depth - depth.min()) / span if span > 0 else np.zeros(len(v))
    return nondependent + t * (dependent - nondependent)


def sphere_override(
    moduli: np.ndarray,
    vertices: np.ndarray,
    center: np.ndarray,
    radius: float,
    modulus: float,
) -> np.ndarray:
    """A copy of ``moduli : (n,) float`` with ``modulus`` inside a sphere (a stiff or soft tumour).

    ``vertices : (n, 3) float`` mm; ``center : (3,) float`` mm, same frame; ``radius`` mm.
    """
    e = as_moduli(moduli, len(vertices))
    _check_positive(modulus, "modulus")
    inside = np.linalg.norm(as_vertices(vertices) - np.asarray(center, float), axis=1) <= radius
    out = e.copy()
    out[inside] = modulus
    return out


def as_moduli(moduli, n: int, name: str = "stiffness") -> np.ndarray:
    """Validate a per-vertex array: ``(n,) float``, finite and > 0."""
    e = np.ascontiguousarray(moduli, dtype=np.float64)
    if e.shape != (n,):
        raise InputError(f"{name} must have shape ({n},) (one modulus per vertex), got {e.shape}")
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise InputError(f"{name} must be finite and > 0 everywhere")
    return e


def node_moduli(mass_moduli: np.ndarray, spring_ends: np.ndarray) -> np.ndarray:
    """``E : (N,) float`` over all graph nodes: mass nodes, then spring nodes (mean of their ends)."""
    e = np.asarray(mass_moduli, dtype=float)
    return np.concatenate([e, 0.5 * (e[spring_ends[:, 0]] + e[spring_ends[:, 1]])])


def _check_positive(value: float, name: str) -> None:
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a finite modulus > 0, got {value!r}")


def parse_stiffness(spec: str, vertices, gravity) -> np.ndarray | None:
    """Per-vertex moduli ``(n,) float`` of a lung with ``vertices : (n, 3)`` mm LPS from a text ``spec``:
    ``uniform`` (None), ``gradient:DEPENDENT,NONDEPENDENT`` (:func:`gravity_gradient` along the unit
    ``gravity`` vector) or ``sphere:X,Y,Z,RADIUS,E`` (mm, LPS; :func:`sphere_override`)."""

    kind, _, args = spec.partition(":")
    kind = kind.strip().lower()
    if kind == "uniform" and not args:
        return None
    if kind == "gradient":
        vals = _floats(args)
        if vals is None or len(vals) != 2:
            raise InputError("stiffness gradient needs DEPENDENT,NONDEPENDENT moduli, e.g. gradient:0.5,1.5")
        return gravity_gradient(vertices, gravity, *vals)
    if kind == "sphere":
        nums = _floats(args)
        if nums is None or len(nums) != 5:
            raise InputError("stiffness sphere needs X,Y,Z,RADIUS,E (mm, LPS; relative modulus)")
        return sphere_override(uniform(len(vertices)), vertices, nums[:3], nums[3], nums[4])
    raise InputError(f"stiffness must be uniform, gradient:D,N or sphere:X,Y,Z,R,E, got {spec!r}")


def _floats(text: str):
    try:
        return [float(x) for x in text.split(",")] if text else []
    except ValueError:
        return None
