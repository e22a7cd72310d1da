"""``lungdeform validate breathing``: fit every trace under a folder, score held-out cycles.

Finds RPM ``.vxp`` and marker ``.csv`` files under ``--data`` (recursively), runs the held-out protocol
of :mod:`lungdeform.breathing.holdout` on each (PV driver, Lujan cos^{2n}, per-cycle Fourier) and writes
``OUT/metrics.json``::

    {"traces": {"<file name>": {"model_rms_percent": …, "lujan_rms_percent": …,
                                "fourier_rms_percent": …, …}},
     "median_model_rms_percent": …, …}

Besides the issue's keys: the medians of every calibration variant (shared_shape with drift = the
headline, shared_shape_no_drift, anchored, per_cycle_refit), the same error as a % of each held-out
trace's whole range, the score on model-free "regular" held-out cycles, the white-noise floor, and a
paired PV-vs-Lujan comparison (per trace; a comparison of two medians is not paired).
A trace that cannot be read or holds too few cycles is reported under "errors" and left out of the
medians; if no trace can be scored the command fails (exit 2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from lungdeform.atomic import write_json
from lungdeform.breathing.holdout import MODELS, evaluate
from lungdeform.breathing.holdout import MODELS as models
from lungdeform.breathing.trace import read_trace
from lungdeform.errors import InputError, LungdeformError

from .common import STRICT_EXIT, say


def _pct(x) -> str:
    """A median for the summary lines: 'n/a' where undefined (None: no finite score)."""
    return "n/a" if x is None else f"{x:.2f}"


def find_traces(data: Path) -> list[Path]:
    # by extension, case-insensitively; hidden files (e.g. macOS '._name.csv' resource forks) skipped
    files = [p for p in Path(data).rglob("*") if p.is_file() and p.suffix.lower() in (".vxp", ".csv")
             and not p.name.startswith(".")]
    return sorted(files, key=lambda p: str(p))


def validate_breathing(data: Path, out: Path, tidal_volume_ml: float = 500.0, train_fraction: float = 0.5,
                       progress=None) -> dict:

    data = Path(data)
    if not data.is_dir():
        raise InputError(f"--data {data}: not a folder")
    files = find_traces(data)
    if not files:
        raise InputError(f"--data {data}: no .vxp or .csv trace found")
    traces, errors = {}, {}
    names = [f.name for f in files]
    for f in files:
        # keyed by file name; by the path under --data when two sub-folders hold the same name
        key = f.name if names.count(f.name) == 1 else f.relative_to(data).as_posix()
        if progress:
            progress(f"fitting {key}")
        try:
            res = evaluate(read_trace(f), tidal_volume_ml=tidal_volume_ml, train_fraction=train_fraction)
        except LungdeformError as exc:
            errors[key] = " ".join(str(exc).split())
            continue
        res.pop("_curves")
        traces[key] = res
    if not traces:
        raise InputError(f"--data {data}: no trace could be scored ({len(errors)} failed; first: "
                         f"{next(iter(errors.items()))[1]})")

    def med(key, sub=None):
        vals = [(r[sub][key] if sub else r[key]) for r in traces.values()]
        vals = [v for v in vals if v is not None and np.isfinite(v)]
        return float(np.median(vals)) if vals else None

    normal = {k: v for k, v in traces.items() if "-N-" in k or "-NO-" in k}
    diff = np.array([r["shared_shape"]["model"] - r["shared_shape"]["lujan"] for r in traces.values()])
    metrics = {
        "traces": traces,
        "median_model_rms_percent": med("model_rms_percent"),
        "median_lujan_rms_percent": med("lujan_rms_percent"),
        "median_fourier_rms_percent": med("fourier_rms_percent"),
        "median_shared_shape": {m: med(m, "shared_shape") for m in models},
        "median_shared_shape_no_drift": {m: med(m, "shared_shape_no_drift") for m in models},
        "median_anchored": {m: med(m, "anchored") for m in models},
        "median_per_cycle_refit": {m: med(m, "per_cycle_refit") for m in models},
        "median_percent_of_trace_range": {m: med(m, "percent_of_trace_range") for m in models},
        "median_regular_cycles": {m: med(m, "regular_cycles") for m in models},
        "median_noise_floor_percent": med("noise_floor_percent"),
        "median_model_rms_percent_regular_sessions": (
            float(np.median([r["model_rms_percent"] for r in normal.values()])) if normal else None),
        "paired_model_vs_lujan": {"traces_model_better": int((diff < 0).sum()), "traces": int(diff.size),
                                  "median_difference_percent": float(np.median(diff))},
        "target_median_model_rms_percent": 5.0,
        "n_traces": len(traces),
        "errors": errors,
        "protocol": (
            "amplitude signed inhalation-positive (inspiration is the shorter phase); cycles split at "
            "detected inspiration onsets with detected end-inhale peaks (the same detector for RPM and "
            f"markers); amplitude -> volume linear, {tidal_volume_ml:g} mL tidal volume; first "
            f"{train_fraction:g} of the cycles fit, later cycles held out. model/lujan_rms_percent: shape "
            "parameters from the training cycles only; each held-out cycle gets its onsets and peak "
            "time and a least-squares gain, offset and linear drift (3 numbers; shared_shape_no_drift: "
            "2; anchored: none fitted, gain/offset/drift solved from the levels at the 3 anchors). "
            "fourier_rms_percent: K=2 Fourier series fitted to each held-out cycle itself (in-sample). "
            "RMS as % of the median per-cycle peak-to-peak of the held-out cycles "
            "(percent_of_trace_range: of the held-out trace's whole range)."),
    }
    Path(out).mkdir(parents=True, exist_ok=True)
    write_json(Path(out) / "metrics.json", metrics, strict=True)
    return metrics


def register(apps) -> None:
    @apps.validate.command("breathing")
    def breathing(
        data: Path = typer.Option(..., "--data", help="Folder searched for .vxp / .csv traces."),
        out: Path = typer.Option(..., "--out", help="Output folder for metrics.json."),
        tidal_volume_ml: float = typer.Option(500.0, "--tidal-volume-ml"),
        train_fraction: float = typer.Option(0.5, "--train-fraction"),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when the median target is not met (for CI)."),
    ):
        """Fit the PV driver to every breathing trace; held-out RMS against Lujan and Fourier."""

        m = validate_breathing(data, out, tidal_volume_ml, train_fraction,
                               progress=say)
        for name, r in m["traces"].items():
            typer.echo(f"{name}: PV {r['model_rms_percent']:.2f} %  Lujan {r['lujan_rms_percent']:.2f} %  "
                       f"Fourier/cycle {r['fourier_rms_percent']:.2f} %")
        for name, err in m["errors"].items():
            typer.echo(f"skipped {name}: {err}", err=True)
        typer.echo(f"median held-out RMS: PV {_pct(m['median_model_rms_percent'])} %, "
                   f"Lujan {_pct(m['median_lujan_rms_percent'])} %, "
                   f"Fourier per cycle {_pct(m['median_fourier_rms_percent'])} % (target PV < 5 %)")

        def f(d):
            return " / ".join(_pct(d[k]) for k in MODELS) + " %"

        typer.echo(f"medians PV / Lujan / Fourier: shared shape, no drift {f(m['median_shared_shape_no_drift'])}; "
                   f"anchored {f(m['median_anchored'])}; per-cycle refit {f(m['median_per_cycle_refit'])}")
        typer.echo(f"  as % of each held-out trace's whole range {f(m['median_percent_of_trace_range'])}; "
                   f"regular cycles only {f(m['median_regular_cycles'])}; "
                   f"white-noise floor {_pct(m['median_noise_floor_percent'])} %")
        p = m["paired_model_vs_lujan"]
        typer.echo(f"  PV better than Lujan on {p['traces_model_better']} of {p['traces']} traces "
                   f"(median difference {p['median_difference_percent']:+.2f} points)")
        typer.echo(f"wrote {Path(out) / 'metrics.json'}")
        median = m["median_model_rms_percent"]
        if strict and not (median is not None and median < m["target_median_model_rms_percent"]):  # NaN fails too
            raise typer.Exit(STRICT_EXIT)
