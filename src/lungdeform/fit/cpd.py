"""Coherent Point Drift, deformable (Myronenko & Song 2010): ``pycpd``'s iteration, without its waste.

``pycpd.DeformableRegistration`` (MIT) forms ``diag(P1) @ G`` as a dense ``(M, M)`` matrix product
(O(M³) per iteration, as much as the solve itself), computes ``P @ X`` twice per iteration and
builds ``(M, N, D)`` and ``(M, M, D)`` temporaries for the squared distances (the first variance,
the kernel ``G`` and every E-step). :func:`deformable_cpd` runs the same EM iteration (same start,
same updates, same stopping rule) with a row scaling, one ``P @ X``, the first variance in closed
form and :func:`scipy.spatial.distance.cdist`: the same weights to rounding, in about half the time
at ``M = N = 1500`` (the baselines and the correspondence field of :mod:`lungdeform.fit.registration`).

With ``rank_tolerance`` the M-step's ``(M, M)`` solve of ``(diag(P1) G + α σ² I) W = B`` goes
through a low-rank factor of the kernel instead (it is fixed over the iterations): ``G ≈ L Lᵀ`` by
LAPACK's pivoted Cholesky (``dpstrf``, stopped where every remaining diagonal entry of ``G − L Lᵀ``
is below ``rank_tolerance``; ``G``'s diagonal is 1), then Woodbury's identity
``W = (B − D L (α σ² I + Lᵀ D L)⁻¹ Lᵀ B) / (α σ²)`` with ``D = diag(P1)``: an ``(r, r)`` solve per
iteration instead of an ``(M, M)`` LU. A Gaussian kernel of width comparable to the shape has few
eigenvalues above that tolerance (the correspondence field's, on DIR-Lab COPDgene case 1, left
lung: rank 356 of 1500 at 10⁻¹⁰); its points end within 10⁻⁸ mm of the dense solve's there.
The E-step never forms ``P``: the posteriors ``p_mn = exp(−a_mn) / (Σ_m exp(−a_mn) + c)``,
``a_mn = |x_n − Ty_m|² / (2σ²)``, are computed as ``exp(−(a_mn − a_n)) / (Σ_m exp(−(a_mn − a_n)) +
c exp(a_n))`` with ``a_n = min_m a_mn`` (equal in exact arithmetic, within rounding in floating point),
and ``P1``, ``P X`` come from one product of the unnormalised matrix with ``[1, X] / column sums``. Unshifted, as
σ² shrinks most entries of ``exp(−a)`` underflow to 0 or to subnormal numbers, where NumPy's ``exp``
and the BLAS take 10–40 times longer per entry (measured on COPDgene case 1's left lung: the E-step
of the last iterations, σ² ≈ 10⁻³, took 3–5 times its first one); shifted, every column holds a 1 and
the exponents are capped at :data:`SHIFTED_FLOOR` (nothing subnormal, a change far below rounding).
``pycpd`` is a required dependency (pyproject.toml).
"""

from __future__ import annotations

import numpy as np
import pycpd
from pycpd.emregistration import EMRegistration
from scipy.linalg import blas as blas_lib
from scipy.linalg import lapack
from scipy.spatial.distance import cdist

from lungdeform import blas
from lungdeform.errors import InputError

#: The E-step's shifted exponents ``a_mn − min_m a_mn`` are capped here: ``exp(−700) ≈ 1e−304``, at
#: most ``M · 1e−304`` of a column sum that is at least 1, so the cap changes ``P`` by nothing a
#: float64 can hold, and no weight is subnormal (module docstring).
SHIFTED_FLOOR = 700.0


def first_variance(x: np.ndarray, y: np.ndarray) -> float:
    """pycpd's starting ``σ² = Σ_mn |x_n − y_m|² / (D M N)`` for ``x : (N, D)``, ``y : (M, D)``, in closed form
    (``Σ_mn |x_n − y_m|² = M Σ|x|² + N Σ|y|² − 2 (Σx)·(Σy)``, no ``(M, N, D)`` temporary)."""
    (n, d), m = x.shape, len(y)
    total = m * np.sum(x * x) + n * np.sum(y * y) - 2.0 * float(x.sum(axis=0) @ y.sum(axis=0))
    return float(total / (d * m * n))


def kernel_factor(g: np.ndarray, tolerance: float) -> np.ndarray:
    """``L : (M, r)`` with ``g ≈ L Lᵀ`` for a positive semi-definite ``g : (M, M)``: LAPACK's pivoted
    Cholesky (``dpstrf``), stopped once every remaining diagonal entry of ``g − L Lᵀ`` is below
    ``tolerance`` (same unit as ``g``'s diagonal)."""
    c, piv, rank, info = lapack.dpstrf(g, tol=float(tolerance), lower=1)
    if info < 0:
        raise InputError(f"the kernel's pivoted Cholesky failed (LAPACK dpstrf info {info})")
    out = np.zeros((len(g), int(rank)))
    out[piv - 1] = np.tril(c[:, :int(rank)])
    return out


class FastDeformable(pycpd.DeformableRegistration):
    """``pycpd.DeformableRegistration`` with the cheaper start, E-step, transform update and variance
    (module docstring); ``rank_tolerance`` (None: the dense solve) selects the low-rank M-step."""

    def __init__(self, *, X, Y, alpha, beta, w, max_iterations, tolerance, rank_tolerance=None):
        EMRegistration.__init__(self, X=X, Y=Y, sigma2=first_variance(X, Y), max_iterations=max_iterations,
                                tolerance=tolerance, w=w)
        if not (alpha > 0 and beta > 0):
            raise InputError(f"CPD needs alpha > 0 and beta > 0, got {alpha!r}, {beta!r}")
        self.alpha, self.beta = float(alpha), float(beta)
        self.P = None  # never formed (module docstring)
        self.W = np.zeros((self.M, self.D))
        self.G = np.exp(cdist(Y, Y, "sqeuclidean") / (-2.0 * self.beta ** 2))  # pycpd's gaussian_kernel
        self._factor = None if rank_tolerance is None else kernel_factor(self.G, rank_tolerance)

    def expectation(self):
        # a_mn = |x_n − Ty_m|² / (2σ²) from the scaled points; per column, exp(−(a − min_m a)) floored at
        # exp(−SHIFTED_FLOOR): the same P (module docstring), no column underflows, no entry is subnormal
        f = 1.0 / np.sqrt(2.0 * self.sigma2)
        p = cdist(self.TY * f, self.X * f, "sqeuclidean")  # (M, N)
        low = p.min(axis=0)
        np.subtract(low, p, out=p)
        np.maximum(p, -SHIFTED_FLOOR, out=p)
        np.exp(p, out=p)
        c = (2 * np.pi * self.sigma2) ** (self.D / 2) * self.w / (1 - self.w) * self.M / self.N
        column = p.sum(axis=0)
        inv = 1.0 / (column + c * np.exp(np.minimum(low, SHIFTED_FLOOR)))  # column >= 1: its nearest is exp(0)
        rhs = np.empty((self.N, self.D + 1))
        rhs[:, 0] = inv
        np.multiply(self.X, inv[:, None], out=rhs[:, 1:])
        both = p @ rhs  # P1 and P @ X in one pass over the (M, N) matrix; P itself is never formed
        self.P1, self._px = both[:, 0], np.ascontiguousarray(both[:, 1:])
        self.Pt1 = column * inv
        self.Np = np.sum(self.P1)

    def update_transform(self):
        b = self._px - self.P1[:, None] * self.Y
        reg = self.alpha * self.sigma2
        if self._factor is not None:  # Woodbury through G ≈ L Lᵀ (module docstring)
            # Lᵀ D L + α σ² I is symmetric positive definite: its upper triangle by one rank-k update
            # of (√D L) (half a general product's flops), then Cholesky (deformable_cpd limits the BLAS)
            s = blas_lib.dsyrk(1.0, np.sqrt(self.P1)[:, None] * self._factor, trans=1)
            s[np.diag_indices_from(s)] += reg
            chol, info = lapack.dpotrf(s, lower=0, overwrite_a=1, clean=0)
            if info != 0:
                raise InputError(f"CPD's M-step: the kernel's reduced system is not positive definite (dpotrf info {info})")
            z, _ = lapack.dpotrs(chol, self._factor.T @ b, lower=0)
            self.W = (b - self.P1[:, None] * (self._factor @ z)) / reg
            return
        a = self.P1[:, None] * self.G  # = diag(P1) @ G, exactly
        a[np.diag_indices_from(a)] += reg
        self.W = np.linalg.solve(a, b)

    def update_variance(self):
        qprev = self.sigma2
        self.q = np.inf
        x_px = np.dot(np.transpose(self.Pt1), np.sum(np.multiply(self.X, self.X), axis=1))
        y_py = np.dot(np.transpose(self.P1), np.sum(np.multiply(self.TY, self.TY), axis=1))
        tr_pxy = np.sum(np.multiply(self.TY, self._px))
        self.sigma2 = (x_px - 2 * tr_pxy + y_py) / (self.Np * self.D)
        if self.sigma2 <= 0:
            self.sigma2 = self.tolerance / 10
        self.diff = np.abs(self.sigma2 - qprev)


def deformable_cpd(x, y, *, alpha: float, beta: float, w: float, max_iterations: int, tolerance: float,
                   rank_tolerance: float | None = None):
    """CPD's Gaussian weights ``W : (M, D)`` moving the source ``y : (M, D)`` towards the target
    ``x : (N, D)`` (same unit as both; ``y + G W`` with ``G = exp(−|y_i − y_j|² / (2 beta²))``), with
    pycpd's meanings of ``alpha`` (smoothness), ``beta`` (kernel width), ``w`` (outlier weight),
    ``max_iterations`` and ``tolerance`` (on the change of σ²). ``rank_tolerance``: the M-step through
    a low-rank factor of ``G`` (module docstring); None: the dense solve. The BLAS runs one thread
    inside (:func:`lungdeform.blas.limited`: ``(M, M)`` and ``(M, N)`` products, threads that spin on a
    busy machine)."""
    with blas.limited():
        reg = FastDeformable(X=np.ascontiguousarray(x, float), Y=np.ascontiguousarray(y, float), alpha=alpha,
                             beta=beta, w=w, max_iterations=max_iterations, tolerance=tolerance,
                             rank_tolerance=rank_tolerance)
        reg.register()
    return np.asarray(reg.W, float)
