"""Population statistics of fitted constants over a cohort (issue 6 item 2), and, for a synthetic
cohort, the recovery of the known truth (item 3).

Input: the per-job result records the cohort runner writes (``OUT/subjects/<subject>/<side>/result.json``,
schema ``lungdeform.cohort.result`` version 1; see :func:`check_result`). Failed records are counted
and listed, never part of a statistic.

Readings chosen:

- Statistics per quantity: mean, SD (sample SD, ``ddof=1``; undefined, written as null, for fewer
  than two values), min, max and n over the lungs where the quantity is finite (a missing
  landmark error is left out, not zero). Overall and per side.
- Quantities: c1…c9 (the fit's normalisation: c7…c9 scaled so that the largest ``|c|`` among them
  is 1), the fit errors ``surface_mean_mm``, ``surface_rms_mm``, ``surface_p95_mm``,
  ``landmark_mean_mm``, ``objective_rms_mm``, the end-exhale volume (the first of ``volumes_ml``)
  and ``delta_volume_ml`` (largest minus end-exhale volume), and the fit time ``seconds``.
- Table I comparison per side and constant: the population mean ± SD against the paper's value
  (c7…c9 normalised like the fit's, so that c8 = 0.95 of the paper reads 1), whether it lies in
  the observed range [min, max], and its distance from the mean in SDs. Note: directions are normalised (15)–(17), so c1, c3, c5 are defined only up to a
  common factor; their raw values compare with Table I only in the gauge the fit starts from.
- Recovery (a ``truth.json`` from :mod:`lungdeform.synthetic` in the manifest folder): per
  constant the error fitted − true (mean, SD, max ``|error|``, mean ``|error|/|true|``, RMS), the
  scale-free ratios c1/c3 and c5/c3, and the displacement-field error at every target volume
  from the saved ``model.npz``: per vertex (when the model mesh is the synthetic end-exhale mesh)
  total, normal and tangential parts against the true, noise-free surface, and the symmetric
  surface distance to it.
- Gauge of c1, c3, c5 in the recovery: the same model has every common factor of c1, c3, c5 and the
  fit holds c3 at its start (:data:`lungdeform.search.GAUGE`), so raw errors of these three mix the
  gauge with the fit's error. Their errors are taken against the truth rescaled into the fit's
  gauge, ``true·(fitted c3 / true c3)`` (:data:`SCALE_CONSTANTS`; the error of c3 is then zero by
  construction; undefined, null, when either c3 is 0); the raw errors are kept as
  ``constants_raw`` (per lung ``error_raw``). c1/c3, c5/c3 and c2, c4, c6…c9 are gauge-free.
"""

from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .atomic import finite_json
from .cohort import RESULT_SCHEMA, RESULT_VERSION, finite_or_none
from .constants import TABLE_I, table_constants
from .errors import InputError
from .search import GAUGE
CONSTANTS = tuple(f"c{i}" for i in range(1, 10))
METRICS = ("surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "landmark_mean_mm", "objective_rms_mm")
VOLUMES = ("volume_ee_ml", "delta_volume_ml")
QUANTITIES = CONSTANTS + METRICS + VOLUMES + ("seconds",)
SIDES = ("left", "right")
RATIOS = {"c1/c3": (0, 2), "c5/c3": (4, 2)}
#: c1, c3, c5: defined only up to a common factor (directions are normalised); index of c3.
SCALE_CONSTANTS = {"c1": 0, "c3": 2, "c5": 4}
#: What the recovery's errors of c1, c3, c5 are (recovery.json notes, recovery.csv).
GAUGE_NOTE = ("c1, c3, c5 errors are against the truth rescaled into the fit's gauge, true·(fitted c3 / true c3) "
              "(c1, c3, c5 share an arbitrary common factor and the fit holds c3 at its start; the c3 error is "
              "then 0 by construction); the raw errors fitted − true of c1, c3, c5 are under constants_raw")


@dataclass(frozen=True)
class Summary:
    """Statistics of one quantity (same unit as the quantity); NaN where undefined."""

    mean: float
    sd: float
    min: float
    max: float
    n: int

    def as_dict(self) -> dict:
        return {k: finite_or_none(getattr(self, k)) for k in ("mean", "sd", "min", "max")} | {"n": self.n}


def describe(values) -> Summary:
    """Mean, sample SD (ddof=1), min, max and n of the finite entries of ``values : (k,)``."""
    v = np.asarray([np.nan if x is None else x for x in np.ravel(values)], float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return Summary(math.nan, math.nan, math.nan, math.nan, 0)
    sd = float(np.std(v, ddof=1)) if len(v) > 1 else math.nan
    return Summary(float(v.mean()), sd, float(v.min()), float(v.max()), int(len(v)))


# --------------------------------------------------------------------------- result records
def check_result(record, where: str = "result") -> dict:
    """Validate one cohort result record; return it. Raises :class:`InputError` naming ``where``
    (the subject/side or file) and the field at fault."""
    if not isinstance(record, dict):
        raise InputError(f"{where}: a result must be a JSON object, got {type(record).__name__}")
    if record.get("schema") != RESULT_SCHEMA or record.get("version") != RESULT_VERSION:
        raise InputError(f"{where}: not a {RESULT_SCHEMA} v{RESULT_VERSION} record "
                         f"(schema {record.get('schema')!r}, version {record.get('version')!r})")
    for key in ("subject", "side", "status"):
        if not isinstance(record.get(key), str):
            raise InputError(f"{where}: field '{key}' must be a string")
    where = f"{where} {record['subject']}/{record['side']}"
    if record["side"] not in SIDES:
        raise InputError(f"{where}: side must be 'left' or 'right', got {record['side']!r}")
    if record["status"] not in ("ok", "failed"):
        raise InputError(f"{where}: status must be 'ok' or 'failed', got {record['status']!r}")
    if record["status"] == "ok":
        c = record.get("constants")
        if not isinstance(c, (list, tuple)) or len(c) != 9:
            raise InputError(f"{where}: an ok result needs 'constants' with 9 values c1…c9")
        vols = record.get("volumes_ml")
        if not isinstance(vols, (list, tuple)) or len(vols) < 2:
            raise InputError(f"{where}: an ok result needs 'volumes_ml' with at least 2 volumes")
        if not isinstance(record.get("metrics"), dict):
            raise InputError(f"{where}: an ok result needs a 'metrics' object")
    return record


def result_values(record: dict) -> dict[str, float]:
    """``{quantity: value}`` of one ok record (NaN where missing)."""
    out = {name: float(v) for name, v in zip(CONSTANTS, record["constants"])}
    metrics = record.get("metrics") or {}
    for name in METRICS:
        v = metrics.get(name)
        out[name] = math.nan if v is None else float(v)
    vols = [float(v) for v in record["volumes_ml"]]
    out["volume_ee_ml"] = vols[0]
    out["delta_volume_ml"] = vols[-1] - vols[0]
    s = record.get("seconds")
    out["seconds"] = math.nan if s is None else float(s)
    return out


def split_results(results: Sequence[dict]) -> tuple[list[dict], list[dict]]:
    """Validate and split into ``(ok, failed)``; duplicated (subject, side) ok records are refused."""
    ok, failed, seen = [], [], set()
    for i, r in enumerate(results):
        check_result(r, f"result {i + 1}")
        if r["status"] == "ok":
            key = (r["subject"], r["side"])
            if key in seen:
                raise InputError(f"result {i + 1}: {key[0]}/{key[1]} appears twice")
            seen.add(key)
            ok.append(r)
        else:
            failed.append(r)
    return ok, failed


# --------------------------------------------------------------------------- statistics
def population_statistics(results: Sequence[dict]) -> dict:
    """``{"overall": {q: Summary}, "by_side": {side: {q: Summary}}, "n_results", "n_ok",
    "n_failed", "failed": [...]}`` over the ok records."""
    ok, failed = split_results(results)
    rows = [(r["side"], result_values(r)) for r in ok]
    overall = {q: describe([v[q] for _, v in rows]) for q in QUANTITIES}
    by_side = {side: {q: describe([v[q] for s, v in rows if s == side]) for q in QUANTITIES}
               for side in SIDES if any(s == side for s, _ in rows)}
    return {"n_results": len(results), "n_ok": len(ok), "n_failed": len(failed),
            "overall": overall, "by_side": by_side,
            "failed": [{"subject": r["subject"], "side": r["side"], "error_type": r.get("error_type"),
                        "error": r.get("error")} for r in failed]}


def table_i(side: str) -> np.ndarray:
    """Table I's c1…c9 for ``side`` in the fit's convention ``(9,) float``: c7…c9 divided by their
    largest ``|c|`` (the paper's 0.01, 0.95, 0.07 become 0.0105, 1, 0.0737 for the left lung)."""
    from .synthetic import normalise_force_constants

    return normalise_force_constants(table_constants(side))


def table_comparison(by_side: dict[str, dict[str, Summary]]) -> dict:
    """Per side and constant: the paper's Table I value against the population.

    ``{side: {c: {"paper", "paper_as_printed", "mean", "sd", "min", "max", "n", "in_range",
    "sd_from_mean"}}}``. ``paper``: Table I in the fit's normalisation (:func:`table_i`; only
    c7…c9 differ from ``paper_as_printed``); ``in_range``: min ≤ paper ≤ max (None without data);
    ``sd_from_mean``: (paper − mean)/SD.
    """
    out = {}
    for side, stats in by_side.items():
        rows = {}
        ref = table_i(side)
        for k, name in enumerate(CONSTANTS):
            st = stats[name]
            paper = float(ref[k])
            in_range = None if st.n == 0 else bool(st.min <= paper <= st.max)
            z = (paper - st.mean) / st.sd if st.n > 1 and st.sd > 0 else math.nan
            rows[name] = {"paper": paper, "paper_as_printed": float(TABLE_I[side][k]), **st.as_dict(),
                          "in_range": in_range, "sd_from_mean": finite_or_none(z)}
        out[side] = rows
    return out


# --------------------------------------------------------------------------- recovery
def _alignments(metrics_path: Path) -> list[np.ndarray | None]:
    """The 4×4 rigid transforms (moving → end-exhale) ``run_fit`` applied to each target, from its
    ``metrics.json`` (empty when absent)."""
    import json

    try:
        m = json.loads(metrics_path.read_text(encoding="utf-8"))
        # "applied": the whole transform (any --align); older metrics files only have "apex"
        return [np.asarray((a.get("applied") or a["apex"])["matrix"], float) for a in m.get("alignment", [])]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def _point_errors(pred: np.ndarray, true: np.ndarray, faces: np.ndarray, suffix: str = "") -> dict:
    """Per-vertex error of ``pred`` against ``true`` (both (n, 3) mm, same mesh): total, and its
    parts along the true surface's normal and tangent to it."""
    from .mesh import vertex_normals

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
    from .distance import symmetric_distance
    from .errors import LungdeformError
    from .mesh import Surface
    from .modelfile import load_model

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

    ``truth``: :func:`lungdeform.synthetic.read_truth`'s mapping. ``subjects_dir``: the runner's
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


# --------------------------------------------------------------------------- tables and files
def _csv(header: list[str], rows: list[list]) -> str:
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow(["" if (isinstance(x, float) and not math.isfinite(x)) or x is None else
                    (f"{x:.6g}" if isinstance(x, float) else x) for x in row])
    return buf.getvalue()


def statistics_csv(stats: dict[str, Summary], side: str | None = None) -> list[list]:
    lead = [] if side is None else [side]
    return [lead + [q, s.mean, s.sd, s.min, s.max, s.n] for q, s in stats.items()]


def write_population(results: list[dict], out: Path, manifest_dir: Path,
                     progress: Callable[[str], None] | None = None) -> dict:
    """Population statistics (and recovery for a synthetic cohort) of a cohort run.

    ``results``: the runner's result records (ok and failed). ``out``: the cohort output folder
    (the one holding ``subjects/``); written there, atomically: ``population.json``,
    ``population.csv`` (overall), ``population_by_side.csv``, ``table1.csv`` (Table I comparison),
    ``plots/constants_by_side.png``, ``plots/constants_vs_volume.png``, ``plots/fit_errors.png``;
    when ``manifest_dir/truth.json`` exists also ``recovery.json``, ``recovery.csv``,
    ``recovery_by_lung.csv`` and ``plots/recovery.png``. Returns a summary dict (counts, the file
    paths, the Table I flags and, with a truth, the recovery headline).
    """
    from .atomic import write_json, write_text
    from .synthetic import read_truth

    say = progress or (lambda _m: None)
    out = Path(out)
    stats = population_statistics(results)
    table = table_comparison(stats["by_side"])
    files: dict[str, str] = {}
    doc = {
        "schema": "lungdeform.population", "version": 1,
        "n_results": stats["n_results"], "n_ok": stats["n_ok"], "n_failed": stats["n_failed"],
        "failed": stats["failed"],
        "statistics": {"sd": "sample SD (ddof=1); null for fewer than 2 values",
                       "excluded": "failed results; non-finite values (e.g. no landmarks)"},
        "overall": {q: s.as_dict() for q, s in stats["overall"].items()},
        "by_side": {side: {q: s.as_dict() for q, s in st.items()} for side, st in stats["by_side"].items()},
        "table_i": table,
        "notes": "c7…c9 normalised so that the largest |c| among them is 1; c1, c3, c5 are defined only "
                 "up to a common factor (directions are normalised).",
    }
    files["population.json"] = str(write_json(out / "population.json", doc))
    head = ["quantity", "mean", "sd", "min", "max", "n"]
    files["population.csv"] = str(write_text(out / "population.csv", _csv(head, statistics_csv(stats["overall"]))))
    side_rows = [row for side, st in stats["by_side"].items() for row in statistics_csv(st, side)]
    files["population_by_side.csv"] = str(write_text(out / "population_by_side.csv", _csv(["side"] + head, side_rows)))
    t_rows = [[side, c, v["paper"], v["paper_as_printed"], v["mean"], v["sd"], v["min"], v["max"], v["n"],
               "" if v["in_range"] is None else str(v["in_range"]).lower(), v["sd_from_mean"]]
              for side, rows in table.items() for c, v in rows.items()]
    files["table1.csv"] = str(write_text(out / "table1.csv", _csv(
        ["side", "constant", "paper", "paper_as_printed", "mean", "sd", "min", "max", "n", "paper_in_range",
         "paper_sd_from_mean"],
        [[x if x is not None else math.nan for x in row] for row in t_rows])))
    ok, _ = split_results(results)
    say("population plots")
    files.update(population_plots(ok, out / "plots"))
    summary = {"n_results": stats["n_results"], "n_ok": stats["n_ok"], "n_failed": stats["n_failed"],
               "failed": stats["failed"],
               "table_i_in_range": {side: {c: v["in_range"] for c, v in rows.items()} for side, rows in table.items()},
               "recovery": None, "files": files}
    truth_path = Path(manifest_dir) / "truth.json"
    if truth_path.is_file():
        say("recovery of the synthetic truth")
        truth = read_truth(truth_path)
        rec = recovery(results, truth, subjects_dir=out / "subjects", truth_dir=Path(manifest_dir))
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
        files["recovery.csv"] = str(write_text(out / "recovery.csv", _csv(
            ["quantity", "mean_error", "sd_error", "max_abs_error", "rms_error", "mean_relative_error", "n", "note"],
            [[math.nan if x is None else x for x in row] for row in crow + frow])))
        lrows = []
        for lu in rec["lungs"]:
            last = (lu["field"] or [{}])[-1]
            lrows.append([lu["subject"], lu["side"], lu["source"]]
                         + [lu["true"][c] for c in CONSTANTS] + [lu["fitted"][c] for c in CONSTANTS]
                         + [last.get(k, math.nan) for k in FIELD_KEYS] + [lu["gauge_factor"]])
        files["recovery_by_lung.csv"] = str(write_text(out / "recovery_by_lung.csv", _csv(
            ["subject", "side", "source"] + [f"true_{c}" for c in CONSTANTS] + [f"fit_{c}" for c in CONSTANTS]
            + list(FIELD_KEYS) + ["gauge_factor"], lrows)))
        files.update(recovery_plot(rec, out / "plots"))
        summary["recovery"] = {"n_matched": rec["n_matched"], "missing": rec["missing"],
                               "constants": rec["constants"], "constants_raw": rec["constants_raw"],
                               "gauge": GAUGE_NOTE, "field": rec["field"]}
    return summary


# --------------------------------------------------------------------------- plots
SIDE_COLOURS = {"left": "tab:blue", "right": "tab:orange"}


def _figure(rows: int, cols: int, size=(3.2, 2.6)):
    """A matplotlib Figure on the Agg canvas (no pyplot state, safe in workers)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    height = size[1] * rows
    fig = Figure(figsize=(size[0] * cols, height))
    # fixed margins in inches (constrained layout costs a second per figure): title, axis labels
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.6 / height, top=1 - 0.75 / height, hspace=0.75, wspace=0.35)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(rows, cols, squeeze=False)


def _save(fig, path: Path) -> str:
    from .atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return str(path)


def _strip_box(ax, groups: list[np.ndarray], rng: np.random.Generator, colours: list[str]) -> None:
    """Box (median, quartiles) and jittered points per group at x = 0, 1, …"""
    for x, (vals, col) in enumerate(zip(groups, colours)):
        vals = vals[np.isfinite(vals)]
        if len(vals) == 0:
            continue
        if len(vals) > 1:
            ax.boxplot([vals], positions=[x], widths=0.5, showfliers=False, manage_ticks=False,
                       medianprops={"color": "black"})
        ax.scatter(x + rng.uniform(-0.12, 0.12, len(vals)), vals, s=14, color=col, alpha=0.8, zorder=3)


def population_plots(ok: Sequence[dict], folder: Path) -> dict[str, str]:
    """Per-constant distributions per side with Table I marked, constants against end-exhale
    volume, and the fit errors per side (PNG, atomically). ``ok``: validated ok records."""
    rng = np.random.default_rng(0)  # jitter only
    rows = [(r["side"], result_values(r)) for r in ok]
    sides = [s for s in SIDES if any(side == s for side, _ in rows)] or list(SIDES)
    col = [SIDE_COLOURS[s] for s in sides]
    files = {}

    fig, axes = _figure(3, 3)
    for k, name in enumerate(CONSTANTS):
        ax = axes.flat[k]
        groups = [np.array([v[name] for s, v in rows if s == side]) for side in sides]
        _strip_box(ax, groups, rng, col)
        for x, side in enumerate(sides):
            ax.hlines(table_i(side)[k], x - 0.35, x + 0.35, colors="red", linewidth=2,
                      label="Table I" if x == 0 else None, zorder=4)
        ax.set_xticks(range(len(sides)), [f"{s}\n(n={len(g[np.isfinite(g)])})" for s, g in zip(sides, groups)])
        ax.set_xlim(-0.6, len(sides) - 0.4)
        ax.set_title(name)
        if k == 0:
            ax.legend(fontsize=7, loc="best")
    fig.suptitle("Fitted constants per side (boxes: quartiles; red: Santhanam et al. Table I, c7…c9 normalised)")
    files["plots/constants_by_side.png"] = _save(fig, folder / "constants_by_side.png")

    fig, axes = _figure(3, 3)
    for k, name in enumerate(CONSTANTS):
        ax = axes.flat[k]
        for side in sides:
            pts = np.array([(v["volume_ee_ml"], v[name]) for s, v in rows if s == side]).reshape(-1, 2)
            ax.scatter(pts[:, 0], pts[:, 1], s=14, color=SIDE_COLOURS[side], label=side)
            ax.axhline(table_i(side)[k], color=SIDE_COLOURS[side], linestyle="--", linewidth=1)
        ax.set_title(name)
        ax.set_xlabel("end-exhale volume (mL)")
        if k == 0 and rows:
            ax.legend(fontsize=7)
    fig.suptitle("Constants against end-exhale lung volume (dashed: Table I per side)")
    files["plots/constants_vs_volume.png"] = _save(fig, folder / "constants_vs_volume.png")

    fig, axes = _figure(1, len(METRICS))
    for k, name in enumerate(METRICS):
        ax = axes.flat[k]
        _strip_box(ax, [np.array([v[name] for s, v in rows if s == side]) for side in sides], rng, col)
        ax.set_xticks(range(len(sides)), sides)
        ax.set_xlim(-0.6, len(sides) - 0.4)
        ax.set_title(name.replace("_mm", " (mm)"), fontsize=9)
    fig.suptitle("Fit errors per side (largest-volume target)")
    files["plots/fit_errors.png"] = _save(fig, folder / "fit_errors.png")
    return files


def recovery_plot(rec: dict, folder: Path) -> dict[str, str]:
    """Fitted against true value per constant and ratio (identity line), and the per-lung
    normal and tangential displacement error (PNG, atomically)."""
    names = list(CONSTANTS) + list(RATIOS)
    fig, axes = _figure(3, 4)
    lungs = rec["lungs"]
    for k, name in enumerate(names):
        ax = axes.flat[k]
        for side in SIDES:
            pts = np.array([(lu["true_in_fit_gauge"][name], lu["fitted"][name]) for lu in lungs
                            if lu["side"] == side]).reshape(-1, 2)
            ax.scatter(pts[:, 0], pts[:, 1], s=14, color=SIDE_COLOURS[side], label=side)
        vals = np.array([[lu["true_in_fit_gauge"][name], lu["fitted"][name]] for lu in lungs]).ravel()
        vals = vals[np.isfinite(vals)]
        if len(vals):
            lo, hi = vals.min(), vals.max()
            pad = 0.05 * (hi - lo) or 0.05 * abs(hi) or 0.05
            ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="grey", linewidth=1)
        ax.set_title(name)
        ax.set_xlabel("true · fitted c3/true c3" if name in SCALE_CONSTANTS else "true", fontsize=8)
        ax.set_ylabel("fitted")
        if k == 0 and lungs:
            ax.legend(fontsize=7)
    ax = axes.flat[len(names)]
    for side in SIDES:
        pts = np.array([(lu["field"][-1].get("normal_rms_mm", np.nan), lu["field"][-1].get("tangential_rms_mm", np.nan))
                        for lu in lungs if lu["side"] == side and lu["field"]]).reshape(-1, 2)
        ax.scatter(pts[:, 0], pts[:, 1], s=14, color=SIDE_COLOURS[side])
    ax.set_xlabel("normal RMS error (mm)")
    ax.set_ylabel("tangential RMS error (mm)")
    ax.set_title("displacement error, largest volume", fontsize=9)
    fig.suptitle("Recovery of the synthetic truth (grey: fitted = true)")
    return {"plots/recovery.png": _save(fig, folder / "recovery.png")}
