"""``report.html`` of ``lungdeform validate single-scan`` (:func:`write_report`): every row per lung and as
medians (over every lung and over the lungs with landmarks), the medians per surface region, and the
pictures: per-lung bars of each row's surface and landmark error, the medians per region, and the
landmarks' motion per axis, observed and predicted."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from lungdeform.atomic import write_text
from lungdeform.geometry.regions import REGIONS
from lungdeform.plot.figure import png_bytes
from lungdeform.plot.statistics import grouped_bars

TABLE = "<table border=1 cellspacing=0 cellpadding=3>"


def row_names(lungs: dict) -> list[str]:
    """The rows scored on any of ``lungs`` (``metrics["lungs"]``), in order of first appearance."""
    return list(dict.fromkeys(r for v in lungs.values() for r, x in v.items() if isinstance(x, dict)
                              and "surface_mean_mm" in x))


def _cell(v, fmt: str = "{:.2f}") -> str:
    return "–" if v is None else fmt.format(v)


def _figure(values: dict, title: str, ylabel: str = "mm") -> str:
    fig = grouped_bars(values, title=title, ylabel=ylabel)
    return f'<img alt="{html.escape(title)}" src="data:image/png;base64,{base64.b64encode(png_bytes(fig)).decode()}">'


def medians_table(summary: dict, rows: list[str]) -> str:
    """Per row: the surface median over every lung, over the lungs with landmarks, the landmark median,
    and both as a ratio to isotropic scaling."""
    lines = [("surface, every lung ({n})", "surface_mean_mm", summary["n_lungs"]),
             ("surface, lungs with landmarks ({n})", "surface_mean_mm_landmark_lungs", summary["n_lungs_landmarks"]),
             ("landmarks ({n})", "landmark_mean_mm", summary["n_lungs_landmarks"]),
             ("surface ÷ isotropic", "surface_vs_isotropic", None), ("landmarks ÷ isotropic", "landmark_vs_isotropic", None)]
    head = "".join(f"<th>{html.escape(r)}</th>" for r in rows)
    body = "".join(f"<tr><td>{html.escape(label.format(n=n))}</td>" +
                   "".join(f"<td>{_cell(summary.get(r, {}).get(key))}</td>" for r in rows) + "</tr>"
                   for label, key, n in lines)
    return f"{TABLE}<tr><th>median (mm)</th>{head}</tr>{body}</table>"


def subsets_table(summary: dict, rows: list[str]) -> str:
    """Per subset of lungs (with / without landmarks, uncut, per folder): surface / landmark medians."""
    head = "".join(f"<th>{html.escape(r)}</th>" for r in rows)
    body = "".join(f"<tr><td>{html.escape(name)} ({sub['n_lungs']})</td>" + "".join(
        f"<td>{_cell(sub.get(r, {}).get('surface_mean_mm'))} / {_cell(sub.get(r, {}).get('landmark_mean_mm'))}</td>"
        for r in rows) + "</tr>" for name, sub in summary.get("subsets", {}).items())
    return f"{TABLE}<tr><th>lungs</th>{head}</tr>{body}</table>"


def lungs_table(lungs: dict, rows: list[str]) -> str:
    """Per lung: surface / landmark mean error of each row; a cut lung marked, with its crop faces."""
    head = "".join(f"<th>{html.escape(r)}</th>" for r in rows)
    body = []
    for k, v in lungs.items():
        cut = v.get("lung_info", {}).get("cut") or []
        label = html.escape(k) + (f" <small>(cut: {html.escape(', '.join(cut))})</small>" if cut else "")
        body.append(f"<tr><td>{label}</td>" + "".join(
            f"<td>{_cell(v[r]['surface_mean_mm'])} / {_cell(v[r].get('landmark_mean_mm'))}</td>" if r in v
            else "<td>–</td>" for r in rows) + "</tr>")
    return f"{TABLE}<tr><th>lung</th>{head}</tr>{''.join(body)}</table>"


def regions_table(summary: dict, lungs: dict, rows: list[str]) -> str:
    """Per region: its share of the area (median over the lungs) and each row's median distance (mm)."""
    shares = {r: [v["region_shares"][r] for v in lungs.values() if "region_shares" in v] for r in REGIONS}
    head = "".join(f"<th>{html.escape(r)}</th>" for r in rows)
    body = "".join(
        f"<tr><td>{r} ({_cell(min(shares[r]) if shares[r] else None)}–{_cell(max(shares[r]) if shares[r] else None)})"
        "</td>" + "".join(f"<td>{_cell(summary.get(row, {}).get('regions_mm', {}).get(r))}</td>" for row in rows)
        + "</tr>" for r in REGIONS)
    return f"{TABLE}<tr><th>region (share of area)</th>{head}</tr>{body}</table>"


def _motion_figure(lungs: dict) -> str:
    axes = {}
    for k, v in lungs.items():
        if v.get("default", {}).get("landmark_motion_mm") is None:
            continue
        motion = v["default"]["landmark_motion_mm"]
        axes[f"{k} observed"] = dict(zip(motion["axes"], motion["observed"]))
        for r in ("default", "paper"):
            if r in v:
                axes[f"{k} {r}"] = dict(zip(motion["axes"], v[r]["landmark_motion_mm"]["predicted"]))
    return _figure(axes, "landmark motion per axis") if axes else "<p>No lung with landmarks.</p>"


def write_report(path: Path, result: dict) -> Path:
    """``report.html`` (module docstring) of the metrics ``result`` of
    :func:`lungdeform.validate.single_scan.run_single_scan`."""
    lungs, summary = result["lungs"], result["summary"]
    rows = row_names(lungs)
    with_lm = {k: v for k, v in lungs.items() if v.get("lung_info", {}).get("landmarks", True)}
    parts = ["<html><head><meta charset='utf-8'><title>Single scan</title></head><body>",
             "<h1>One scan to the larger volume: surface / landmark mean error (mm)</h1>",
             f"<p>{html.escape(result['protocol'])}. Defaults: {html.escape(json.dumps(result['defaults']))}</p>",
             (f"<h2>Medians over {summary['n_lungs']} lungs ({summary['n_lungs_landmarks']} with landmarks, "
              f"{summary.get('n_lungs_cut', 0)} cut by the field of view)</h2>"),
             medians_table(summary, rows), "<h2>Subsets: surface / landmark medians (mm)</h2>",
             subsets_table(summary, rows),
             "<h2>Per region: median of the area-weighted mean distance to the real surface (mm)</h2>",
             f"<p>Regions: {html.escape(result.get('region_definition', ''))}.</p>",
             regions_table(summary, lungs, rows),
             _figure({r: {reg: summary[r]["regions_mm"][reg] for reg in REGIONS if summary[r]["regions_mm"][reg] is not None}
                      for r in rows}, "median distance per region"),
             "<h2>Per lung: surface / landmark mean error (mm)</h2>", lungs_table(lungs, rows),
             _figure({r: {k: v[r]["surface_mean_mm"] for k, v in lungs.items() if r in v} for r in rows},
                     "surface mean distance per lung")]
    if with_lm:
        parts.append(_figure({r: {k: v[r]["landmark_mean_mm"] for k, v in with_lm.items()
                                  if r in v and v[r].get("landmark_mean_mm") is not None} for r in rows},
                             "landmark mean error per lung"))
    parts += ["<h2>Mean |landmark displacement| per axis (mm): observed and predicted</h2>", _motion_figure(lungs),
              "</body></html>"]
    return write_text(path, "\n".join(parts))
