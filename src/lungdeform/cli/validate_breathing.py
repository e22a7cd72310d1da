"""``lungdeform validate breathing``: fit every trace under a folder, score held-out cycles.

Finds RPM ``.vxp`` and marker ``.csv`` files under ``--data`` (recursively), runs the held-out protocol
of :mod:`lungdeform.holdout` on each (PV driver, Lujan cos^{2n}, per-cycle Fourier) and writes
``OUT/metrics.json``::

    {"traces": {"<file name>": {"model_rms_percent": …, "lujan_rms_percent": …,
                                "fourier_rms_percent": …, …}},
     "median_model_rms_percent": …, …}

A trace that cannot be read or holds too few cycles is reported under "errors" and left out of the
medians; if no trace can be scored the command fails (exit 2).
"""

from __future__ import annotations

from pathlib import Path

import typer

from .common import say


def find_traces(data: Path) -> list[Path]:
    files = [p for p in Path(data).rglob("*") if p.is_file() and p.suffix.lower() in (".vxp", ".csv")]
    return sorted(files, key=lambda p: str(p))


def validate_breathing(data: Path, out: Path, tidal_volume_ml: float = 500.0, train_fraction: float = 0.5,
                       progress=None) -> dict:
    import numpy as np

    from lungdeform.atomic import write_text
    from lungdeform.cli.breathe import _clean, to_json
    from lungdeform.errors import InputError, LungdeformError
    from lungdeform.holdout import evaluate
    from lungdeform.trace import read_trace

    data = Path(data)
    if not data.is_dir():
        raise InputError(f"--data {data}: not a folder")
    files = find_traces(data)
    if not files:
        raise InputError(f"--data {data}: no .vxp or .csv trace found")
    traces, errors = {}, {}
    for f in files:
        if progress:
            progress(f"fitting {f.name}")
        try:
            res = evaluate(read_trace(f), tidal_volume_ml=tidal_volume_ml, train_fraction=train_fraction)
        except LungdeformError as exc:
            errors[f.name] = " ".join(str(exc).split())
            continue
        res.pop("_curves")
        traces[f.name] = res
    if not traces:
        raise InputError(f"--data {data}: no trace could be scored ({len(errors)} failed; first: "
                         f"{next(iter(errors.items()))[1]})")

    def med(key, sub=None):
        vals = [(r[sub][key] if sub else r[key]) for r in traces.values()]
        return float(np.median(vals))

    normal = {k: v for k, v in traces.items() if "-N-" in k or "-NO-" in k}
    metrics = {
        "traces": traces,
        "median_model_rms_percent": med("model_rms_percent"),
        "median_lujan_rms_percent": med("lujan_rms_percent"),
        "median_fourier_rms_percent": med("fourier_rms_percent"),
        "median_shared_shape": {m: med(m, "shared_shape") for m in ("model", "lujan", "fourier")},
        "median_per_cycle_refit": {m: med(m, "per_cycle_refit") for m in ("model", "lujan", "fourier")},
        "median_model_rms_percent_regular_sessions": (
            float(np.median([r["model_rms_percent"] for r in normal.values()])) if normal else None),
        "median_percent_of_trace_range": {m: med(m, "percent_of_trace_range")
                                          for m in ("model", "lujan", "fourier")},
        "target_median_model_rms_percent": 5.0,
        "n_traces": len(traces),
        "errors": errors,
        "protocol": ("cycles split at inspiration onsets (RPM: recorded Z/P marks); amplitude -> volume "
                     f"linear, {tidal_volume_ml:g} mL tidal volume; first {train_fraction:g} of the cycles fit, "
                     "later cycles held out. model/lujan_rms_percent: shape parameters from the training "
                     "cycles only, each held-out cycle gets its onsets, peak time, gain and offset. "
                     "fourier_rms_percent: K=2 Fourier series fitted to each held-out cycle itself "
                     "(in-sample). RMS as % of the median per-cycle peak-to-peak of the held-out cycles."),
    }
    Path(out).mkdir(parents=True, exist_ok=True)
    write_text(Path(out) / "metrics.json", to_json(_clean(metrics)))
    return metrics


def register(apps) -> None:
    @apps.validate.command("breathing")
    def breathing(
        data: Path = typer.Option(..., "--data", help="Folder searched for .vxp / .csv traces."),
        out: Path = typer.Option(..., "--out", help="Output folder for metrics.json."),
        tidal_volume_ml: float = typer.Option(500.0, "--tidal-volume-ml"),
        train_fraction: float = typer.Option(0.5, "--train-fraction"),
    ):
        """Fit the PV driver to every breathing trace; held-out RMS against Lujan and Fourier."""
        m = validate_breathing(data, out, tidal_volume_ml, train_fraction,
                               progress=say)
        for name, r in m["traces"].items():
            typer.echo(f"{name}: PV {r['model_rms_percent']:.2f} %  Lujan {r['lujan_rms_percent']:.2f} %  "
                       f"Fourier/cycle {r['fourier_rms_percent']:.2f} %")
        for name, err in m["errors"].items():
            typer.echo(f"skipped {name}: {err}", err=True)
        typer.echo(f"median held-out RMS: PV {m['median_model_rms_percent']:.2f} %, "
                   f"Lujan {m['median_lujan_rms_percent']:.2f} %, "
                   f"Fourier per cycle {m['median_fourier_rms_percent']:.2f} % (target PV < 5 %)")
        r = m["median_percent_of_trace_range"]
        typer.echo(f"as % of each held-out trace's whole peak-to-peak range: PV {r['model']:.2f} %, "
                   f"Lujan {r['lujan']:.2f} %, Fourier per cycle {r['fourier']:.2f} %")
        typer.echo(f"wrote {Path(out) / 'metrics.json'}")
