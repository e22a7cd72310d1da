"""Per-unit-volume displacement and real-time playback (paper eq. (1), Sec. V; METHOD §7).

Velocity ``D'[i] = F[i]/M[i]`` with ``M = 1``, so the displacement for one unit of volume is
``u_i = k·F[i]·d_i``. The enclosed volume of ``p + s·u`` is exactly a cubic polynomial in ``s``
(each triangle's signed volume is trilinear in its corners), so ``k`` is chosen by solving that cubic:
the surface at ``s = calibration_ml / unit_ml`` units encloses exactly ``V_EE + calibration_ml``.
At volume V the surface is ``x = p + s·u`` with ``s = (V − V_EE)/ΔV`` (the paper's linear reading);
:func:`scale_for_volume` inverts the cubic for an exact volume instead. Stepping by one unit is
``x ← x + u``: three additions per vertex.
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.mesh import as_vertices


def _det(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, np.cross(b, c))


def volume_polynomial(vertices: np.ndarray, faces: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """``a : (4,) float``, mm³: the enclosed volume of ``vertices + s·displacement`` is
    ``a[0] + a[1]·s + a[2]·s² + a[3]·s³`` exactly (divergence theorem, per-face trilinearity).

    ``vertices, displacement : (n, 3) float`` mm; ``faces : (m, 3) int`` outward.
    """
    p = as_vertices(vertices)
    u = as_vertices(displacement, "displacement")
    p = p - p.mean(axis=0)  # translation-invariant for closed surfaces; limits cancellation
    pa, pb, pc = (p[faces[:, k]] for k in range(3))
    ua, ub, uc = (u[faces[:, k]] for k in range(3))
    a0 = _det(pa, pb, pc).sum()
    a1 = (_det(ua, pb, pc) + _det(pa, ub, pc) + _det(pa, pb, uc)).sum()
    a2 = (_det(ua, ub, pc) + _det(ua, pb, uc) + _det(pa, ub, uc)).sum()
    a3 = _det(ua, ub, uc).sum()
    return np.array([a0, a1, a2, a3]) / 6.0


def smallest_positive_root(coeffs: np.ndarray, target: float) -> float:
    """Smallest real ``s > 0`` with ``c1·s + c2·s² + c3·s³ = target`` (``coeffs`` = a0…a3; a0 ignored)."""
    _, c1, c2, c3 = coeffs
    roots = np.roots([c3, c2, c1, -target]) if abs(c3) > 0 or abs(c2) > 0 else np.array([target / c1])
    real = roots[np.abs(roots.imag) <= 1e-9 * max(1.0, np.abs(roots).max())].real
    pos = real[real > 0]
    if len(pos) == 0:
        raise LungdeformError("no positive scale reaches the requested volume: the displacement does not grow the lung")
    return float(pos.min())


def calibrate(
    vertices: np.ndarray,
    faces: np.ndarray,
    raw: np.ndarray,
    *,
    calibration_ml: float = 500.0,
    unit_ml: float = 1.0,
) -> np.ndarray:
    """Scale a raw displacement field into mm per ``unit_ml`` of volume, exactly at ``calibration_ml``.

    Parameters
    ----------
    vertices : (n, 3) float
        End-exhale positions p, mm.
    faces : (m, 3) int
    raw : (n, 3) float
        ``F[i]·d_i`` (any scale).
    calibration_ml : float
        The volume change (mL) at which the volume is made exact (the tidal volume).
    unit_ml : float
        ΔV, the volume of one unit (mL).

    Returns
    -------
    u : (n, 3) float
        mm per unit, such that ``V(p + (calibration_ml/unit_ml)·u) = V(p) + calibration_ml`` exactly.
    """
    if not (calibration_ml > 0 and unit_ml > 0):
        raise InputError("calibration_ml and unit_ml must be > 0 mL")
    coeffs = volume_polynomial(vertices, faces, raw)
    if not coeffs[1] > 0:
        raise LungdeformError(
            "the displacement field shrinks or does not change the volume to first order "
            f"(dV/ds = {coeffs[1]:.3g} mm³): check the surface orientation and the force"
        )
    k = smallest_positive_root(coeffs, calibration_ml * 1000.0)  # mm³
    units = calibration_ml / unit_ml
    return np.ascontiguousarray(raw * (k / units))


def scale_for_volume(volume_poly: np.ndarray, delta_ml: float) -> float:
    """Exact number of units ``s`` that grows the volume by ``delta_ml`` (mL ≥ 0), given
    ``volume_poly`` = :func:`volume_polynomial` of the calibrated per-unit displacement."""
    if delta_ml == 0:
        return 0.0
    if delta_ml < 0:
        _, c1, c2, c3 = volume_poly
        roots = np.roots([c3, c2, c1, -delta_ml * 1000.0])
        real = roots[np.abs(roots.imag) <= 1e-9 * max(1.0, np.abs(roots).max())].real
        neg = real[real < 0]
        if len(neg) == 0:
            raise LungdeformError(f"no scale shrinks the lung by {-delta_ml} mL")
        return float(neg.max())
    return smallest_positive_root(volume_poly, delta_ml * 1000.0)


class Playback:
    """Real-time playback of ``x = p + s·u``: buffers allocated once, no allocation per frame.

    Parameters
    ----------
    rest : (n, 3) float
        End-exhale positions p, mm.
    displacement : (n, 3) float
        u, mm per unit volume.
    dtype : numpy dtype
        Storage of the frame buffer (float32 halves the bytes per frame, as a GPU would use).

    Attributes
    ----------
    positions : (n, 3) array
        The current frame, updated in place.
    """

    def __init__(self, rest: np.ndarray, displacement: np.ndarray, dtype=np.float64):
        p = as_vertices(rest, "rest")
        u = as_vertices(displacement, "displacement")
        if p.shape != u.shape:
            raise InputError(f"rest {p.shape} and displacement {u.shape} must have the same shape")
        self.rest = p.astype(dtype)
        self.unit = u.astype(dtype)
        self.positions = self.rest.copy()
        self._step = self.unit.copy()
        self.scale = 0.0
        self._step_units = 1.0

    def set_step(self, units: float) -> None:
        """Precompute the per-step increment ``units · u`` (once per breathing rate change)."""
        np.multiply(self.unit, units, out=self._step)
        self._step_units = float(units)

    def step(self) -> np.ndarray:
        """``x ← x + Δs·u`` in place (three additions per vertex); returns :attr:`positions`."""
        np.add(self.positions, self._step, out=self.positions)
        self.scale += self._step_units
        return self.positions

    def seek(self, scale: float) -> np.ndarray:
        """``x = p + s·u`` in place for any ``s`` (units of volume above end-exhale)."""
        np.multiply(self.unit, scale, out=self.positions)
        np.add(self.positions, self.rest, out=self.positions)
        self.scale = float(scale)
        return self.positions
