"""Self-contained HTML report of a fit: metrics table and PNG plots embedded as base64.

The alignment used and, for a 4-D CT, the hysteresis table (:mod:`lungdeform.fit.cycle`) come
first. Plots (drawn by :mod:`lungdeform.plot`): the error colour map on the predicted surface (shaded,
from the front, the lateral side and the back; colour = distance of each model vertex to the target
surface, mm, one scale), a row per target; the cumulative distribution of those distances per method
(median marked), a panel per target, or for three targets or more (a 4-D CT) the headline target's
beside every target's median and 95th percentile;
the ray hit-distance histogram; bounding-box dimensions and volume / box-volume against volume
(paper Fig. 4); the fitted direction field (arrows in two views); the fit history.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_bytes
from lungdeform.plot.figure import png_bytes
from lungdeform.plot.fit import bounding_box, cumulative_panels, direction_field, fit_history, ray_histogram, target_errors
from lungdeform.plot.surface import error_maps


def _png(fig) -> str:
    return base64.b64encode(png_bytes(fig)).decode("ascii")


def _img(b64: str, title: str) -> str:
    return f'<h3>{html.escape(title)}</h3><img alt="{html.escape(title)}" src="data:image/png;base64,{b64}">'


def error_views(side: str) -> tuple[str, str, str]:
    """The error map's views of a ``side`` lung: front, its outer (lateral) face, back."""
    return ("anterior", f"lateral-{side}" if side in ("left", "right") else "lateral-right", "posterior")


def _table(per: dict) -> str:
    cols = ["surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "surface_max_mm", "landmark_mean_mm",
            "landmark_median_mm", "landmark_max_mm"]
    head = "".join(f"<th>{c}</th>" for c in cols)
    rows = "".join(
        f"<tr><td>{html.escape(name)}</td>" + "".join(f"<td>{v.get(c, float('nan')):.2f}</td>" for c in cols) + "</tr>"
        for name, v in per.items())
    return f"<table><tr><th>method</th>{head}</tr>{rows}</table>"


def _cycle(metrics: dict) -> str:
    """The alignment used and, for a 4-D CT, its hysteresis table (docs/FITTING.md, "4-D CT input")."""
    choice = metrics.get("alignment_choice")
    out = "" if choice is None else (f"<p>Alignment: <b>{html.escape(choice['used'])}</b> "
                                     f"({html.escape(choice['why'])}).</p>")
    pairs = (metrics.get("cycle") or {}).get("hysteresis")
    if metrics.get("cycle") is None:
        return out
    if not pairs:
        return out + "<p>Hysteresis: no phase on the exhale branch.</p>"
    rows = "".join(f"<tr><td>{html.escape(p['exhale'])}</td><td>{p['exhale_ml']:.1f}</td><td>{html.escape(p['inhale'])}"
                   f"</td><td>{p['inhale_ml']:.1f}</td><td>{p['mean_mm']:.2f}</td><td>{p['p95_mm']:.2f}</td>"
                   f"<td>{p['max_mm']:.2f}</td></tr>" for p in pairs)
    return out + ("<h2>Hysteresis (not modelled: the fit averages inhale and exhale at equal volume)</h2><table><tr>"
                  "<th>exhale phase</th><th>mL</th><th>inhale phase</th><th>mL</th><th>mean mm</th><th>p95 mm</th>"
                  f"<th>max mm</th></tr>{rows}</table>")


def _error_figures(faces, predictions, metrics, measured, grey: str) -> list[str]:
    """The error colour map of the model, one figure with a row per target
    (:func:`lungdeform.plot.surface.error_maps`: a 4-D CT's phases side by side on one colour scale),
    and the distributions of every method: a cumulative panel per target
    (:func:`lungdeform.plot.fit.cumulative_panels`) up to two targets, from three on the headline
    target's cumulative distribution beside every target's median and 95th percentile
    (:func:`lungdeform.plot.fit.target_errors`): two PNGs whatever the number of targets."""
    names = list(metrics["targets"])
    label = names[0] if len(names) == 1 else None
    rows = [(predictions[(t, "model")][0], np.where(measured, predictions[(t, "model")][1], np.nan)) for t in names]
    what = f"model: distance of each vertex to {label}" if label else "model: distance of each vertex to its target"
    maps = error_maps(rows, faces, views=error_views(metrics["side"]), title=f"{what}{grey}",
                      row_titles=None if label else names)
    panels = {f"distance of each predicted vertex to {t}" if label else t:
              {name: predictions[(t, name)][1][measured] for name in metrics["targets"][t]} for t in names}
    many = len(names) > 2
    draw = target_errors if many else cumulative_panels
    curves = draw(panels, ylabel="fraction of measured vertices")
    what = ("headline target (cumulative) and every target (median, 95th percentile)" if many else
            "cumulative" + ("" if label else ", one panel per target"))
    return [_img(_png(maps), "Error colour map (model)" + ("" if label else " (one row per target)")),
            _img(_png(curves), f"Error distributions ({what})")]


def write_report(path, *, rest, targets, fits, predictions, metrics, headline: str = "optimizer",
                 keep=None) -> Path:
    """Write the HTML report atomically; returns the path. ``headline``: the key of ``fits`` whose
    model is the headline ``model`` (rays and direction field are drawn for it). ``keep : (n,) bool``
    the model vertices measured (False: near a crop face; grey in the error map, left out of the
    distributions, as they are of the metrics); default all."""
    measured = np.ones(rest.n_vertices, bool) if keep is None else np.asarray(keep, bool)
    grey = "" if measured.all() else "; grey: near a crop face, not measured"

    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>lungdeform fit report</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #999;padding:3px 8px;text-align:right}img{max-width:100%}</style></head><body>",
             "<h1>lungdeform fit report</h1>",
             f"<p>Inputs: {html.escape(', '.join(metrics['inputs']))}; side {html.escape(metrics['side'])}; "
             f"volumes {', '.join(f'{v:.1f}' for v in metrics['volumes_ml'])} mL; model mesh "
             f"{metrics['model_mesh_vertices']} vertices. Surfaces measured with the crop faces left out "
             "(exact point-to-triangle distances, area weighted); landmarks moved by the sliding interpolation "
             "of each method's surface displacement (the smoothest field with its normal motion; crop faces carry no data).</p>"]
    parts.append(_cycle(metrics))
    protocols = metrics.get("protocols", {})
    if protocols:
        parts.append("<h2>What each method saw</h2><ul>" + "".join(
            f"<li><b>{html.escape(k)}</b>: {html.escape(v)}</li>" for k, v in protocols.items()) + "</ul>")
    for tname, per in metrics["targets"].items():
        parts.append(f"<h2>Target {html.escape(tname)}</h2>{_table(per)}")
    parts += _error_figures(rest.faces, predictions, metrics, measured, grey)
    fit = fits.get(headline, fits["optimizer"])
    parts.append(_img(_png(ray_histogram(*fit.rays.histogram())), "Ray hit distances (fitted directions)"))
    parts.append(f"<p>Rays: {html.escape(str(fit.rays.summary()))}</p>")
    parts.append(_img(_png(bounding_box(metrics["bounding_box"])), "Bounding box against volume (paper Fig. 4)"))
    parts.append(_img(_png(direction_field(rest.vertices, fit.directions, np.linalg.norm(fit.displacement, axis=1))),
                      "Fitted direction field"))
    parts.append(_img(_png(fit_history({k: r.history for k, r in fits.items()})), "Fit history"))
    parts.append("<h2>Fit</h2><pre>" + html.escape(str({k: r.as_dict() for k, r in fits.items()})) + "</pre>")
    parts.append("</body></html>")
    path = Path(path)
    write_bytes(path, "\n".join(parts).encode("utf-8"))
    return path
