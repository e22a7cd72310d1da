"""Breathing curves: volume over time, the PV loop, residuals, and the prediction's errors and an
excerpt of its predictions (``lungdeform breathe``, ``validate breathing``, ``validate prediction``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from .figure import new_figure


def breathing_volume(t_s: np.ndarray, volume_ml: np.ndarray, title: str, *, data=None,
                     held_out_from: float | None = None) -> Figure:
    """Volume (mL) against time (s); ``data = (t_s, volume_ml)`` of a calibrated trace drawn under it;
    ``held_out_from``: shade the held-out cycles from that time on."""
    fig = new_figure(10.0, 3.6, layout="constrained")
    ax = fig.subplots()
    if data is not None:
        ax.plot(data[0], data[1], lw=0.7, color="0.5", label="trace (calibrated)")
    ax.plot(t_s, volume_ml, lw=1.0, color="C0", label="PV model")
    if held_out_from is not None:
        ax.axvspan(held_out_from, t_s[-1], color="C1", alpha=0.08, label="held-out cycles")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("volume (mL)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    return fig


def pv_loop(pressure_cmh2o: np.ndarray, volume_ml: np.ndarray, title: str) -> Figure:
    """Volume (mL) against muscle pressure (cmH2O) over the breath."""
    fig = new_figure(4.8, 4.2, layout="constrained")
    ax = fig.subplots()
    ax.plot(pressure_cmh2o, volume_ml, lw=0.8)
    ax.set_xlabel("muscle pressure P_mus (cmH2O)")
    ax.set_ylabel("volume (mL)")
    ax.set_title(title, fontsize=10)
    return fig


def residuals(t_s: np.ndarray, resid: np.ndarray, title: str, ylabel: str = "residual (mL)") -> Figure:
    """A residual against time (s) with the zero line."""
    fig = new_figure(10.0, 3.0, layout="constrained")
    ax = fig.subplots()
    ax.plot(t_s, resid, lw=0.7)
    ax.axhline(0.0, color="0.4", lw=0.5)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    return fig


def prediction_errors(horizons_ms: np.ndarray, model_over_linear: dict[str, Sequence[float]],
                      model_over_none: dict[str, Sequence[float]]) -> Figure:
    """Prediction error against horizon: per trace (thin lines) and their median (thick), as the
    model's RMS over the linear baseline's (left) and over no prediction (right); 1 = no better."""
    fig = new_figure(10.0, 3.8, layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    for ax, curves, title in ((axes[0], model_over_linear, "model / linear autoregression"),
                              (axes[1], model_over_none, "model / no prediction (last sample)")):
        rows = np.array([c for c in curves.values()], float)
        for c in rows:
            ax.plot(horizons_ms, c, color="0.7", lw=0.7)
        ax.plot(horizons_ms, np.nanmedian(rows, axis=0), "o-", color="C0", lw=2.0, label="median over traces")
        ax.axhline(1.0, color="0.3", lw=0.8, ls="--")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("prediction horizon (ms)")
        ax.set_ylabel("RMS ratio")
        ax.legend(loc="upper left", fontsize=8)
    return fig


def prediction_excerpt(t_s: np.ndarray, signal: np.ndarray, predictions: dict[str, np.ndarray],
                       horizon_s: float, *, start_s: float, title: str, unit: str = "",
                       length_s: float = 30.0) -> Figure:
    """``length_s`` of a trace from ``start_s`` with each predictor's predictions drawn at the time
    they predict (``t + horizon_s``), so a good prediction lies on the signal."""
    fig = new_figure(10.0, 3.6, layout="constrained")
    ax = fig.subplots()
    keep = (t_s >= start_s) & (t_s <= start_s + length_s)
    ax.plot(t_s[keep], signal[keep], color="black", lw=1.6, label="signal")
    styles = {"model": ("C0", "-"), "linear": ("C1", "--"), "none": ("0.55", ":")}
    for name, p in predictions.items():
        shown = keep & (t_s + horizon_s <= start_s + length_s)
        colour, ls = styles.get(name, (None, "-"))
        ax.plot(t_s[shown] + horizon_s, p[shown], color=colour, ls=ls, lw=1.0, label=f"{name} (made {horizon_s * 1000:.0f} ms earlier)")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"signal ({unit})" if unit else "signal")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper right", fontsize=8, ncols=2)
    return fig
