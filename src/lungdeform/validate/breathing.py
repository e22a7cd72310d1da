"""Held-out validation of the PV breathing driver over a folder of recorded traces.

``lungdeform validate breathing`` behind it: :func:`validate_breathing` finds RPM ``.vxp`` and marker
``.csv`` files under a folder (recursively, :func:`find_traces`), runs the held-out protocol of
:mod:`lungdeform.breathing.holdout` on each (PV driver, Lujan cos^{2n}, Fourier K = 2, all three fitted
on the training part only) and writes ``OUT/metrics.json``::

    {"traces": {"<file name>": {"model_rms_percent": …, "lujan_rms_percent": …,
                                "shared_shape": {"model", "lujan", "fourier"}, …,
                                "fourier_insample_rms_percent": …}},
     "median_model_rms_percent": …, "median_shared_shape": {…}, …,
     "in_sample": {"median_fourier_insample_rms_percent": …, "median_per_cycle_refit_insample": {…}}}

Besides those keys: the medians of every held-out calibration variant (shared_shape with drift = the
headline, shared_shape_no_drift, anchored), the same error as a % of each held-out trace's whole
range, the score on model-free "regular" held-out cycles, the white-noise floor, and a paired
PV-vs-Lujan comparison (per trace; a comparison of two medians is not paired). The per-cycle refit
(each held-out cycle fitted to itself) is **not** held out: its medians are under ``in_sample``
(until 0.8 they sat beside the held-out ones as ``median_fourier_rms_percent`` and
``median_per_cycle_refit``).
A trace that cannot be read or holds too few cycles is reported under "errors" and left out of the
medians; if no trace can be scored, :class:`lungdeform.errors.InputError`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lungdeform.atomic import write_json
from lungdeform.breathing import holdout
from lungdeform.breathing.trace import read_trace
from lungdeform.errors import InputError, LungdeformError
from lungdeform.progress import Progress

#: The median held-out RMS (% of the breath amplitude) the PV driver is asked to stay under.
TARGET_MEDIAN_MODEL_RMS_PERCENT = 5.0


def find_traces(data: Path) -> list[Path]:
    """The ``.vxp`` and ``.csv`` files under ``data`` (recursively, extension in any case), sorted by
    path; hidden files (e.g. macOS ``._name.csv`` resource forks) skipped."""
    files = [p for p in Path(data).rglob("*") if p.is_file() and p.suffix.lower() in (".vxp", ".csv")
             and not p.name.startswith(".")]
    return sorted(files, key=lambda p: str(p))


def trace_files(data: Path) -> dict[str, Path]:
    """The traces under the folder ``data`` (:func:`find_traces`) keyed by file name (by the path under
    ``data`` when two sub-folders hold the same name); InputError when ``data`` is not a folder or holds none."""
    data = Path(data)
    if not data.is_dir():
        raise InputError(f"data {data}: not a folder")
    files = find_traces(data)
    if not files:
        raise InputError(f"data {data}: no .vxp or .csv trace found")
    names = [f.name for f in files]
    return {(f.name if names.count(f.name) == 1 else f.relative_to(data).as_posix()): f for f in files}


def score_traces(data: Path, tidal_volume_ml: float = 500.0, train_fraction: float = 0.5,
                 progress: Progress | None = None) -> tuple[dict, dict]:
    """:func:`lungdeform.breathing.holdout.evaluate` on every trace under ``data``. Returns
    ``(scores, errors)``, both keyed as :func:`trace_files`; ``errors`` holds the one-line reason a
    trace could not be scored."""
    traces, errors = {}, {}
    for key, f in trace_files(data).items():
        if progress:
            progress(f"fitting {key}")
        try:
            res = holdout.evaluate(read_trace(f), tidal_volume_ml=tidal_volume_ml, train_fraction=train_fraction)
        except LungdeformError as exc:
            errors[key] = " ".join(str(exc).split())
            continue
        res.pop("_curves")
        traces[key] = res
    if not traces:
        raise InputError(f"data {data}: no trace could be scored ({len(errors)} failed; first: "
                         f"{next(iter(errors.items()))[1]})")
    return traces, errors


def _median(traces: dict, key: str, sub: str | None = None) -> float | None:
    """The median of ``key`` (of ``sub``) over the traces where it is finite; None where none is."""
    vals = [(r[sub][key] if sub else r[key]) for r in traces.values()]
    vals = [v for v in vals if v is not None and np.isfinite(v)]
    return float(np.median(vals)) if vals else None


def protocol(tidal_volume_ml: float, train_fraction: float) -> str:
    """The protocol in words, as written into metrics.json."""
    return (
        f"split in time: the first {train_fraction:g} of each trace's duration is the training part, the rest "
        "held out; from the training part only: a marker's principal axis, the inhalation-positive sign "
        "(inspiration is the shorter phase), the sampling rate, the cycle detector's period and typical "
        f"excursion, and the linear amplitude -> volume calibration ({tidal_volume_ml:g} mL tidal volume); "
        "cycles split at detected inspiration onsets with detected end-inhale peaks (the same detector for "
        "RPM and markers, with the training part's period and excursion in both parts); the complete cycles "
        "of each part are its cycles. model/lujan_rms_percent and shared_shape (model, lujan, fourier): "
        "shape parameters from the training cycles only; each held-out cycle gets its onsets and peak time "
        "and a least-squares gain, offset and linear drift (3 numbers; shared_shape_no_drift: 2; anchored: "
        "none fitted, gain/offset/drift solved from the levels at the 3 anchors). RMS as % of the median "
        "per-cycle peak-to-peak of the held-out cycles (percent_of_trace_range: of the held-out trace's "
        "whole range). Not held out: fourier_insample_rms_percent and per_cycle_refit_insample, each "
        "held-out cycle fitted to itself (in-sample).")


def summarise(traces: dict, errors: dict, tidal_volume_ml: float, train_fraction: float) -> dict:
    """The metrics document of scored ``traces`` (and the ``errors`` of the others): per-trace
    scores, medians of every held-out variant, the paired PV-vs-Lujan comparison, the target and
    protocol, and apart (``in_sample``) the medians of the per-cycle refits."""
    models = holdout.MODELS

    def med(key, sub=None):
        return _median(traces, key, sub)

    normal = {k: v for k, v in traces.items() if "-N-" in k or "-NO-" in k}
    diff = np.array([r["shared_shape"]["model"] - r["shared_shape"]["lujan"] for r in traces.values()])
    return {
        "traces": traces,
        "median_model_rms_percent": med("model_rms_percent"),
        "median_lujan_rms_percent": med("lujan_rms_percent"),
        "median_shared_shape": {m: med(m, "shared_shape") for m in models},
        "median_shared_shape_no_drift": {m: med(m, "shared_shape_no_drift") for m in models},
        "median_anchored": {m: med(m, "anchored") for m in models},
        "median_percent_of_trace_range": {m: med(m, "percent_of_trace_range") for m in models},
        "median_regular_cycles": {m: med(m, "regular_cycles") for m in models},
        "median_noise_floor_percent": med("noise_floor_percent"),
        "median_model_rms_percent_regular_sessions": (
            float(np.median([r["model_rms_percent"] for r in normal.values()])) if normal else None),
        "paired_model_vs_lujan": {"traces_model_better": int((diff < 0).sum()), "traces": int(diff.size),
                                  "median_difference_percent": float(np.median(diff))},
        "in_sample": {"median_fourier_insample_rms_percent": med("fourier_insample_rms_percent"),
                      "median_per_cycle_refit_insample": {m: med(m, "per_cycle_refit_insample") for m in models}},
        "target_median_model_rms_percent": TARGET_MEDIAN_MODEL_RMS_PERCENT,
        "n_traces": len(traces),
        "errors": errors,
        "protocol": protocol(tidal_volume_ml, train_fraction),
    }


def validate_breathing(data: Path, out: Path, tidal_volume_ml: float = 500.0, train_fraction: float = 0.5,
                       progress: Progress | None = None) -> dict:
    """Score every trace under the folder ``data`` (:func:`score_traces`) and write
    ``out/metrics.json`` (:func:`summarise`; ``out`` created); returns the metrics. ``tidal_volume_ml``:
    the calibration (mL); ``train_fraction``: the share of each trace's cycles fitted."""
    traces, errors = score_traces(data, tidal_volume_ml, train_fraction, progress)
    metrics = summarise(traces, errors, tidal_volume_ml, train_fraction)
    Path(out).mkdir(parents=True, exist_ok=True)
    write_json(Path(out) / "metrics.json", metrics, strict=True)
    return metrics
