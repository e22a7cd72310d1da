"""DIR-Lab 4-D CT landmarks: loading a case, the paper's one-scalar model, richer real-time models
and their evaluation. Finding the files and reading ``voxel_spacing.csv`` is
:mod:`lungdeform.validate.dirlab_files` (its public names are re-exported here).

Data (Castillo et al. 2009, 2010): per case, 300 landmark pairs at the extreme phases T00 and T50
and 75 landmarks tracked through T00, T10, …, T50. In DIR-Lab's phase convention **T00 is
end-inhale and T50 end-exhale**, so T10–T40 are all on the *exhale* branch; the inhale branch
(T60–T90) is not sampled. True inspiration/expiration hysteresis therefore cannot be identified
from these files; the richer models below describe the shape of the exhale path only.

Frames: landmark positions are mm in the image's index-aligned frame,
``mm = (index - 1) * spacing`` (see :mod:`lungdeform.io.landmarks`); arrays are ``(n, 3) float``.

Hypotheses of the paper tested here (Sec. IV-B; docs/METHOD_NOTES.md §6–§7):

- *direction constant*: each point moves along one fixed direction ``d_i`` through the cycle;
- *magnitude linear in volume*: the displacement is ``s · u_i`` with one scalar ``s`` per volume.

Without images the lung volume of each phase is not measured; the global scalar ``s_p`` fitted by
least squares to all landmarks of phase ``p`` stands in for the volume fraction
``(V_p - V_T50) / (V_T00 - V_T50)``. The one-scalar model is therefore
``x_p = x_T50 + s_p · (x_T00 - x_T50)`` (both hypotheses at once). The richer models keep the same
single driver ``s`` per phase (what a volume signal provides at run time) and add per-landmark or
per-region parameters, each a few multiply-adds per point per frame:

``lag_*``      ``x = x50 + (s + a · b(s)) d`` — direction constant, timing differs (phase lag);
``curved_*``   ``x = x50 + s d + b(s) c``     — the path may bend (direction not constant);
``two_component`` ``x = x50 + s1 d + s2 e``   — a second global mode ``e`` (two scalars per phase).

``b(s) = sqrt(s (1 - s))`` is the first-order effect of a phase lag τ when the volume follows a
cosine, ``s = (1 + cos θ)/2``: ``s(θ - τ) ≈ s(θ) + τ sqrt(s (1 - s))``. It vanishes at T00 and
T50, so every model still passes through both extreme positions.

Held-out protocol: leave one of T10–T40 out; fit the per-landmark/per-region parameters on the
other three; on the held-out phase fit the global driver(s) on the landmarks of the *other* folds
(landmark cross-fitting, default 5 folds) and measure each landmark's error. No number that shapes
a landmark's prediction has seen that landmark at that phase.

Model choice: a case's ``best_model`` (also ``best_model_diagnostic``) is chosen on that case's own
held-out errors, so its error is optimistic: a diagnostic, not a result. The model a user would run
on a new case is the *default model* (:func:`default_models`), chosen by leave-one-case-out: for
each case, the model with the lowest mean over the OTHER cases of their held-out means; that case's
``default_model_heldout_mean_mm`` is then an honest error. :func:`pooled_choice` gives the model
chosen on all cases of the run (the default for a case outside it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lungdeform.errors import InputError, ReadError
from lungdeform.io.landmarks import as_spacing, read_dirlab_points

# Finding the files and reading voxel_spacing.csv live in dirlab_files; its public names are
# re-exported here so that ``lungdeform.validate.dirlab.discover`` etc. keep working.
from .dirlab_files import (
    PHASES,
    PUBLISHED_GEOMETRY,
    PUBLISHED_SOURCE,
    CaseFiles,
    Discovery,
    discover,
    find_cases,
    geometry_notes,
    read_voxel_spacing,
)

INTERMEDIATE = ("T10", "T20", "T30", "T40")
#: Published mean T00→T50 displacement of the 300 pairs, mm (Castillo et al. 2009 for cases 1–5,
#: Castillo et al. 2010 / the DIR-Lab site for cases 6–10).
PUBLISHED_MEAN_300_MM = {1: 3.89, 2: 4.34, 3: 6.94, 4: 9.83, 5: 7.48, 6: 10.89, 7: 11.03, 8: 14.99, 9: 7.92, 10: 7.30}
MODELS = ("one_scalar", "lag_region", "lag_landmark", "curved_region", "curved_landmark", "two_component")


# --------------------------------------------------------------------------- loading
@dataclass(frozen=True)
class CaseData:
    """Landmarks of one case in mm (index-aligned frame).

    ``pairs``: {'T00': (300, 3), 'T50': (300, 3)} or empty; ``phases``: {'T00'…'T50': (75, 3)} or empty.
    """

    case: int
    spacing: np.ndarray
    pairs: dict[str, np.ndarray]
    phases: dict[str, np.ndarray]


def load_case(files: CaseFiles) -> CaseData:
    """Read every file of a case; check that each set has one landmark count across its phases."""
    def read_set(paths: dict[str, Path]) -> dict[str, np.ndarray]:
        pts = {ph: read_dirlab_points(p, files.spacing, files.dims) for ph, p in sorted(paths.items())}
        counts = {ph: len(v) for ph, v in pts.items()}
        if len(set(counts.values())) > 1:
            detail = ", ".join(f"{paths[ph].name}: {n}" for ph, n in counts.items())
            raise ReadError(f"case {files.case}: landmark counts differ between phases ({detail})")
        return pts

    return CaseData(files.case, files.spacing, read_set(files.extreme), read_set(files.sampled))


def mean_displacement(a, b) -> float:
    """Mean Euclidean distance (mm) between corresponding rows of ``a, b : (n, 3)`` mm."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"point sets must both be (n, 3), got {a.shape} and {b.shape}")
    return float(np.linalg.norm(a - b, axis=1).mean())


# --------------------------------------------------------------------------- models
def phase_scalar(x, x50, d, rows=None) -> float:
    """Least-squares ``s`` in ``x ≈ x50 + s·d`` over ``rows`` (all by default). All arrays (n, 3) mm."""
    r = (x - x50) if rows is None else (x - x50)[rows]
    dd = d if rows is None else d[rows]
    den = float(np.sum(dd * dd))
    if den <= 0:
        raise InputError("T00 and T50 landmarks coincide: the motion direction is undefined")
    return float(np.sum(r * dd) / den)


def lag_basis(s):
    """``b(s) = sqrt(s (1 - s))`` clipped to [0, 1]: first-order phase lag of a cosine volume curve."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    return np.sqrt(s * (1.0 - s))


def landmark_regions(x50, midline_x: float | None = None, levels: int = 3) -> np.ndarray:
    """``region : (n,) int``: side of the midline (x) × ``levels`` equal-count bands of z.

    ``x50 : (n, 3)`` mm. ``midline_x`` (mm) defaults to the median x of the landmarks.
    """
    x50 = np.asarray(x50, dtype=np.float64)
    mid = float(np.median(x50[:, 0])) if midline_x is None else float(midline_x)
    side = (x50[:, 0] >= mid).astype(int)
    edges = np.quantile(x50[:, 2], np.linspace(0, 1, levels + 1)[1:-1])
    band = np.searchsorted(edges, x50[:, 2], side="right")
    return side * levels + band


@dataclass(frozen=True)
class PathModel:
    """A fitted real-time path model for one case (see the module docstring for the equations).

    ``x50, d : (n, 3)`` mm; ``a : (n,)`` (lag models) or None; ``c : (n, 3)`` mm (curved models) or
    None; ``e : (n, 3)`` (two_component) or None.
    """

    kind: str
    x50: np.ndarray
    d: np.ndarray
    a: np.ndarray | None = None
    c: np.ndarray | None = None
    e: np.ndarray | None = None

    @property
    def n_drivers(self) -> int:
        return 2 if self.kind == "two_component" else 1

    def drivers(self, x, rows=None) -> np.ndarray:
        """Global driver(s) of a phase from its landmarks ``x : (n, 3)`` (least squares over ``rows``)."""
        if self.kind != "two_component":
            return np.array([phase_scalar(x, self.x50, self.d, rows)])
        sel = slice(None) if rows is None else rows
        A = np.stack([self.d[sel].ravel(), self.e[sel].ravel()], axis=1)
        sol, *_ = np.linalg.lstsq(A, (x - self.x50)[sel].ravel(), rcond=None)
        return sol

    def predict(self, drivers) -> np.ndarray:
        """Positions ``(n, 3)`` mm for the driver(s) of one phase."""
        drv = np.atleast_1d(np.asarray(drivers, dtype=np.float64))
        s = float(drv[0])
        if self.kind == "one_scalar":
            return self.x50 + s * self.d
        if self.kind.startswith("lag"):
            return self.x50 + (s + self.a[:, None] * lag_basis(s)) * self.d
        if self.kind.startswith("curved"):
            return self.x50 + s * self.d + lag_basis(s) * self.c
        return self.x50 + s * self.d + float(drv[1]) * self.e


def fit_path_model(kind: str, x00, x50, train, regions=None) -> PathModel:
    """Fit a :class:`PathModel` of ``kind`` (one of :data:`MODELS`).

    ``x00, x50 : (n, 3)`` mm (end-inhale, end-exhale); ``train``: list of ``(n, 3)`` mm positions at
    intermediate phases; ``regions : (n,) int`` for the ``*_region`` kinds. Each training phase's
    driver is its one-scalar least-squares ``s``; per-landmark/region parameters are then the
    linear least-squares solution (closed form).
    """
    if kind not in MODELS:
        raise InputError(f"model kind must be one of {', '.join(MODELS)}, got {kind!r}")
    x00 = np.asarray(x00, dtype=np.float64)
    x50 = np.asarray(x50, dtype=np.float64)
    d = x00 - x50
    if kind == "one_scalar":
        return PathModel(kind, x50, d)
    train = [np.asarray(t, dtype=np.float64) for t in train]
    if not train:
        raise InputError(f"model {kind!r} needs at least one intermediate phase to fit")
    s = np.array([phase_scalar(t, x50, d) for t in train])
    R = np.stack([t - x50 - si * d for t, si in zip(train, s)])  # (P, n, 3) residual of one-scalar
    b = lag_basis(s)  # (P,)
    n = len(x50)
    if kind.endswith("_region"):
        if regions is None:
            raise InputError(f"model {kind!r} needs regions")
        regions = np.asarray(regions)
        if regions.shape != (n,):
            raise InputError(f"regions must have shape ({n},), got {regions.shape}")
    if kind.startswith("lag"):
        num = np.einsum("p,pnk,nk->n", b, R, d)
        den = float(np.sum(b * b)) * np.sum(d * d, axis=1)
        if kind == "lag_region":
            num = np.bincount(regions, num, minlength=regions.max() + 1)[regions]
            den = np.bincount(regions, den, minlength=regions.max() + 1)[regions]
        a = np.divide(num, den, out=np.zeros(n), where=den > 0)
        return PathModel(kind, x50, d, a=a)
    if kind.startswith("curved"):
        bb = float(np.sum(b * b))
        c = np.einsum("p,pnk->nk", b, R) / bb if bb > 0 else np.zeros((n, 3))
        if kind == "curved_region":
            sums = np.stack([np.bincount(regions, c[:, k], minlength=regions.max() + 1) for k in range(3)], 1)
            cnt = np.bincount(regions, minlength=regions.max() + 1)[:, None]
            c = (sums / np.maximum(cnt, 1))[regions]
        return PathModel(kind, x50, d, c=np.ascontiguousarray(c))
    # two_component: leading mode of the one-scalar residuals across the training phases
    _, _, vt = np.linalg.svd(R.reshape(len(train), -1), full_matrices=False)
    e = vt[0].reshape(n, 3)
    return PathModel(kind, x50, d, e=np.ascontiguousarray(e))


def heldout_errors(kind: str, phases: dict[str, np.ndarray], regions=None, folds: int = 5) -> dict[str, np.ndarray]:
    """Leave-one-phase-out errors ``{phase: (n,) mm}`` over T10–T40 (protocol in the module docstring)."""
    if folds < 2:
        raise InputError(f"folds must be ≥ 2, got {folds}")
    x00, x50 = phases["T00"], phases["T50"]
    n = len(x50)
    fold = np.arange(n) % folds
    out = {}
    for h in INTERMEDIATE:
        model = fit_path_model(kind, x00, x50, [phases[p] for p in INTERMEDIATE if p != h], regions)
        pred = np.empty_like(x50)
        for k in range(folds):
            test = fold == k
            pred[test] = model.predict(model.drivers(phases[h], rows=~test))[test]
        out[h] = np.linalg.norm(pred - phases[h], axis=1)
    return out


def rounding_floor_mm(spacing, s_values, samples: int = 200_000, seed: int = 0) -> float:
    """Approximate mean error (mm) a perfect model still shows because positions are whole voxels.

    Each stored position is taken to be off by an independent uniform error in ``±spacing/2`` per
    axis; the one-scalar prediction carries ``(1 - s)·e50 + s·e00`` and the truth ``e_p``. Monte
    Carlo, fixed seed. Landmarks that stay in the same voxel have correlated errors, so a model can
    come in under this figure; read it as the scale of the noise, not a hard bound.
    """
    sp = as_spacing(spacing)
    rng = np.random.default_rng(seed)
    vals = []
    for s in np.atleast_1d(s_values):
        e = (rng.random((3, samples, 3)) - 0.5) * sp
        vals.append(np.linalg.norm(e[0] - (1 - s) * e[1] - s * e[2], axis=1).mean())
    return float(np.mean(vals))


# --------------------------------------------------------------------------- per-case evaluation
@dataclass(frozen=True)
class CaseResult:
    """Everything measured on one case. Errors are mean Euclidean distances in mm over T10–T40.

    A case with 300-pair files only (no 75-point phases) has the model fields set to None and
    empty dicts.
    """

    case: int
    n_pairs: int
    mean_displacement_300_mm: float | None
    published_300_mm: float | None
    n_tracked: int
    phase_scalars: dict[str, float]
    no_motion_mean_mm: float | None
    one_scalar_mean_mm: float | None
    one_scalar_per_phase_mm: dict[str, float]
    heldout_mean_mm: dict[str, float]
    best_model: str | None
    best_model_heldout_mean_mm: float | None
    best_single_driver_model: str | None
    rounding_floor_mm: float | None
    heldout_landmark_mm: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        return {
            "mean_displacement_300_mm": self.mean_displacement_300_mm,
            "published_300_mm": self.published_300_mm,
            "n_pairs_300": self.n_pairs,
            "n_tracked": self.n_tracked,
            "phase_scalars": self.phase_scalars,
            "no_motion_mean_mm": self.no_motion_mean_mm,
            "one_scalar_mean_mm": self.one_scalar_mean_mm,
            "one_scalar_per_phase_mm": self.one_scalar_per_phase_mm,
            "heldout_mean_mm": self.heldout_mean_mm,
            "best_model": self.best_model,
            "best_model_heldout_mean_mm": self.best_model_heldout_mean_mm,
            "best_model_diagnostic": self.best_model,
            "best_single_driver_model": self.best_single_driver_model,
            "rounding_floor_mm": self.rounding_floor_mm,
        }


def evaluate_case(data: CaseData, dims=None, folds: int = 5, models=MODELS) -> CaseResult:
    """Run every measurement of one case (see :class:`CaseResult`)."""
    if data.pairs:
        disp = mean_displacement(data.pairs["T00"], data.pairs["T50"])
        n_pairs = len(data.pairs["T00"])
    else:
        disp, n_pairs = None, 0
    if not data.phases:
        return CaseResult(data.case, n_pairs, disp, PUBLISHED_MEAN_300_MM.get(data.case), 0, {}, None, None, {},
                          {}, None, None, None, None)
    ph = data.phases
    x00, x50 = ph["T00"], ph["T50"]
    d = x00 - x50
    scal = {p: phase_scalar(ph[p], x50, d) for p in INTERMEDIATE}
    one = {p: float(np.linalg.norm(x50 + scal[p] * d - ph[p], axis=1).mean()) for p in INTERMEDIATE}
    none = float(np.mean([np.linalg.norm(ph[p] - x50, axis=1).mean() for p in INTERMEDIATE]))
    midline = None if dims is None else float((np.asarray(dims)[0] - 1) / 2.0 * data.spacing[0])
    regions = landmark_regions(x50, midline)
    per_lm = {m: np.mean(list(heldout_errors(m, ph, regions, folds).values()), axis=0) for m in models}
    held = {m: float(v.mean()) for m, v in per_lm.items()}
    best = min(held, key=held.get)
    single = {m: v for m, v in held.items() if m != "two_component"}
    return CaseResult(
        case=data.case,
        n_pairs=n_pairs,
        mean_displacement_300_mm=disp,
        published_300_mm=PUBLISHED_MEAN_300_MM.get(data.case),
        n_tracked=len(x50),
        phase_scalars=scal,
        no_motion_mean_mm=none,
        one_scalar_mean_mm=float(np.mean(list(one.values()))),
        one_scalar_per_phase_mm=one,
        heldout_mean_mm=held,
        best_model=best,
        best_model_heldout_mean_mm=held[best],
        best_single_driver_model=min(single, key=single.get) if single else best,
        heldout_landmark_mm=per_lm,
        rounding_floor_mm=rounding_floor_mm(data.spacing, list(scal.values())),
    )


def _case_means(results, exclude=None) -> dict[str, float]:
    """``{model: mean over the cases of their held-out means (mm)}`` over ``results`` with models
    (all but case ``exclude``), for the models every one of them has."""
    usable = [r for r in results if r.heldout_mean_mm and r.case != exclude]
    if not usable:
        return {}
    models = [m for m in usable[0].heldout_mean_mm if all(m in r.heldout_mean_mm for r in usable)]
    return {m: float(np.mean([r.heldout_mean_mm[m] for r in usable])) for m in models}


def default_models(results: list[CaseResult]) -> dict[int, tuple[str | None, float | None]]:
    """``{case: (default model, its held-out mean on that case, mm)}`` by leave-one-case-out: the
    model with the lowest mean of the per-case held-out means over the OTHER cases of ``results``
    (so the case's own errors play no part in its choice). ``(None, None)`` for a case without
    models, or when no other case has them (a run of one case)."""
    out: dict[int, tuple[str | None, float | None]] = {}
    for r in results:
        score = {m: v for m, v in _case_means(results, exclude=r.case).items() if m in r.heldout_mean_mm}
        if not r.heldout_mean_mm or not score:
            out[r.case] = (None, None)
            continue
        choice = min(score, key=score.get)
        out[r.case] = (choice, r.heldout_mean_mm[choice])
    return out


def pooled_choice(results: list[CaseResult]) -> dict:
    """The model chosen on all cases of ``results``: ``{"model", "mean_of_case_means_mm": {model:
    mm}, "cases"}``, the lowest mean of the per-case held-out means (None without models)."""
    means = _case_means(results)
    return {
        "model": min(means, key=means.get) if means else None,
        "mean_of_case_means_mm": means,
        "cases": [r.case for r in results if r.heldout_mean_mm],
    }


def _gain(a: np.ndarray, b: np.ndarray, n_boot: int, seed: int) -> dict:
    """Mean of ``a - b`` (per-landmark held-out errors, mm) with a bootstrap 95 % interval over landmarks."""
    diff = np.asarray(a) - np.asarray(b)
    rng = np.random.default_rng(seed)
    boots = diff[rng.integers(0, len(diff), size=(n_boot, len(diff)))].mean(axis=1)
    lo, hi = np.quantile(boots, [0.025, 0.975])
    return {"mean_mm": float(diff.mean()), "ci95_mm": [float(lo), float(hi)]}


def hypothesis_summary(results: list[CaseResult], n_boot: int = 2000, seed: int = 0) -> dict:
    """Which of the paper's hypotheses the held-out errors support, case by case.

    ``timing_gain``: one_scalar − best lag model (direction kept, per-landmark/region timing freed).
    If its 95 % bootstrap interval (over landmarks) lies above 0, one shared scalar per phase is
    refuted for that case. ``bending_gain``: best lag − best curved model (the path may bend); above 0
    refutes a constant direction. The best variants are picked on the same held-out errors, which
    flatters them slightly. A hypothesis "holds" in a case when its gain's interval includes 0 or
    lies below it.
    """
    rows = {}
    t_ref = b_ref = n = 0
    for r in results:
        per = r.heldout_landmark_mm
        lag = min((k for k in per if k.startswith("lag")), key=lambda k: per[k].mean(), default=None)
        cur = min((k for k in per if k.startswith("curved")), key=lambda k: per[k].mean(), default=None)
        if lag is None or cur is None or "one_scalar" not in per:
            continue
        n += 1
        tg = _gain(per["one_scalar"], per[lag], n_boot, seed)
        bg = _gain(per[lag], per[cur], n_boot, seed)
        t_ref += tg["ci95_mm"][0] > 0
        b_ref += bg["ci95_mm"][0] > 0
        rows[str(r.case)] = {"timing_gain": {"model": lag, **tg}, "bending_gain": {"model": cur, **bg}}
    return {
        "per_case": rows,
        "magnitude_one_scalar": f"refuted in {t_ref}/{n} cases (freeing per-point timing lowers held-out error, 95 % CI > 0)",
        "direction_constant": f"refuted in {b_ref}/{n} cases (letting paths bend lowers held-out error, 95 % CI > 0)",
    }
