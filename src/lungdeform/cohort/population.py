"""Population statistics of fitted constants over a cohort: the constants' range across a
population (paper Sec. IV-B.3). For a synthetic cohort (a ``truth.json`` in the manifest folder) the
runner adds the recovery of the known truth (:func:`lungdeform.cohort.recovery.add_recovery`).

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
  the observed range [min, max], and its distance from the mean in SDs; the constants whose paper
  value lies outside the observed range per side are listed (``table_i_departures``).
- Time per lung (:func:`fit_times`): each ok job's wall time (reading, alignment, fit, writing; s),
  their median, min, max and total. Note: directions are normalised (15)–(17), so c1, c3, c5 are defined only up to a
  common factor; their raw values compare with Table I only in the gauge the fit starts from.
"""

from __future__ import annotations

import csv
import io as _io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from lungdeform.atomic import write_json, write_text
from lungdeform.constants import TABLE_I, table_constants
from lungdeform.errors import InputError
from lungdeform.plot.figure import save_png
from lungdeform.plot.statistics import ScatterPanel, StripPanel, scatter_grid, strip_boxes
from lungdeform.progress import Progress, silent

from .job import RESULT_SCHEMA, RESULT_VERSION, finite_or_none
from .synthetic import normalise_force_constants

CONSTANTS = tuple(f"c{i}" for i in range(1, 10))
METRICS = ("surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "landmark_mean_mm", "objective_rms_mm")
VOLUMES = ("volume_ee_ml", "delta_volume_ml")
QUANTITIES = CONSTANTS + METRICS + VOLUMES + ("seconds",)
SIDES = ("left", "right")


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


def table_departures(table: dict) -> list[dict]:
    """The rows of :func:`table_comparison` whose paper value lies outside the population's observed
    range: ``[{"side", "constant", "paper", "mean", "min", "max", "sd_from_mean"}]``, in table order."""
    return [{"side": side, "constant": c, **{k: v[k] for k in ("paper", "mean", "min", "max", "sd_from_mean")}}
            for side, rows in table.items() for c, v in rows.items() if v["in_range"] is False]


def fit_times(ok: Sequence[dict]) -> dict:
    """Time per lung of the validated ok records ``ok``: ``{"median_s", "min_s", "max_s", "total_s",
    "n", "per_lung": [{"subject", "side", "seconds"}]}`` (s; a job's wall time on its worker, from
    reading its inputs to writing its folder; statistics null without any time)."""
    per = [{"subject": r["subject"], "side": r["side"], "seconds": finite_or_none(r.get("seconds"))} for r in ok]
    t = np.array([p["seconds"] for p in per if p["seconds"] is not None], float)
    stats = ({"median_s": float(np.median(t)), "min_s": float(t.min()), "max_s": float(t.max()),
              "total_s": float(t.sum())} if len(t) else dict.fromkeys(("median_s", "min_s", "max_s", "total_s")))
    return {**stats, "n": int(len(t)), "per_lung": per}


# --------------------------------------------------------------------------- tables and files
def csv_text(header: list[str], rows: list[list]) -> str:
    """CSV text of ``header`` and ``rows``: floats as ``%.6g``, None and non-finite floats as empty cells."""
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
                     progress: Progress | None = None) -> dict:
    """Population statistics (and recovery for a synthetic cohort) of a cohort run.

    ``results``: the runner's result records (ok and failed). ``out``: the cohort output folder
    (the one holding ``subjects/``); written there, atomically: ``population.json``,
    ``population.csv`` (overall), ``population_by_side.csv``, ``table1.csv`` (Table I comparison),
    ``times.csv`` (time per lung, :func:`fit_times`),
    ``plots/constants_by_side.png``, ``plots/constants_vs_volume.png``, ``plots/fit_errors.png``;
    the recovery of a synthetic cohort's truth is :func:`lungdeform.cohort.recovery.add_recovery`.
    Returns a summary dict (counts, the file paths, the Table I comparison and its flags, the
    departures from Table I, the time per lung without its per-lung list, ``"recovery": None``).
    """

    say = progress or silent
    out = Path(out)
    stats = population_statistics(results)
    table = table_comparison(stats["by_side"])
    ok, _ = split_results(results)
    times = fit_times(ok)
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
        "table_i_departures": table_departures(table),
        "time_per_lung": times,
        "notes": "c7…c9 normalised so that the largest |c| among them is 1; c1, c3, c5 are defined only "
                 "up to a common factor (directions are normalised).",
    }
    files["population.json"] = str(write_json(out / "population.json", doc))
    head = ["quantity", "mean", "sd", "min", "max", "n"]
    files["population.csv"] = str(write_text(out / "population.csv", csv_text(head, statistics_csv(stats["overall"]))))
    side_rows = [row for side, st in stats["by_side"].items() for row in statistics_csv(st, side)]
    files["population_by_side.csv"] = str(write_text(out / "population_by_side.csv", csv_text(["side"] + head, side_rows)))
    t_rows = [[side, c, v["paper"], v["paper_as_printed"], v["mean"], v["sd"], v["min"], v["max"], v["n"],
               "" if v["in_range"] is None else str(v["in_range"]).lower(), v["sd_from_mean"]]
              for side, rows in table.items() for c, v in rows.items()]
    files["table1.csv"] = str(write_text(out / "table1.csv", csv_text(
        ["side", "constant", "paper", "paper_as_printed", "mean", "sd", "min", "max", "n", "paper_in_range",
         "paper_sd_from_mean"],
        [[x if x is not None else math.nan for x in row] for row in t_rows])))
    files["times.csv"] = str(write_text(out / "times.csv", csv_text(
        ["subject", "side", "seconds"], [[p["subject"], p["side"], math.nan if p["seconds"] is None else p["seconds"]]
                                         for p in times["per_lung"]])))
    say("population plots")
    files.update(population_plots(ok, out / "plots"))
    summary = {"n_results": stats["n_results"], "n_ok": stats["n_ok"], "n_failed": stats["n_failed"],
               "failed": stats["failed"],
               "table_i_in_range": {side: {c: v["in_range"] for c, v in rows.items()} for side, rows in table.items()},
               "table_i": table, "table_i_departures": table_departures(table),
               "time_per_lung": {k: v for k, v in times.items() if k != "per_lung"},
               "recovery": None, "files": files}
    return summary


# --------------------------------------------------------------------------- plots
SIDE_COLOURS = {"left": "tab:blue", "right": "tab:orange"}


def population_plots(ok: Sequence[dict], folder: Path) -> dict[str, str]:
    """Per-constant distributions per side with Table I marked, constants against end-exhale
    volume, and the fit errors per side (PNG, atomically). ``ok``: validated ok records."""
    rng = np.random.default_rng(0)  # jitter only
    rows = [(r["side"], result_values(r)) for r in ok]
    sides = [s for s in SIDES if any(side == s for side, _ in rows)] or list(SIDES)
    col = [SIDE_COLOURS[s] for s in sides]

    def groups(name: str) -> list[np.ndarray]:
        return [np.array([v[name] for s, v in rows if s == side]) for side in sides]

    files = {}
    panels = []
    for k, name in enumerate(CONSTANTS):
        g = groups(name)
        panels.append(StripPanel(name, g, [f"{s}\n(n={len(x[np.isfinite(x)])})" for s, x in zip(sides, g)],
                                 reference=[table_i(side)[k] for side in sides]))
    fig = strip_boxes(panels, col, rows=3, cols=3, rng=rng, reference_label="Table I",
                      title="Fitted constants per side (boxes: quartiles; red: Santhanam et al. Table I, "
                            "c7…c9 normalised)")
    files["plots/constants_by_side.png"] = str(save_png(fig, folder / "constants_by_side.png"))

    panels = [ScatterPanel(name, {side: np.array([(v["volume_ee_ml"], v[name]) for s, v in rows if s == side])
                                  for side in sides},
                             levels={side: table_i(side)[k] for side in sides}, xlabel="end-exhale volume (mL)",
                             legend=k == 0)
              for k, name in enumerate(CONSTANTS)]
    fig = scatter_grid(panels, SIDE_COLOURS, rows=3, cols=3,
                       title="Constants against end-exhale lung volume (dashed: Table I per side)")
    files["plots/constants_vs_volume.png"] = str(save_png(fig, folder / "constants_vs_volume.png"))

    panels = [StripPanel(name.replace("_mm", " (mm)"), groups(name), sides, title_size=9) for name in METRICS]
    panels.append(StripPanel("time per lung (s)", groups("seconds"), sides, title_size=9))
    fig = strip_boxes(panels, col, rows=1, cols=len(panels), rng=rng,
                      title="Fit errors per side (largest-volume target) and time per lung")
    files["plots/fit_errors.png"] = str(save_png(fig, folder / "fit_errors.png"))
    return files
