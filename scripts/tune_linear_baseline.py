"""Tune the linear autoregressive baseline of ``lungdeform validate prediction`` by a recorded grid search.

Why: the model's settings (:class:`lungdeform.breathing.predict.BlendPredictor`) were chosen on the
16 shared breathing traces (docs/PREDICTION.md lists the variants tried), so the baseline it is
compared with gets a search of its own, on the same traces, scored the same way, over every setting
:class:`lungdeform.breathing.predict.LinearPredictor` has: the window, the training memory (a
sliding window of ``train_s`` seconds, or every pair with a forgetting half-life, or every pair
unweighted), the refit interval and the ridge. The criterion uses the baseline alone (never the
model): the geometric mean over traces and horizons of the per-trace RMS ratio baseline / no
prediction, on the samples ``validate prediction`` scores (30 s warm-up; the same horizons): every
trace weighs the same. (A first search ranked by the median over traces instead: the 16 traces fall
in two groups, quiet near 0.3 and irregular near 0.8, and the median, between them, rests on a few
traces; the setting it picked, 10 s of memory, was worse than the untuned baseline on 11 of the 16
traces at 500 ms.)

Usage (from the repository root; a few minutes on a quiet machine)::

    LUNGDEFORM_DATA=/work/shared/data .venv/bin/python scripts/tune_linear_baseline.py \\
        --data $LUNGDEFORM_DATA/breathing-traces --out linear_search.json [--check]

It prints the best settings, the ten best and the leave-one-trace-out check (for each trace, the
settings chosen on the other traces by the same criterion, scored on that trace), and writes every
setting's per-trace figures to ``--out``. ``--check`` first runs the online
:class:`~lungdeform.breathing.predict.LinearPredictor` and this script's replay of it on one trace
for a few settings and stops if they differ (the replay is only a faster way to run the same
predictor over a recorded trace: it refits at the same samples, on the same pairs, with the same
weights).

The replay: features and targets are the online predictor's (differences from the newest sample on
the trace's own sample interval, read by linear interpolation; a pair is learned once a sample at or
after its target time has arrived); the normal equations are updated only at the samples where the
online predictor refits, from the pairs learned by then, so one run costs a few solves per second
of trace instead of a Python call per sample.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lungdeform.breathing.predict import EPS_S, LinearPredictor, LinearSettings
from lungdeform.breathing.trace import read_trace
from lungdeform.validate.breathing import trace_files
from lungdeform.validate.prediction import HORIZONS_MS, WARM_S, scored_rms

#: The search (docs/PREDICTION.md "The linear baseline, tuned"), in three stages, as a person tunes:
#: 1. every window × memory at refit 1 s and ridge 1e-3 (the model's linear part's refit and ridge order);
#: 2. at the eight best of stage 1, every refit interval × ridge;
#: 3. every window × memory again at the best refit and ridge of stage 2 (skipped when stage 2 kept
#:    stage 1's); the best of all the settings scored is the baseline.
WINDOWS_S = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0)
#: ("sliding", train_s): the pairs of the last train_s s, unweighted; ("forget", half-life s): every
#: pair, weighted 0.5^(age / half-life); ("all", None): every pair, unweighted
MEMORIES = (("sliding", 5.0), ("sliding", 10.0), ("sliding", 15.0), ("sliding", 30.0), ("sliding", 60.0),
            ("sliding", 120.0), ("forget", 5.0), ("forget", 10.0), ("forget", 15.0), ("forget", 30.0), ("forget", 60.0),
            ("forget", 120.0), ("forget", 300.0), ("all", None))
REFITS_S = (0.5, 1.0, 5.0)
RIDGES = (0.0, 1e-4, 1e-3, 1e-2)
STAGE1_REFIT_S, STAGE1_RIDGE = 1.0, 1e-3
STAGE2_TOP = 8


@dataclass(frozen=True)
class Setting:
    """One point of the grid, in :class:`LinearPredictor`'s terms."""

    window_s: float
    memory: str
    memory_s: float | None
    refit_s: float
    ridge: float

    @property
    def linear(self) -> LinearSettings:
        """The same setting as :class:`lungdeform.breathing.predict.LinearSettings`."""
        return LinearSettings(self.window_s, self.memory_s if self.memory == "sliding" else None,
                              self.memory_s if self.memory == "forget" else None, self.refit_s, self.ridge)

    def predictor(self, horizon_s: float, dt_s: float) -> LinearPredictor:
        return self.linear.predictor(horizon_s, dt_s)

    @property
    def text(self) -> str:
        mem = ("all pairs" if self.memory == "all" else
               f"last {self.memory_s:g} s" if self.memory == "sliding" else f"half-life {self.memory_s:g} s")
        return f"window {self.window_s:g} s, {mem}, refit {self.refit_s:g} s, ridge {self.ridge:g}"


def stage1(refit_s: float = STAGE1_REFIT_S, ridge: float = STAGE1_RIDGE) -> list[Setting]:
    """Every window × memory at one refit interval and ridge."""
    return [Setting(w, m, ms, refit_s, ridge) for w, (m, ms) in itertools.product(WINDOWS_S, MEMORIES)]


def stage2(best: list[Setting]) -> list[Setting]:
    """Every refit interval × ridge at each of ``best``."""
    return [Setting(b.window_s, b.memory, b.memory_s, r, lam) for b in best for r in REFITS_S for lam in RIDGES]


def rows_of(t: np.ndarray, x: np.ndarray, n_lags: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(has (n,) bool, rows (n, L + 1))``: where the online predictor has features, and its rows
    ``[x(t − k·dt) − x(t) for k = 1…L−1, x(t), 1]``."""
    has = t - t[0] >= (n_lags - 1) * dt - EPS_S
    lags = t[:, None] - dt * np.arange(1, n_lags)[None, :]
    feats = np.interp(lags, t, x) - x[:, None]
    return has, np.hstack([feats, x[:, None], np.ones((t.size, 1))])


def replay(t: np.ndarray, x: np.ndarray, horizon_s: float, s: Setting, dt: float, rows=None) -> np.ndarray:
    """The predictions ``(n,)`` of ``s.predictor(horizon_s, dt)`` run over ``(t, x)`` (module doc);
    ``rows``: :func:`rows_of` for this window, if known."""
    n_lags = max(2, round(s.window_s / dt) + 1)
    has, rows = rows if rows is not None else rows_of(t, x, n_lags, dt)
    idx = np.flatnonzero(has)  # the pairs, in the order they are queued
    tp = t[idx]
    target = np.interp(tp + horizon_s, t, x) - x[idx]
    # pairs learned by the time each pair's sample arrives (its own target is never among them)
    learned_at = np.searchsorted(tp, tp + EPS_S - horizon_s, side="right")
    normal = _Normal(rows[idx], target, tp, s)
    pred = x.copy()
    k, coef = 0, None
    while k < idx.size:  # k: a sample where the online predictor refits
        new = normal.solve(int(learned_at[k]), n_lags)
        if new is None:  # too few pairs or singular: the last fit (if any) kept, tried again next sample
            if coef is not None:
                pred[idx[k]] = x[idx[k]] + rows[idx[k]] @ coef
            k += 1
            continue
        coef, end = new, next_refit(tp, k, s.refit_s)
        pred[idx[k:end]] = x[idx[k:end]] + rows[idx[k:end]] @ coef
        k = end
    return pred


def next_refit(tp: np.ndarray, k: int, refit_s: float) -> int:
    """The first index after ``k`` whose time is at least ``refit_s`` after ``tp[k]`` (the online
    predictor's test ``t − t_fit >= refit_s``, rounding included); ``tp.size`` if none."""
    end = max(int(np.searchsorted(tp, tp[k] + refit_s, side="left")), k + 1)
    while end - 1 > k and tp[end - 1] - tp[k] >= refit_s:
        end -= 1
    while end < tp.size and not tp[end] - tp[k] >= refit_s:
        end += 1
    return end


class _Normal:
    """The normal equations of the pairs learned so far, as the online predictor keeps them."""

    def __init__(self, rows, target, tp, s: Setting):
        self.rows, self.target, self.tp, self.s = rows, target, tp, s
        m = rows.shape[1]
        self.a, self.b, self.t_acc, self.done = np.zeros((m, m)), np.zeros(m), None, 0

    def solve(self, learned: int, n_lags: int):
        """The refit on the first ``learned`` pairs: coefficients, or None (too few pairs, singular)."""
        s, tp = self.s, self.tp
        if s.memory == "sliding":
            lo = int(np.searchsorted(tp, tp[learned - 1] - s.memory_s - EPS_S, side="left")) if learned else 0
            r, y = self.rows[lo:learned], self.target[lo:learned]
            a, b, n = r.T @ r, r.T @ y, learned - lo
        else:
            if learned > self.done:
                r, y, tn = self.rows[self.done:learned], self.target[self.done:learned], tp[self.done:learned]
                w = np.ones(tn.size)
                if s.memory == "forget":
                    w = 0.5 ** ((tn[-1] - tn) / s.memory_s)
                    if self.t_acc is not None:
                        decay = 0.5 ** ((tn[-1] - self.t_acc) / s.memory_s)
                        self.a, self.b = self.a * decay, self.b * decay
                rw = r * w[:, None]
                self.a, self.b = self.a + rw.T @ r, self.b + rw.T @ y
                self.t_acc, self.done = tn[-1], learned
            a, b, n = self.a, self.b, learned
        if n <= n_lags:
            return None
        m = a.shape[0]
        reg = s.ridge * np.trace(a) / m * np.eye(m)
        reg[-1, -1] = 0.0
        try:
            return np.linalg.solve(a + reg, b)
        except np.linalg.LinAlgError:
            return None


def online(t, x, horizon_s: float, s: Setting, dt: float) -> np.ndarray:
    p = s.predictor(horizon_s, dt)
    return np.array([p.update(ti, xi) for ti, xi in zip(t, x)])


def check(traces: dict, settings) -> float:
    """Largest relative difference between the replay and the online predictor on the first trace."""
    t, x, dt = next(iter(traces.values()))
    worst = 0.0
    for s in settings:
        for h_ms in (100, 500):
            a, b = online(t, x, h_ms / 1000.0, s, dt), replay(t, x, h_ms / 1000.0, s, dt)
            worst = max(worst, float(np.max(np.abs(a - b)) / np.ptp(x)))
    return worst


class Scorer:
    """Each setting's ratios to no prediction, ``{trace: [ratio at each horizon]}``, computed once
    (settings scored before, in ``partial``, are read back: the search resumes)."""

    def __init__(self, traces: dict, horizons_ms, partial: Path | None = None, say=print):
        self.traces, self.horizons_ms, self.partial, self.say = traces, tuple(horizons_ms), partial, say
        self.none = {k: [scored_rms(t, x, x, h / 1000.0, WARM_S)[0] for h in horizons_ms]
                     for k, (t, x, _) in traces.items()}
        self.results: dict[Setting, dict] = {}
        self._rows: dict = {}
        if partial is not None and partial.is_file():
            done = json.loads(partial.read_text())
            if done.get("traces") == list(traces) and done.get("horizons_ms") == list(horizons_ms):
                self.results = {Setting(**d["setting"]): d["ratios"] for d in done["scored"]}

    def _rows_of(self, key: str, window_s: float):
        if (key, window_s) not in self._rows:
            t, x, dt = self.traces[key]
            self._rows[(key, window_s)] = rows_of(t, x, max(2, round(window_s / dt) + 1), dt)
        return self._rows[(key, window_s)]

    def __call__(self, settings) -> list[Setting]:
        for j, s in enumerate(settings):
            if s in self.results:
                continue
            self.results[s] = {
                k: [scored_rms(t, x, replay(t, x, h / 1000.0, s, dt, self._rows_of(k, s.window_s)), h / 1000.0,
                               WARM_S)[0] / self.none[k][i] for i, h in enumerate(self.horizons_ms)]
                for k, (t, x, dt) in self.traces.items()}
            if (j + 1) % 10 == 0 or j + 1 == len(settings):
                self.say(f"  {len(self.results)} settings scored", file=sys.stderr, flush=True)
                self.save()
        return list(settings)

    def save(self) -> None:
        if self.partial is None:
            return
        tmp = self.partial.with_suffix(".tmp")
        tmp.write_text(json.dumps({"traces": list(self.traces), "horizons_ms": list(self.horizons_ms),
                                   "scored": [{"setting": asdict(s), "ratios": r} for s, r in self.results.items()]}))
        tmp.replace(self.partial)


def search(scorer: Scorer, names) -> dict:
    """The three stages (:data:`WINDOWS_S` …): ``{"stage1": [...], "stage2": [...], "stage3": [...], "best"}``."""
    def rank(settings):
        return sorted(settings, key=lambda s: criterion(scorer.results[s], names))

    s1 = rank(scorer(stage1()))
    s2 = rank(scorer(stage2(s1[:STAGE2_TOP])))
    top = s2[0]
    s3 = [] if (top.refit_s, top.ridge) == (STAGE1_REFIT_S, STAGE1_RIDGE) else rank(scorer(stage1(top.refit_s, top.ridge)))
    best = rank(s1 + s2 + s3)[0]
    return {"stage1": s1, "stage2": s2, "stage3": s3, "best": best}


def criterion(ratios: dict, names) -> float:
    """Geometric mean over ``names`` and the horizons of the ratio to no prediction."""
    per = np.array([ratios[n] for n in names])
    return float(np.exp(np.mean(np.log(per))))


def leave_one_trace_out(results: dict, names) -> dict:
    """For each trace, the setting (of those the search scored) best on the other traces, and its
    ratios on that trace."""
    out = {}
    for name in names:
        others = [n for n in names if n != name]
        best = min(results, key=lambda k: criterion(results[k], others))
        out[name] = {"setting": best, "ratios": results[best][name]}
    return out


def _line(results: dict, s: Setting, names) -> str:
    med = np.median(np.array([results[s][n] for n in names]), axis=0)
    return f"  {criterion(results[s], names):.4f}  {s.text}  [{' '.join(f'{v:.3f}' for v in med)}]"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--check", action="store_true", help="compare the replay with the online predictor first")
    args = ap.parse_args(argv)
    traces = {}
    for key, f in trace_files(args.data).items():
        tr = read_trace(f)
        traces[key] = (tr.t_s, tr.amplitude, float(np.median(np.diff(tr.t_s))))
    if args.check:
        picks = [Setting(2.0, "sliding", 30.0, 5.0, 0.0), Setting(1.5, "forget", 60.0, 1.0, 1e-4),
                 Setting(3.0, "all", None, 0.5, 1e-2)]
        worst = check(traces, picks)
        print(f"replay against the online predictor: largest difference {worst:.2e} of the trace's range")
        if worst > 1e-6:
            return 1
    names = list(traces)
    scorer = Scorer(traces, HORIZONS_MS, args.out.with_suffix(".partial.json"))
    found = search(scorer, names)
    plain = Setting(2.0, "sliding", 30.0, 5.0, 0.0)
    scorer([plain])
    res = scorer.results
    print(f"{len({s for k in ('stage1', 'stage2', 'stage3') for s in found[k]})} settings searched on {len(names)} traces, horizons {', '.join(map(str, HORIZONS_MS))} ms "
          "(criterion: geometric mean over traces and horizons of the ratio to no prediction; then the "
          "medians over traces per horizon)")
    for stage in ("stage1", "stage2", "stage3"):
        if found[stage]:
            print(f"{stage}: best five of {len(found[stage])}")
            for s in found[stage][:5]:
                print(_line(res, s, names))
    print("best:")
    print(_line(res, found["best"], names))
    print("linear_plain (the baseline of <= 0.7):")
    print(_line(res, plain, names))
    searched = {s: res[s] for k in ("stage1", "stage2", "stage3") for s in found[k]}
    loto = leave_one_trace_out(searched, names)
    held = np.median(np.array([v["ratios"] for v in loto.values()]), axis=0)
    picked = sorted({v["setting"].text for v in loto.values()})
    print(f"leave-one-trace-out: median ratio per horizon [{' '.join(f'{v:.3f}' for v in held)}]; settings picked: "
          + "; ".join(picked))
    doc = {"horizons_ms": list(HORIZONS_MS), "warm_s": WARM_S, "traces": names,
           "criterion": "geometric mean over traces and horizons of RMS(linear) / RMS(none)",
           "stages": {k: [asdict(s) for s in found[k]] for k in ("stage1", "stage2", "stage3")},
           "best": asdict(found["best"]), "best_criterion": criterion(res[found["best"]], names),
           "scored": [{"setting": asdict(s), "criterion": criterion(r, names), "ratios": r} for s, r in res.items()
                      if s in searched or s == plain],
           "leave_one_trace_out": {n: {"setting": asdict(v["setting"]), "ratios": v["ratios"]} for n, v in loto.items()},
           "leave_one_trace_out_medians": held.tolist()}
    args.out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
