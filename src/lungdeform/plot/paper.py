"""The paper's Figs. 7–9 (Santhanam et al. 2008): the planar and circular meshes' displacement
against the mass-spring-damper reference, and the convergence of both (``validate paper``).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .figure import new_figure


def planar_figure(vertices: np.ndarray, faces: np.ndarray, transfer_u: np.ndarray, msd_u: np.ndarray,
                  rms_percent: float) -> Figure:
    """Fig. 8: (a) the planar mesh (``vertices (n, 3)`` mm, ``faces (m, 3)``), (b) deformed by the
    out-of-plane transfer displacement ``transfer_u (n,)`` (exaggerated), (c) ``msd_u − transfer_u``
    as a % of the largest MSD displacement."""
    fig = new_figure(15.0, 4.8, dpi=100)
    v, f, u = vertices, faces, transfer_u
    span = float(np.ptp(v[:, :2], axis=0).max())
    exaggerate = 0.25 * span / max(float(np.abs(u).max()), 1e-300)
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=f, color="0.85", edgecolor="0.4", linewidth=0.2)
    ax.set_zlim(0, 0.3 * span)
    ax.set_title("(a) regular planar mesh, uniform E")
    ax = fig.add_subplot(1, 3, 2, projection="3d")
    ax.plot_trisurf(v[:, 0], v[:, 1], exaggerate * u, triangles=f, cmap="viridis", edgecolor="0.3", linewidth=0.1)
    ax.set_zlim(0, 0.3 * span)
    ax.set_title(f"(b) deformed by the transfer model (×{exaggerate:.3g})")
    for a in fig.axes:
        a.set_xlabel("x (mm)")
        a.set_ylabel("y (mm)")
    ax = fig.add_subplot(1, 3, 3)
    diff = 100.0 * (msd_u - u) / float(np.abs(msd_u).max())
    im = ax.tripcolor(v[:, 0], v[:, 1], f, diff, shading="gouraud", cmap="coolwarm")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"(c) MSD − transfer, % of max (RMS {rms_percent:.2g} %)")
    fig.colorbar(im, ax=ax, shrink=0.8, label="% of the largest MSD displacement")
    fig.subplots_adjust(left=0.02, right=0.95, wspace=0.15)
    return fig


def circular_figure(vertices: np.ndarray, faces: np.ndarray, moduli: np.ndarray, displacement: np.ndarray,
                    radial_displacement: np.ndarray, stiff_to_soft: float, position_controlled: float) -> Figure:
    """Fig. 9: (a) the disc mesh (``vertices (n, 3)`` mm), node size ∝ ``moduli (n,)``; (b) deformed
    by ``displacement (n, 3)`` (exaggerated by the largest ``radial_displacement (n,)``)."""
    fig = new_figure(12.0, 5.4, dpi=100)
    v, f, e = vertices, faces, moduli
    radius = float(np.linalg.norm(v[:, :2], axis=1).max())
    exaggerate = 0.25 * radius / max(float(np.abs(radial_displacement).max()), 1e-300)
    w = v + exaggerate * displacement
    sizes = 4 + 60 * (e - e.min()) / max(float(np.ptp(e)), 1e-300)
    lim = 1.3 * radius
    for k, (pts, title) in enumerate([(v, "(a) 2-D circular mesh, node size ∝ E"),
                                      (w, f"(b) deformed, unit radial force (×{exaggerate:.3g})")]):
        ax = fig.add_subplot(1, 2, k + 1)
        if k == 1:
            ax.triplot(v[:, 0], v[:, 1], f, color="0.8", linewidth=0.4)
        ax.triplot(pts[:, 0], pts[:, 1], f, color="0.35", linewidth=0.5)
        sc = ax.scatter(pts[:, 0], pts[:, 1], s=sizes, c=np.log10(e), cmap="plasma", zorder=3)
        ax.set_aspect("equal")
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(title)
    fig.subplots_adjust(left=0.06, right=0.86, bottom=0.14, top=0.93, wspace=0.25)
    fig.colorbar(sc, cax=fig.add_axes((0.89, 0.2, 0.015, 0.65)), label="log10 E")
    fig.text(0.06, 0.03, f"stiff/soft mean radial displacement ratio {stiff_to_soft:.3f}"
             f" (position-controlled {position_controlled:.3f}); grey = original")
    return fig


def convergence_figure(push_sweeps: np.ndarray, push_residual: np.ndarray, msd_residual: np.ndarray,
                       msd_error: np.ndarray, *, tol: float, n_nodes: int, title: str) -> Figure:
    """Fig. 7: relative residual (log scale) against sweeps (node updates / ``n_nodes``): the push
    loop's ``push_residual`` at ``push_sweeps``, the MSD's residual and error per step (= sweep)."""
    fig = new_figure(8.0, 5.5, dpi=100, layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    ax.semilogy(push_sweeps, np.maximum(push_residual, 1e-300), label="push loop: max|Pitcher| / max|f|")
    steps = np.arange(len(msd_residual))
    ax.semilogy(steps, np.maximum(msd_residual, 1e-300), label="MSD: max|f − K u| / max|f|")
    ax.semilogy(steps, np.maximum(msd_error, 1e-300), "--", label="MSD: max|u − C| / max|C|")
    ax.axhline(tol, color="0.5", linewidth=0.8, linestyle=":")
    ax.set_xlabel(f"sweeps (node updates / {n_nodes} graph nodes); 1 MSD step = 1 sweep")
    ax.set_ylabel("relative residual")
    ax.set_title(title)
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    return fig
