"""Recovery of the known truth by the fits of a synthetic cohort: a ``truth.json``
from :mod:`lungdeform.cohort.synthetic` in the manifest folder, against the cohort runner's result records
(:mod:`lungdeform.cohort.population` for their schema and the population statistics).

Readings chosen:

- Recovery: per constant the error fitted − true (mean, SD, max ``|error|``, mean
  ``|error|/|true|``, RMS), the scale-free ratios c1/c3 and c5/c3, and the displacement-field error
  at every target volume from the saved ``model.npz``: per vertex (when the model mesh is the
  synthetic end-exhale mesh) total, normal and tangential parts against the true, noise-free
  surface, and the symmetric surface distance to it.
- Gauge of c1, c3, c5 in the recovery: the same model has every common factor of c1, c3, c5 and the
  fit holds c3 at its start (:data:`lungdeform.fit.search.GAUGE`), so raw errors of these three mix the
  gauge with the fit's error. Their errors are taken against the truth rescaled into the fit's
  gauge, ``true·(fitted c3 / true c3)`` (:data:`SCALE_CONSTANTS`; the error of c3 is then zero by
  construction; undefined, null, when either c3 is 0); the raw errors are kept as
  ``constants_raw`` (per lung ``error_raw``). c1/c3, c5/c3 and c2, c4, c6…c9 are gauge-free.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from lungdeform.atomic import finite_json, write_json, write_text
from lungdeform.errors import LungdeformError
from lungdeform.fit.search import GAUGE
from lungdeform.geometry.distance import symmetric_distance
from lungdeform.geometry.mesh import Surface, vertex_normals
from lungdeform.io.modelfile import load_model
from lungdeform.plot.figure import save_png
from lungdeform.plot.statistics import ScatterPanel, scatter_grid
from lungdeform.progress import Progress

from .job import finite_or_none
from .population import CONSTANTS, METRICS, SIDE_COLOURS, SIDES, csv_text, describe, split_results
from .synthetic import read_truth

#: The scale-free ratios compared besides c1…c9: name → (numerator, denominator) index.
RATIOS = {"c1/c3": (0, 2), "c5/c3": (4, 2)}
#: c1, c3, c5: defined only up to a common factor (directions are normalised); index of c3.
SCALE_CONSTANTS = {"c1": 0, "c3": 2, "c5": 4}
#: What the recovery's errors of c1, c3, c5 are (recovery.json notes, recovery.csv).
GAUGE_NOTE = ("c1, c3, c5 errors are against the truth rescaled into the fit's gauge, true·(fitted c3 / true c3) "
              "(c1, c3, c5 share an arbitrary common factor and the fit holds c3 at its start; the c3 error is "
              "then 0 by construction); the raw errors fitted − true of c1, c3, c5 are under constants_raw")


def _alignments(metrics_path: Path) -> list[np.ndarray | None]:
    """The 4×4 rigid transforms (moving → end-exhale) ``run_fit`` applied to each target, from its
    ``metrics.json`` (empty when absent)."""

    try:
        m = json.loads(metrics_path.read_text(encoding="utf-8"))
        # "applied": the whole transform (any --align); older metrics files only have "apex"
        return [np.asarray((a.get("applied") or a["apex"])["matrix"], float) for a in m.get("alignment", [])]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def _point_errors(pred: np.ndarray, true: np.ndarray, faces: np.ndarray, suffix: str = "") -> dict:
    """Per-vertex error of ``pred`` against ``true`` (both (n, 3) mm, same mesh): total, and its
    parts along the true surface's normal and tangent to it."""

    e = pred - true
    n = vertex_normals(true, faces)
    en = np.einsum("ij,ij->i", e, n)
    et = e - en[:, None] * n
    norm = np.linalg.norm(e, axis=1)
    return {f"point_mean{suffix}_mm": float(norm.mean()), f"point_rms{suffix}_mm": float(np.sqrt(np.mean(norm**2))),
            f"point_max{suffix}_mm": float(norm.max()), f"normal_rms{suffix}_mm": float(np.sqrt(np.mean(en**2))),
            f"tangential_rms{suffix}_mm": float(np.sqrt(np.mean(np.sum(et**2, axis=1))))}


def _field_errors(model_path: Path, arrays_path: Path, side: str, volumes_ml, scales,
                  table_shifts=None) -> list[dict] | None:
    """Displacement-field error per target volume of a fitted model against the truth arrays.

    The truth lives in the end-exhale frame, as does the model. ``run_fit`` rigidly aligns each
    target onto the end-exhale surface first; when its ``metrics.json`` (beside the model) records
    that transform, the errors against the truth moved by the same transform (the target the fit
    actually saw) are reported too, with the suffix ``_aligned``, and the transform's translation.
    ``table_shifts : (k, 3)`` mm (truth ``table_shifts_mm``): where the scans were moved; the target
    the fit saw is then the truth plus that shift, moved by the transform.
    """

    if not model_path.is_file() or not arrays_path.is_file():
        return None
    try:
        lung = load_model(model_path).lungs.get(side)
    except LungdeformError:
        return None
    if lung is None:
        return None
    with np.load(arrays_path) as z:
        p, faces, u = z["vertices"], z["faces"], z["displacement"]
    same_mesh = lung.surface.vertices.shape == p.shape and bool(np.allclose(lung.surface.vertices, p, atol=1e-6))
    aligns = _alignments(model_path.parent / "metrics.json")
    out = []
    for j, (v, s) in enumerate(zip(volumes_ml[1:], scales)):
        true = p + float(s) * u
        pred = lung.positions_at(lung.scale_for(float(v)))
        sym = symmetric_distance(Surface(pred, lung.surface.faces), Surface(true, faces)).stats
        row = {"volume_ml": float(v), "surface_to_truth_mean_mm": sym.mean, "surface_to_truth_rms_mm": sym.rms,
               "true_displacement_rms_mm": float(np.sqrt(np.mean(np.sum((true - p) ** 2, axis=1))))}
        if same_mesh:
            row.update(_point_errors(pred, true, faces))
        if j < len(aligns):
            m = aligns[j]
            scan = true + (np.asarray(table_shifts[j], float) if table_shifts else 0.0)
            moved = scan @ m[:3, :3].T + m[:3, 3]
            row["alignment_translation_mm"] = float(np.linalg.norm(m[:3, 3]))
            # how far the alignment put the scan from where the truth is (0: the frame recovered)
            row["alignment_error_rms_mm"] = float(np.sqrt(np.mean(np.sum((moved - true) ** 2, axis=1))))
            row["surface_to_aligned_truth_rms_mm"] = symmetric_distance(
                Surface(pred, lung.surface.faces), Surface(moved, faces)).stats.rms
            if same_mesh:
                row.update(_point_errors(pred, moved, faces, "_aligned"))
        out.append(row)
    return out


FIELD_KEYS = ("point_mean_mm", "point_rms_mm", "point_max_mm", "normal_rms_mm", "tangential_rms_mm",
              "surface_to_truth_mean_mm", "surface_to_truth_rms_mm", "true_displacement_rms_mm",
              "alignment_translation_mm", "alignment_error_rms_mm", "point_rms_aligned_mm", "normal_rms_aligned_mm",
              "tangential_rms_aligned_mm", "surface_to_aligned_truth_rms_mm")


def recovery(results: Sequence[dict], truth: dict, *, subjects_dir: Path | None = None,
             truth_dir: Path | None = None) -> dict:
    """Recovery of the synthetic truth by the fits.

    ``truth``: :func:`lungdeform.cohort.synthetic.read_truth`'s mapping. ``subjects_dir``: the runner's
    ``OUT/subjects`` (for ``<subject>/<side>/model.npz``); ``truth_dir``: the folder the truth's
    relative array paths start from. Without them only the constants are compared.

    Errors of c1, c3, c5 are against the truth in the fit's gauge (:func:`gauge_factor`, module
    docstring); their raw errors are under ``constants_raw``.

    Returns ``{"constants": {name: {...}}, "constants_raw": {c1, c3, c5: {...}}, "field": {key:
    Summary dict} (largest volume), "lungs": [per lung], "missing": [...], "unmatched": [...]}``.
    """
    ok, failed = split_results(results)
    lungs, unmatched = [], []
    names = list(CONSTANTS) + list(RATIOS)
    for r in ok:
        key = (r["subject"], r["side"])
        rec = truth.get(key)
        if rec is None:
            unmatched.append({"subject": key[0], "side": key[1]})
            continue
        fitted = np.asarray(r["constants"], float)
        true = np.asarray(rec["constants"], float)
        fv = list(fitted) + [_ratio(fitted[a], fitted[b]) for a, b in RATIOS.values()]
        tv = list(true) + [_ratio(true[a], true[b]) for a, b in RATIOS.values()]
        gauge = gauge_factor(fitted, true)
        ref = list(tv)  # the truth in the fit's gauge: c1, c3, c5 rescaled, the rest as they are
        for k in SCALE_CONSTANTS.values():
            ref[k] = float(true[k]) * gauge
        field = None
        if subjects_dir is not None and truth_dir is not None and rec.get("files", {}).get("arrays"):
            field = _field_errors(Path(subjects_dir) / key[0] / key[1] / "model.npz",
                                  Path(truth_dir) / rec["files"]["arrays"], key[1], r["volumes_ml"],
                                  rec.get("scales", []), rec.get("table_shifts_mm"))
        lungs.append({"subject": key[0], "side": key[1], "source": rec.get("source"),
                      "noise_mm": rec.get("noise_mm"), "true": dict(zip(names, map(float, tv))),
                      "fitted": dict(zip(names, map(float, fv))),
                      "gauge_factor": gauge, "true_in_fit_gauge": dict(zip(names, map(float, ref))),
                      "error": {n: float(f - t) for n, f, t in zip(names, fv, ref)},
                      "error_raw": {n: float(fitted[k] - true[k]) for n, k in SCALE_CONSTANTS.items()},
                      "metrics": {k: finite_or_none((r.get("metrics") or {}).get(k)) for k in METRICS},
                      "field": field})
    const = {n: _error_stats([lu["error"][n] for lu in lungs], [lu["true_in_fit_gauge"][n] for lu in lungs])
             for n in names}
    raw = {n: _error_stats([lu["error_raw"][n] for lu in lungs], [lu["true"][n] for lu in lungs])
           for n in SCALE_CONSTANTS}
    last = [lu["field"][-1] for lu in lungs if lu["field"]]
    field_stats = {k: describe([row.get(k, math.nan) for row in last]).as_dict() for k in FIELD_KEYS}
    for k in METRICS:
        field_stats[f"fit_{k}"] = describe([lu["metrics"][k] for lu in lungs]).as_dict()
    done = {(r["subject"], r["side"]) for r in ok}
    missing = [{"subject": k[0], "side": k[1]} for k in truth if k is not None and k not in done]
    return {"n_matched": len(lungs), "constants": const, "constants_raw": raw, "field": field_stats, "lungs": lungs,
            "missing": missing, "unmatched": unmatched, "n_failed": len(failed)}


def _ratio(a: float, b: float) -> float:
    return float(a) / float(b) if b != 0 else math.nan


def gauge_factor(fitted, true) -> float:
    """``fitted c3 / true c3``: the common factor that takes the truth's c1, c3, c5 into the fit's
    gauge (``fitted, true : (9,)`` constants); NaN when either c3 is 0 or not finite."""
    f, t = float(fitted[GAUGE]), float(true[GAUGE])
    return f / t if f != 0 and t != 0 and math.isfinite(f) and math.isfinite(t) else math.nan


def _error_stats(errors, truths) -> dict:
    """Mean, SD, max |error|, RMS and mean |error|/|truth| of the finite errors (truths ≠ 0)."""
    err, tru = np.asarray(errors, float), np.asarray(truths, float)
    st = describe(err)
    nz = np.isfinite(err) & np.isfinite(tru) & (tru != 0)
    rel = np.abs(err[nz]) / np.abs(tru[nz])
    return {"mean_error": finite_or_none(st.mean), "sd_error": finite_or_none(st.sd),
            "max_abs_error": finite_or_none(np.nanmax(np.abs(err)) if st.n else math.nan),
            "rms_error": finite_or_none(np.sqrt(np.nanmean(err**2)) if st.n else math.nan),
            "mean_relative_error": finite_or_none(rel.mean() if len(rel) else math.nan), "n": st.n}


# --------------------------------------------------------------------------- files
def write_recovery(results: Sequence[dict], truth_path: Path, out: Path) -> tuple[dict[str, str], dict]:
    """Recovery of the synthetic truth ``truth_path`` by a cohort run's fits, written to files.

    ``results``: the runner's result records (ok and failed). ``truth_path``: a ``truth.json`` of
    :mod:`lungdeform.cohort.synthetic` (its folder is where the truth's relative array paths start).
    ``out``: the cohort output folder (the one holding ``subjects/``); written there, atomically:
    ``recovery.json``, ``recovery.csv``, ``recovery_by_lung.csv`` and ``plots/recovery.png``.
    Returns ``(files, headline)``: ``{name: path}`` of the files written, and the recovery headline
    (matched and missing lungs, constant and field errors) of
    :func:`lungdeform.cohort.population.write_population`'s summary.
    """

    out, truth_path = Path(out), Path(truth_path)
    files: dict[str, str] = {}
    truth = read_truth(truth_path)
    rec = recovery(results, truth, subjects_dir=out / "subjects", truth_dir=truth_path.parent)
    files["recovery.json"] = str(write_json(out / "recovery.json", {
        "schema": "lungdeform.recovery", "version": 1, "truth": str(truth_path),
        "noise_mm": truth[None].get("noise_mm"), "law": truth[None].get("law"),
        "notes": "error = fitted − true; " + GAUGE_NOTE + "; c1/c3 and c5/c3 are scale-free; field errors "
                 "at the largest volume against the noise-free true surface",
        **finite_json(rec)}))
    gauged = "against true·(fitted c3 / true c3): c1, c3, c5 share an arbitrary factor, c3 is the fit's gauge"
    crow = [[n, v["mean_error"], v["sd_error"], v["max_abs_error"], v["rms_error"], v["mean_relative_error"], v["n"],
             gauged if n in SCALE_CONSTANTS else ""] for n, v in rec["constants"].items()]
    crow += [[f"{n}_raw", v["mean_error"], v["sd_error"], v["max_abs_error"], v["rms_error"],
              v["mean_relative_error"], v["n"], "raw fitted − true, no gauge correction (not meaningful alone)"]
             for n, v in rec["constants_raw"].items()]
    frow = [[k, v["mean"], v["sd"], v["max"], None, None, v["n"], ""] for k, v in rec["field"].items()]
    files["recovery.csv"] = str(write_text(out / "recovery.csv", csv_text(
        ["quantity", "mean_error", "sd_error", "max_abs_error", "rms_error", "mean_relative_error", "n", "note"],
        [[math.nan if x is None else x for x in row] for row in crow + frow])))
    lrows = []
    for lu in rec["lungs"]:
        last = (lu["field"] or [{}])[-1]
        lrows.append([lu["subject"], lu["side"], lu["source"]]
                     + [lu["true"][c] for c in CONSTANTS] + [lu["fitted"][c] for c in CONSTANTS]
                     + [last.get(k, math.nan) for k in FIELD_KEYS] + [lu["gauge_factor"]])
    files["recovery_by_lung.csv"] = str(write_text(out / "recovery_by_lung.csv", csv_text(
        ["subject", "side", "source"] + [f"true_{c}" for c in CONSTANTS] + [f"fit_{c}" for c in CONSTANTS]
        + list(FIELD_KEYS) + ["gauge_factor"], lrows)))
    files.update(recovery_plot(rec, out / "plots"))
    return files, {"n_matched": rec["n_matched"], "missing": rec["missing"],
                   "constants": rec["constants"], "constants_raw": rec["constants_raw"],
                   "gauge": GAUGE_NOTE, "field": rec["field"]}


# --------------------------------------------------------------------------- plots
def recovery_plot(rec: dict, folder: Path) -> dict[str, str]:
    """Fitted against true value per constant and ratio (identity line), and the per-lung
    normal and tangential displacement error (PNG, atomically)."""
    lungs = rec["lungs"]
    panels = [ScatterPanel(name, {side: np.array([(lu["true_in_fit_gauge"][name], lu["fitted"][name])
                                                  for lu in lungs if lu["side"] == side]) for side in SIDES},
                             identity=True, ylabel="fitted", xlabel_size=8, legend=k == 0,
                             xlabel="true · fitted c3/true c3" if name in SCALE_CONSTANTS else "true")
              for k, name in enumerate(list(CONSTANTS) + list(RATIOS))]
    last = {side: [lu["field"][-1] for lu in lungs if lu["side"] == side and lu["field"]] for side in SIDES}
    panels.append(ScatterPanel(
        "displacement error, largest volume",
        {side: np.array([(f.get("normal_rms_mm", np.nan), f.get("tangential_rms_mm", np.nan)) for f in fields])
         for side, fields in last.items()},
        xlabel="normal RMS error (mm)", ylabel="tangential RMS error (mm)", title_size=9))
    fig = scatter_grid(panels, SIDE_COLOURS, rows=3, cols=4,
                       title="Recovery of the synthetic truth (grey: fitted = true)")
    return {"plots/recovery.png": str(save_png(fig, folder / "recovery.png"))}


def add_recovery(summary: dict, results: list[dict], out: Path, manifest_dir: Path,
                 progress: Progress | None = None) -> dict:
    """When ``manifest_dir/truth.json`` exists (a synthetic cohort), write the recovery of that truth
    (:func:`write_recovery`: ``recovery.json``, ``recovery.csv``, ``recovery_by_lung.csv``,
    ``plots/recovery.png``) into ``out`` and put its headline and files into ``summary`` (the dict
    :func:`lungdeform.cohort.population.write_population` returned); else return ``summary`` unchanged."""
    truth_path = Path(manifest_dir) / "truth.json"
    if not truth_path.is_file():
        return summary
    if progress is not None:
        progress("recovery of the synthetic truth")
    recovered, headline = write_recovery(results, truth_path, out)
    return {**summary, "recovery": headline, "files": {**summary.get("files", {}), **recovered}}
