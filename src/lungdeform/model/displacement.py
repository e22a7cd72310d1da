"""Per-unit-volume displacement, its exact volume, and real-time playback (paper eq. (1), Sec. V).

Velocity ``D'[i] = F[i]/M[i]`` with ``M = 1``, so the displacement for one unit of volume is
``u_i = k·F[i]·d_i``. The enclosed volume of ``p + s·u`` is exactly a cubic polynomial in ``s``
(each triangle's signed volume is trilinear in its corners), so ``k`` is chosen by solving that cubic:
the surface at ``s = calibration_ml / unit_ml`` units encloses exactly ``V_EE + calibration_ml``.
At volume V the surface is ``x = p + s·u`` with ``s = (V − V_EE)/ΔV`` (the paper's linear reading);
:func:`scale_for_volume` inverts the cubic for an exact volume instead. Stepping by one unit is
``x ← x + u``: three additions per vertex.

Units. Every volume a function here takes or returns is in **mL** (``delta_ml``, ``calibration_ml``,
``volume_ml``); the coefficient arrays of the volume cubics (:func:`volume_polynomial`,
:func:`volume_tensors`, ``LungModel.volume_poly``) are in **mm³** (per power of the scale), as the
surfaces are in mm and as the glb extras carry them. mL ↔ mm³ happens in one place per direction
(:data:`MM3_PER_ML`): the root finders convert the volume asked for, :func:`volume_change_ml` and
:func:`enclosed_volume_ml` convert the volume found.

Morph targets (the glb exporter, :mod:`lungdeform.playback.export`): target 0 is the displacement at
the calibration volume, ``(calibration_ml/unit_ml)·u`` (:func:`tidal_displacement`); targets 1–4 the
force-basis fields scaled by one least-squares factor κ (:func:`morph_targets`); the volume of
``p + Σ_k w_k·T_k`` is a cubic form in ``w`` (:func:`volume_tensors`), restricted to one direction
``w`` by :func:`cubic_along`.
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.mesh import as_vertices, signed_volume

#: 1 mL = 1000 mm³ (the one mL ↔ mm³ conversion of the module).
MM3_PER_ML = 1000.0


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


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """Sum of the row dot products of two (m, 3) arrays."""
    return float(np.einsum("ij,ij->", a, b))


def volume_tensors(vertices: np.ndarray, faces: np.ndarray, targets: np.ndarray):
    """Exact volume of ``vertices + Σ_k w_k · targets[k]`` as a cubic form in ``w``.

    Parameters
    ----------
    vertices : (n, 3) float, mm; faces : (m, 3) int, outward; targets : (K, n, 3) float, mm.

    Returns
    -------
    a0 : float, mm³; a1 : (K,); a2 : (K, K) symmetric; a3 : (K, K, K) symmetric, mm³, with
    ``V(w) = a0 + a1·w + wᵀ a2 w + a3(w, w, w)`` (same face trilinearity as
    :func:`volume_polynomial`).
    """
    p = vertices - vertices.mean(axis=0)
    pa, pb, pc = (p[faces[:, c]] for c in range(3))
    u = [[t[faces[:, c]] for c in range(3)] for t in targets]  # u[k][corner] : (m, 3)
    kk = len(targets)
    a0 = _dot(pa, np.cross(pb, pc)) / 6.0
    a1 = np.array([_dot(u[k][0], np.cross(pb, pc)) + _dot(pa, np.cross(u[k][1], pc))
                   + _dot(pa, np.cross(pb, u[k][2])) for k in range(kk)]) / 6.0
    a2 = np.zeros((kk, kk))
    a3 = np.zeros((kk, kk, kk))
    for j in range(kk):
        for k in range(kk):
            bc = np.cross(u[j][1], u[k][2])
            a2[j, k] = (_dot(u[j][0], np.cross(u[k][1], pc)) + _dot(u[j][0], np.cross(pb, u[k][2]))
                        + _dot(pa, bc)) / 6.0
            for i in range(kk):
                a3[i, j, k] = _dot(u[i][0], bc) / 6.0
    a2 = 0.5 * (a2 + a2.T)
    a3 = sum(np.transpose(a3, perm) for perm in
             ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))) / 6.0
    return a0, a1, a2, a3


def cubic_along(a1: np.ndarray, a2: np.ndarray, a3: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``(4,) float`` mm³: the volume cubic of :func:`volume_tensors` along one direction ``w : (K,)``,
    ``V(λ·w) − a0 = (a1·w) λ + (wᵀ a2 w) λ² + a3(w, w, w) λ³`` (constant term 0)."""
    return np.array([0.0, float(a1 @ w), float(w @ a2 @ w), float(np.einsum("ijk,i,j,k->", a3, w, w, w))])


def cubic_in_weight(volume_poly: np.ndarray, units: float) -> np.ndarray:
    """``(4,) float`` mm³: the cubic ``volume_poly`` in ``s`` rewritten in the weight ``λ = s/units``."""
    return volume_poly * units ** np.arange(4)


def _real_roots(coeffs: np.ndarray, target_mm3: float) -> np.ndarray:
    _, c1, c2, c3 = coeffs
    roots = np.roots([c3, c2, c1, -target_mm3])
    return roots[np.abs(roots.imag) <= 1e-9 * max(1.0, np.abs(roots).max())].real


def _smallest_positive_root(coeffs: np.ndarray, target_mm3: float) -> float:
    """Smallest real ``s > 0`` with ``c1·s + c2·s² + c3·s³ = target_mm3`` (``coeffs`` = a0…a3 mm³; a0 ignored)."""
    _, c1, c2, c3 = coeffs
    real = _real_roots(coeffs, target_mm3) if abs(c3) > 0 or abs(c2) > 0 else np.array([target_mm3 / c1])
    pos = real[real > 0]
    if len(pos) == 0:
        raise LungdeformError("no positive scale reaches the requested volume: the displacement does not grow the lung")
    return float(pos.min())


def scale_for_volume(volume_poly: np.ndarray, delta_ml: float) -> float:
    """Exact scale ``s`` with ``V(s) − V(0) = delta_ml`` (mL, either sign): the root of the cubic
    nearest 0 on the side of ``delta_ml``. ``volume_poly : (4,) float`` mm³, the cubic in ``s`` of
    :func:`volume_polynomial` (of the calibrated per-unit displacement: ``s`` in units), of
    :func:`cubic_in_weight` or of :func:`cubic_along`. Raises :class:`LungdeformError` when no such
    root exists (the displacement does not grow, or cannot shrink, the lung by that much)."""
    if delta_ml == 0:
        return 0.0
    target_mm3 = delta_ml * MM3_PER_ML
    if delta_ml < 0:
        real = _real_roots(volume_poly, target_mm3)
        neg = real[real < 0]
        if len(neg) == 0:
            raise LungdeformError(f"no scale shrinks the lung by {-delta_ml} mL")
        return float(neg.max())
    return _smallest_positive_root(volume_poly, target_mm3)


def scales_for_volumes(volume_poly: np.ndarray, delta_ml) -> np.ndarray:
    """``s : (k,) float``, :func:`scale_for_volume` for each of ``delta_ml : (k,) float`` mL."""
    return np.array([scale_for_volume(volume_poly, float(d)) for d in np.asarray(delta_ml, float)])


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
    k = scale_for_volume(coeffs, calibration_ml)
    units = calibration_units(calibration_ml, unit_ml)
    return np.ascontiguousarray(raw * (k / units))


def volume_change_ml(volume_poly: np.ndarray, s) -> np.ndarray:
    """``V(s) − V(0)`` mL for scales ``s`` (float or (k,)), from the cubic ``volume_poly : (4,)`` mm³."""
    _, c1, c2, c3 = volume_poly
    return (c1 * s + c2 * s ** 2 + c3 * s ** 3) / MM3_PER_ML


def enclosed_volume_ml(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume (mL) enclosed by ``vertices : (n, 3) float`` mm, ``faces : (m, 3) int`` outward: the
    measurement that the cubics predict (divergence theorem)."""
    return signed_volume(vertices, faces) / MM3_PER_ML


def calibration_units(calibration_ml: float, unit_ml: float):
    """Units of volume in the calibration volume: ``calibration_ml / unit_ml`` (both mL)."""
    return calibration_ml / unit_ml


def tidal_displacement(displacement: np.ndarray, units) -> np.ndarray:
    """Morph target 0 (``tidal``), mm: the per-unit displacement (mm per unit) times ``units``
    (:func:`calibration_units`), i.e. the displacement at the calibration volume (weight 1)."""
    return displacement * units


def morph_targets(displacement: np.ndarray, basis_displacement: np.ndarray, force_weights: np.ndarray,
                  units: float) -> tuple[np.ndarray, float]:
    """``(targets (5, n, 3) float mm, κ)``: target 0 the :func:`tidal_displacement`, targets 1–4
    ``κ · basis_displacement``, with κ the least-squares factor that makes
    ``Σ_k force_weights[k] · targets[1 + k] = targets[0]`` (1 when the basis is zero).

    displacement : (n, 3) mm per unit; basis_displacement : (4, n, 3) ``F_k · d`` per force field
    (unscaled); force_weights : (4,) the weights of the model's gravity; units : calibration units.
    """
    tidal = tidal_displacement(displacement, units)
    raw = np.tensordot(force_weights, basis_displacement, axes=1)
    denom = float(np.einsum("ij,ij->", raw, raw))
    kappa = float(np.einsum("ij,ij->", raw, tidal)) / denom if denom > 0 else 1.0
    return np.concatenate([tidal[None], kappa * basis_displacement]), kappa


def positions_at(rest: np.ndarray, displacement: np.ndarray, scales) -> np.ndarray:
    """``x = p + s·u`` mm for scales of any shape: ``rest, displacement : (..., n, 3)`` mm (per unit),
    ``scales : (..., n)`` broadcasting against them."""
    return rest + np.asarray(scales)[..., None] * displacement


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
