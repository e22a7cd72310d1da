"""``lungdeform validate prediction``: live breathing prediction scored on recorded traces.

Protocol, per trace (every ``.vxp`` and ``.csv`` trace the breathing commands read under the folder,
:func:`lungdeform.validate.breathing.find_traces`; the signal as
:func:`lungdeform.breathing.trace.read_trace` gives it, in the trace's own unit: the marker's first
principal component in mm, the RPM amplitude in cm):

1. each predictor of :data:`lungdeform.breathing.predict.PREDICTORS` (``model``, and the baselines
   ``none``: the last sample; ``linear``: the online autoregression with the settings searched on the
   shared traces as the model's were, :data:`lungdeform.breathing.predict.LINEAR_TUNED`;
   ``linear_plain``: the untuned one of ≤ 0.7, the last 2 s trained on the preceding 30 s) runs over
   the samples in order, causally, once per horizon ``h``;
2. the prediction made at a sample time ``t_i`` is scored against the trace at ``t_i + h`` (linear
   interpolation between samples), for every ``t_i`` at least ``warm_s`` (30 s) after the first
   sample and with ``t_i + h`` inside the trace: the first 30 s only warm the predictors up;
3. per trace and horizon: the RMS of each predictor and the ratios model/linear, model/linear_plain,
   model/none, linear/none, linear_plain/none; over traces, the median of each ratio (and over the
   quiet-breathing traces, tags N and NO of the marker files' names,
   ``<date>-<marker>-1-<tag>-<seconds>-6.csv``).

4. the model and the linear baseline also give 90 % prediction intervals
   (:class:`lungdeform.breathing.predict_interval.IntervalPredictor`, the same method for both); per
   trace and horizon: ``coverage`` (share of scored samples whose truth is inside), ``width_over_none_rms``
   (mean width over the RMS of no prediction), ``interval_score`` (Gneiting & Raftery 2007, trace units)
   and the same with the prefix ``linear_``; ``interval_score_over_linear``.

Targets (medians of per-trace ratios): model ≤ 0.95 × linear (the tuned baseline) at every horizon;
on quiet traces at 400 ms, model ≤ 0.5 × none; the median coverage within 0.87–0.93 at every horizon.
``metrics.json``::

    {"traces": {NAME: {"tag": …, "n_samples": …, "horizon_ms": {"400": {"model_rms": …, "none_rms": …,
                "linear_rms": …, "linear_plain_rms": …, "model_over_linear": …, "coverage": …,
                "linear_coverage": …, …}, …}}},
     "medians": {"400": {"model_over_linear": …, "model_over_linear_plain": …, "model_over_none": …,
                         "linear_over_none": …, "linear_plain_over_none": …}, …},
     "quiet_medians": {…}, "targets": {…}, "errors": {…}, "protocol": "…"}
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_json
from lungdeform.breathing.predict import (
    LINEAR_PLAIN,
    LINEAR_TUNED,
    PREDICTORS,
    BlendPredictor,
    LinearSettings,
    baseline_linear,
    predict_trace,
)
from lungdeform.breathing.predict_interval import IntervalConfig, interval_score, interval_trace
from lungdeform.breathing.trace import read_trace
from lungdeform.errors import InputError, LungdeformError
from lungdeform.plot.breathing import prediction_errors, prediction_excerpt
from lungdeform.plot.figure import save_png
from lungdeform.progress import Progress

from .breathing import trace_files

#: the horizons of the validation (ms)
HORIZONS_MS = (100, 200, 300, 400, 500)
#: seconds at the start of each trace that only warm the predictors up
WARM_S = 30.0
#: tags of the quiet-breathing marker sessions
QUIET_TAGS = ("N", "NO")
#: median model/linear at every horizon must not exceed this
TARGET_MODEL_OVER_LINEAR = 0.95
#: median model/none on quiet traces at TARGET_QUIET_HORIZON_MS must not exceed this
TARGET_QUIET_MODEL_OVER_NONE = 0.5
TARGET_QUIET_HORIZON_MS = 400
#: median coverage of the 90 % intervals at every horizon must lie in this range
TARGET_COVERAGE = (0.87, 0.93)
#: interval figures of each horizon whose medians over traces are reported
INTERVAL_KEYS = ("coverage", "linear_coverage", "width_over_none_rms", "linear_width_over_none_rms",
                 "interval_score_over_linear")
RATIOS = (("model_over_linear", "model", "linear"), ("model_over_linear_plain", "model", "linear_plain"),
          ("model_over_none", "model", "none"), ("linear_over_none", "linear", "none"),
          ("linear_plain_over_none", "linear_plain", "none"))


def check_horizons(horizons_ms) -> tuple[int, ...]:
    """Horizons as whole milliseconds in (0, 5000], increasing, no repeats; InputError naming them."""
    try:
        h = tuple(int(round(float(v))) for v in horizons_ms)
    except (TypeError, ValueError):
        raise InputError(f"horizons_ms must be numbers of milliseconds, got {horizons_ms!r}") from None
    if not h or any(not 0 < v <= 5000 for v in h) or list(h) != sorted(set(h)):
        raise InputError(f"horizons_ms must be increasing whole ms in (0, 5000], got {list(h)}")
    return h


def trace_tag(name: str) -> str | None:
    """The session tag of a marker file name (``…-LAC-1-N-138-6.csv`` → ``N``), else None."""
    parts = Path(name).stem.split("-")
    return parts[3] if len(parts) == 6 and parts[2] == "1" else None


def scored_rms(t_s: np.ndarray, x: np.ndarray, predicted: np.ndarray, horizon_s: float,
               warm_s: float = WARM_S) -> tuple[float, int]:
    """RMS of ``predicted[i] − x(t_i + h)`` over the scored samples (step 2 of the protocol), and their count."""
    ok = (t_s >= t_s[0] + warm_s) & (t_s + horizon_s <= t_s[-1])
    if not ok.any():
        return math.nan, 0
    truth = np.interp(t_s[ok] + horizon_s, t_s, x)
    return float(np.sqrt(np.mean((predicted[ok] - truth) ** 2))), int(ok.sum())


def scored_intervals(t_s: np.ndarray, x: np.ndarray, band: np.ndarray, horizon_s: float, coverage: float,
                     warm_s: float = WARM_S) -> dict:
    """Over the scored samples (step 2 of the protocol), of the intervals ``band : (n, 3)`` (prediction,
    lo, hi): the share holding the truth (``coverage``), their mean width (trace units; inf while any is
    infinite) and the mean interval score (Gneiting & Raftery 2007, trace units)."""
    ok = (t_s >= t_s[0] + warm_s) & (t_s + horizon_s <= t_s[-1])
    if not ok.any():
        return {"coverage": math.nan, "mean_width": math.nan, "interval_score": math.nan}
    truth = np.interp(t_s[ok] + horizon_s, t_s, x)
    lo, hi = band[ok, 1], band[ok, 2]
    return {"coverage": float(np.mean((lo <= truth) & (truth <= hi))), "mean_width": float(np.mean(hi - lo)),
            "interval_score": float(np.mean(interval_score(lo, hi, truth, coverage)))}


def score_trace(t_s, x, horizons_ms=HORIZONS_MS, warm_s: float = WARM_S, keep: int | None = None,
                interval: IntervalConfig | None = None) -> dict:
    """Every predictor at every horizon on one trace: ``{"n_samples", "horizon_ms": {"400": {…}}}``;
    with ``keep``, also ``"_predictions"`` at that horizon (ms) for the plots. The model and the linear
    baseline carry intervals (``interval``: their settings, coverage 0.9 by default)."""
    interval = interval or IntervalConfig()
    t, v = np.asarray(t_s, float), np.asarray(x, float)
    if t.size < 2 or t[-1] - t[0] <= warm_s:
        raise InputError(f"trace of {t[-1] - t[0]:.1f} s is not longer than the {warm_s:g} s warm-up")
    out: dict = {"n_samples": int(t.size), "duration_s": float(t[-1] - t[0]), "horizon_ms": {}}
    dt = float(np.median(np.diff(t)))
    for h_ms in horizons_ms:
        h = h_ms / 1000.0
        bands = {"model": interval_trace(t, v, BlendPredictor(h), interval),
                 "linear": interval_trace(t, v, baseline_linear(h, dt_s=dt), interval)}
        preds = {name: bands[name][:, 0] if name in bands else predict_trace(t, v, h, name) for name in PREDICTORS}
        row = {}
        for name, p in preds.items():
            row[f"{name}_rms"], row["n_scored"] = scored_rms(t, v, p, h, warm_s)
        for key, a, b in RATIOS:
            row[key] = row[f"{a}_rms"] / row[f"{b}_rms"] if row[f"{b}_rms"] > 0 else math.nan
        for name, band in bands.items():
            prefix = "" if name == "model" else f"{name}_"
            for key, value in scored_intervals(t, v, band, h, interval.coverage, warm_s).items():
                row[prefix + key] = value
            row[prefix + "width_over_none_rms"] = (row.pop(prefix + "mean_width") / row["none_rms"]
                                                   if row["none_rms"] > 0 else math.nan)
        row["interval_score_over_linear"] = (row["interval_score"] / row["linear_interval_score"]
                                             if row["linear_interval_score"] > 0 else math.nan)
        out["horizon_ms"][str(h_ms)] = row
        if keep == h_ms:
            out["_predictions"] = preds
    return out


def medians(traces: dict, horizons_ms, names=None) -> dict:
    """Median over traces (``names``: a subset) of each ratio at each horizon; None where none is finite."""
    out = {}
    for h_ms in horizons_ms:
        out[str(h_ms)] = {}
        for key in [k for k, _, _ in RATIOS] + list(INTERVAL_KEYS):
            vals = [r["horizon_ms"][str(h_ms)][key] for n, r in traces.items() if names is None or n in names]
            vals = [v for v in vals if math.isfinite(v)]
            out[str(h_ms)][key] = float(np.median(vals)) if vals else None
    return out


def targets(med: dict, quiet: dict) -> dict:
    """The two targets as measured: value, threshold and whether each is met."""
    worst = [m["model_over_linear"] for m in med.values()]
    q = quiet.get(str(TARGET_QUIET_HORIZON_MS), {}).get("model_over_none")
    cov = [m["coverage"] for m in med.values()]
    lo, hi = TARGET_COVERAGE
    return {
        "coverage_every_horizon": {"range": [lo, hi], "values": cov,
                                   "met": all(v is not None and lo <= v <= hi for v in cov)},
        "model_over_linear_every_horizon": {
            "worst": None if any(v is None for v in worst) else max(worst), "threshold": TARGET_MODEL_OVER_LINEAR,
            "met": all(v is not None and v <= TARGET_MODEL_OVER_LINEAR for v in worst)},
        "quiet_model_over_none": {"horizon_ms": TARGET_QUIET_HORIZON_MS, "value": q,
                                  "threshold": TARGET_QUIET_MODEL_OVER_NONE,
                                  "met": q is not None and q <= TARGET_QUIET_MODEL_OVER_NONE},
    }


def linear_text(s: LinearSettings) -> str:
    """A linear baseline's settings in words."""
    forget = "" if s.half_life_s is None else f" with a forgetting half-life of {s.half_life_s:g} s"
    memory = f"trained on the preceding {s.train_s:g} s" if s.train_s is not None else "trained on every pair" + forget
    return f"window {s.window_s:g} s, {memory}, refitted every {s.refit_s:g} s, ridge {s.ridge:g}"


def protocol(horizons_ms, warm_s: float) -> str:
    return (f"each predictor runs causally over the trace's samples; the prediction made at t_i is scored "
            f"against the trace at t_i + h (linear interpolation) for t_i >= t_0 + {warm_s:g} s; horizons "
            f"{', '.join(str(h) for h in horizons_ms)} ms; RMS in the trace's own unit; medians over traces of "
            f"per-trace ratios; quiet = marker sessions tagged {' or '.join(QUIET_TAGS)}; none = the last "
            f"sample; linear = least squares with an intercept on a window of samples, settings "
            f"{linear_text(LINEAR_TUNED)} (searched on the 16 shared traces as the model's were: "
            f"scripts/tune_linear_baseline.py); linear_plain = the untuned baseline of <= 0.7, "
            f"{linear_text(LINEAR_PLAIN)}; model = lungdeform.breathing.predict.BlendPredictor; "
            f"intervals (model and linear) = lungdeform.breathing.predict_interval.IntervalPredictor at "
            f"coverage 0.9, scored on the same samples: coverage, mean width / RMS of none, interval score "
            f"(Gneiting & Raftery 2007)")


def score_folder(data: Path, horizons_ms, warm_s: float, plot_ms: int,
                 progress: Progress | None = None) -> tuple[dict, dict]:
    """:func:`score_trace` on every trace under ``data``: ``(scores, errors)`` keyed as
    :func:`lungdeform.validate.breathing.trace_files`."""
    scores, errors = {}, {}
    for key, f in trace_files(data).items():
        if progress:
            progress(f"predicting {key}")
        try:
            tr = read_trace(f)
            scores[key] = {"tag": trace_tag(f.name), "unit": tr.unit,
                           **score_trace(tr.t_s, tr.amplitude, horizons_ms, warm_s, keep=plot_ms)}
            scores[key]["_trace"] = (tr.t_s, tr.amplitude)
        except LungdeformError as exc:
            errors[key] = " ".join(str(exc).split())
    if not scores:
        raise InputError(f"data {data}: no trace could be scored ({len(errors)} failed; first: "
                         f"{next(iter(errors.items()))[1]})")
    return scores, errors


def write_plots(scores: dict, horizons_ms, plot_ms: int, folder: Path) -> dict[str, str]:
    """Ratios against horizon (every trace and the medians) and, for the first quiet trace (else the
    first trace), 30 s of the predictions at ``plot_ms`` over the real signal."""
    folder.mkdir(parents=True, exist_ok=True)
    curves = {n: [r["horizon_ms"][str(h)]["model_over_linear"] for h in horizons_ms] for n, r in scores.items()}
    none = {n: [r["horizon_ms"][str(h)]["model_over_none"] for h in horizons_ms] for n, r in scores.items()}
    files = {"errors_vs_horizon.png": str(save_png(prediction_errors(np.array(horizons_ms), curves, none),
                                                   folder / "errors_vs_horizon.png"))}
    quiet = [n for n, r in scores.items() if r["tag"] in QUIET_TAGS]
    name = (quiet or list(scores))[0]
    t, x = scores[name]["_trace"]
    files["predicted_trace.png"] = str(save_png(
        prediction_excerpt(t, x, scores[name]["_predictions"], plot_ms / 1000.0, start_s=t[0] + WARM_S,
                           title=f"{name}: predictions {plot_ms} ms ahead, plotted at the time they predict",
                           unit=scores[name]["unit"]), folder / "predicted_trace.png"))
    return files


def validate_prediction(data: Path, out: Path, horizons_ms=HORIZONS_MS, warm_s: float = WARM_S,
                        progress: Progress | None = None) -> dict:
    """Score every trace under ``data`` (:func:`score_folder`), write ``out/metrics.json`` and
    ``out/plots/*.png``; return the metrics."""
    horizons_ms = check_horizons(horizons_ms)
    plot_ms = TARGET_QUIET_HORIZON_MS if TARGET_QUIET_HORIZON_MS in horizons_ms else horizons_ms[-1]
    scores, errors = score_folder(data, horizons_ms, warm_s, plot_ms, progress)
    out = Path(out)
    files = write_plots(scores, horizons_ms, plot_ms, out / "plots")
    traces = {n: {k: v for k, v in r.items() if not k.startswith("_")} for n, r in scores.items()}
    quiet = {n for n, r in traces.items() if r["tag"] in QUIET_TAGS}
    med, qmed = medians(traces, horizons_ms), medians(traces, horizons_ms, quiet)
    metrics = {"traces": traces, "medians": med, "quiet_medians": qmed, "n_traces": len(traces),
               "n_quiet": len(quiet), "targets": targets(med, qmed), "errors": errors,
               "horizons_ms": list(horizons_ms), "warm_s": warm_s, "plots": files,
               "protocol": protocol(horizons_ms, warm_s)}
    write_json(out / "metrics.json", metrics, strict=True)
    return metrics
