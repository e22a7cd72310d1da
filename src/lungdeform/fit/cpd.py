"""Coherent Point Drift, deformable (Myronenko & Song 2010): ``pycpd``'s iteration, without its waste.

``pycpd.DeformableRegistration`` (MIT) forms ``diag(P1) @ G`` as a dense ``(M, M)`` matrix product
(O(M³) per iteration, as much as the solve itself), computes ``P @ X`` twice per iteration and
builds an ``(M, N, D)`` temporary for the squared distances. :func:`deformable_cpd` runs the same
EM iteration (same start, same updates, same stopping rule) with a row scaling, one ``P @ X`` and
:func:`scipy.spatial.distance.cdist`: the same weights to rounding (bit-identical on the tests), in
about half the time at ``M = N = 1500`` (the baselines and the correspondence field of
:mod:`lungdeform.fit.registration`). ``pycpd`` is a required dependency (pyproject.toml).
"""

from __future__ import annotations

import numpy as np
import pycpd
from scipy.spatial.distance import cdist


class FastDeformable(pycpd.DeformableRegistration):
    """``pycpd.DeformableRegistration`` with the cheaper E-step, transform update and variance (module docstring)."""

    def expectation(self):
        p = cdist(self.TY, self.X, "sqeuclidean")  # (M, N), as pycpd's sum of squared differences
        c = (2 * np.pi * self.sigma2) ** (self.D / 2)
        c = c * self.w / (1 - self.w)
        c = c * self.M / self.N
        np.negative(p, out=p)
        p /= 2 * self.sigma2
        np.exp(p, out=p)
        den = np.sum(p, axis=0)
        den[den == 0] = np.finfo(float).eps
        den += c
        p /= den
        self.P = p
        self.Pt1 = np.sum(p, axis=0)
        self.P1 = np.sum(p, axis=1)
        self.Np = np.sum(self.P1)

    def update_transform(self):
        a = self.P1[:, None] * self.G  # = diag(P1) @ G, exactly
        a[np.diag_indices_from(a)] += self.alpha * self.sigma2
        self._px = self.P @ self.X
        self.W = np.linalg.solve(a, self._px - self.P1[:, None] * self.Y)

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


def deformable_cpd(x, y, *, alpha: float, beta: float, w: float, max_iterations: int, tolerance: float):
    """CPD's Gaussian weights ``W : (M, D)`` moving the source ``y : (M, D)`` towards the target
    ``x : (N, D)`` (same unit as both; ``y + G W`` with ``G = exp(−|y_i − y_j|² / (2 beta²))``), with
    pycpd's meanings of ``alpha`` (smoothness), ``beta`` (kernel width), ``w`` (outlier weight),
    ``max_iterations`` and ``tolerance`` (on the change of σ²)."""
    reg = FastDeformable(X=np.asarray(x, float), Y=np.asarray(y, float), alpha=alpha, beta=beta, w=w,
                        max_iterations=max_iterations, tolerance=tolerance)
    reg.register()
    return np.asarray(reg.W, float)
