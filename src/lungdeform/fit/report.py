"""Self-contained HTML report of a fit: metrics table and PNG plots embedded as base64.

Plots: error colour map on the predicted surface (three orthographic views, colour = distance
of each model vertex to the target surface, mm); histograms of those distances per method; the
ray hit-distance histogram (METHOD §8); bounding-box dimensions and volume / box-volume against
volume (paper Fig. 4); the fitted direction field (arrows in two views); the fit history.
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_bytes


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _img(b64: str, title: str) -> str:
    return f'<h3>{html.escape(title)}</h3><img alt="{html.escape(title)}" src="data:image/png;base64,{b64}">'


def plot_error_map(points: np.ndarray, error: np.ndarray, title: str) -> str:
    """Three orthographic views of ``points (n, 3)`` mm LPS coloured by ``error (n,)`` mm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 4.5))
    views = (("x (mm, patient left)", "z (mm, head)", 0, 2, 1), ("y (mm, posterior)", "z (mm, head)", 1, 2, 0),
             ("x (mm, patient left)", "y (mm, posterior)", 0, 1, 2))
    vmax = float(np.percentile(error, 98)) if len(error) else 1.0
    for ax, (xl, yl, a, b, depth) in zip(axes, views):
        order = np.argsort(points[:, depth])
        sc = ax.scatter(points[order, a], points[order, b], c=error[order], s=4, cmap="viridis", vmin=0, vmax=vmax)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_aspect("equal")
    fig.colorbar(sc, ax=axes, label="distance to target (mm)", shrink=0.8)
    fig.suptitle(title)
    return _png(fig)


def plot_histograms(errors: dict[str, np.ndarray]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    hi = max((float(np.percentile(e, 99)) for e in errors.values() if len(e)), default=1.0)
    bins = np.linspace(0, max(hi, 1e-3), 40)
    for name, e in errors.items():
        ax.hist(np.clip(e, 0, hi), bins=bins, histtype="step", label=name, linewidth=1.5)
    ax.set_xlabel("distance of predicted vertex to target surface (mm)")
    ax.set_ylabel("vertices")
    ax.legend()
    return _png(fig)


def plot_rays(counts: np.ndarray, edges: np.ndarray) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.stairs(counts, edges, fill=True)
    ax.set_xlabel("signed ray hit distance along d (mm)")
    ax.set_ylabel("rays")
    return _png(fig)


def plot_bounding_box(bb: dict) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for key, style in (("model", "-"), ("observed", "o")):
        rows = bb[key]
        v = [r["volume_ml"] for r in rows]
        d = np.array([r["dims_mm"] for r in rows])
        for k, lab in enumerate("xyz"):
            a1.plot(v, d[:, k], style, label=f"{lab} ({key})", color=f"C{k}")
        a2.plot(v, [r["ratio"] for r in rows], style, color="k", label=key)
    a1.set_xlabel("lung volume (mL)")
    a1.set_ylabel("bounding-box dimension (mm)")
    a1.legend(fontsize=8)
    a2.axhspan(0.32, 0.40, color="0.9", label="paper Fig. 4b range")
    a2.set_xlabel("lung volume (mL)")
    a2.set_ylabel("volume / bounding-box volume")
    a2.legend(fontsize=8)
    return _png(fig)


def plot_directions(points: np.ndarray, directions: np.ndarray, magnitude: np.ndarray) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    step = max(1, len(points) // 600)
    p, d, m = points[::step], directions[::step], magnitude[::step]
    for ax, (a, b, xl, yl) in zip(axes, ((0, 2, "x (mm)", "z (mm)"), (1, 2, "y (mm)", "z (mm)"))):
        q = ax.quiver(p[:, a], p[:, b], d[:, a], d[:, b], m, cmap="plasma", scale=40, width=0.003)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_aspect("equal")
    fig.colorbar(q, ax=axes, label="|u| per unit (mm)", shrink=0.8)
    return _png(fig)


def plot_history(history: dict[str, np.ndarray]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for name, h in history.items():
        ax.plot(np.arange(1, len(h) + 1), h, label=name)
    ax.set_xlabel("objective evaluations")
    ax.set_ylabel("best RMS symmetric distance (mm)")
    ax.legend()
    return _png(fig)


def _table(per: dict) -> str:
    cols = ["surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "surface_max_mm", "landmark_mean_mm",
            "landmark_median_mm", "landmark_max_mm"]
    head = "".join(f"<th>{c}</th>" for c in cols)
    rows = "".join(
        f"<tr><td>{html.escape(name)}</td>" + "".join(f"<td>{v.get(c, float('nan')):.2f}</td>" for c in cols) + "</tr>"
        for name, v in per.items())
    return f"<table><tr><th>method</th>{head}</tr>{rows}</table>"


def write_report(path, *, rest, targets, fits, predictions, metrics, headline: str = "optimizer") -> Path:
    """Write the HTML report atomically; returns the path. ``headline``: the key of ``fits`` whose
    model is the headline ``model`` (rays and direction field are drawn for it)."""

    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>lungdeform fit report</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #999;padding:3px 8px;text-align:right}img{max-width:100%}</style></head><body>",
             "<h1>lungdeform fit report</h1>",
             f"<p>Inputs: {html.escape(', '.join(metrics['inputs']))}; side {html.escape(metrics['side'])}; "
             f"volumes {', '.join(f'{v:.1f}' for v in metrics['volumes_ml'])} mL; model mesh "
             f"{metrics['model_mesh_vertices']} vertices. Surfaces measured with the crop faces left out "
             "(exact point-to-triangle distances, area weighted); landmarks moved by the sliding interpolation "
             "of each method's surface displacement (the smoothest field with its normal motion; crop faces carry no data).</p>"]
    protocols = metrics.get("protocols", {})
    if protocols:
        parts.append("<h2>What each method saw</h2><ul>" + "".join(
            f"<li><b>{html.escape(k)}</b>: {html.escape(v)}</li>" for k, v in protocols.items()) + "</ul>")
    for tname, per in metrics["targets"].items():
        parts.append(f"<h2>Target {html.escape(tname)}</h2>{_table(per)}")
        errs = {name: predictions[(tname, name)][1] for name in per}
        name0 = "model"
        x, e, _ = predictions[(tname, name0)]
        parts.append(_img(plot_error_map(x, e, f"model: distance to {tname}"), "Error colour map (model)"))
        parts.append(_img(plot_histograms(errs), "Error histograms"))
    fit = fits.get(headline, fits["optimizer"])
    parts.append(_img(plot_rays(*fit.rays.histogram()), "Ray hit distances (fitted directions)"))
    parts.append(f"<p>Rays: {html.escape(str(fit.rays.summary()))}</p>")
    parts.append(_img(plot_bounding_box(metrics["bounding_box"]), "Bounding box against volume (paper Fig. 4)"))
    parts.append(_img(plot_directions(rest.vertices, fit.directions, np.linalg.norm(fit.displacement, axis=1)),
                      "Fitted direction field"))
    parts.append(_img(plot_history({k: r.history for k, r in fits.items()}), "Fit history"))
    parts.append("<h2>Fit</h2><pre>" + html.escape(str({k: r.as_dict() for k, r in fits.items()})) + "</pre>")
    parts.append("</body></html>")
    path = Path(path)
    write_bytes(path, "\n".join(parts).encode("utf-8"))
    return path
