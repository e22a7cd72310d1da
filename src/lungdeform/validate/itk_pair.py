"""The ITK right lung at two volumes: the model fitted and measured against baselines.

The experiment behind ``lungdeform validate itk-pair``.

Data (the folder itself or a parent holding ``itk-right-lung-two-volumes``):
``CT_3D_lung_fixed_mask.mha`` (smaller volume, end-exhale), ``CT_3D_lung_moving_mask.mha``
(larger volume) and the 51 landmark pairs ``CT_3D_lung_{fixed,moving}_point_set_corrected.txt``.
:func:`run_itk_pair` runs :func:`lungdeform.evaluate.pipeline.run_fit` on them (by default with the grid
mode and the baselines) and writes ``OUT/metrics.json`` (``model`` and each baseline:
``surface_mean_mm``, ``surface_rms_mm``, ``surface_p95_mm``, ``landmark_mean_mm``,
``landmark_max_mm``; the ray-casting throughput; :func:`targets_met`), ``model.npz`` and
``report.html``. The targets are measured, not asserted.

The headline ``model`` is what a user can run on a new pair with the same inputs (the two masks
and the landmarks): the surface fit with the interior landmark correction
(:mod:`lungdeform.interior.field`), whose landmark errors are measured on landmarks held out from the
correction (5-fold). Its surface is the fit of c1…c9, the stiffness field and the direction
correction (:mod:`lungdeform.fit.direction_correction`); ``model_surface_only`` is the same field with
no landmark used at all, ``model_paper_directions`` the paper's directions with the same stiffness,
``model_uniform_stiffness`` the paper's model (uniform stiffness, the paper's directions);
``model_landmark_fit`` fits c1…c9 on the surfaces and the training landmarks and moves landmarks by
its surface only. The baselines use the surfaces only; ``affine_landmarks`` and ``landmarks_tps``
are landmark-informed references scored on the same folds, so that the model is also compared
with methods that saw the same information (:func:`targets_met` reports both comparisons). Without
``landmark_fit`` the surface-only fit is the headline.
"""

from __future__ import annotations

from pathlib import Path

from lungdeform.atomic import write_json
from lungdeform.data import itk_right_lung
from lungdeform.errors import ReadError
from lungdeform.evaluate.pipeline import run_fit
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.fit.direction_correction import DEFAULT_DEGREE
from lungdeform.fit.rays import rays_per_second
from lungdeform.progress import Progress

FOLDER = "itk-right-lung-two-volumes"
FILES = ("CT_3D_lung_fixed_mask.mha", "CT_3D_lung_moving_mask.mha",
         "CT_3D_lung_fixed_point_set_corrected.txt", "CT_3D_lung_moving_point_set_corrected.txt")
#: What the model file's provenance says ran the fit.
COMMAND = "validate itk-pair"
#: Rays cast on the embedded ITK right lung to measure the ray-casting throughput.
RAYS = 1_000_000

#: The baselines (surfaces only) and the landmark-informed references the targets compare with.
BASELINES = ("no_motion", "affine", "apex_scaling", "cpd")
REFERENCES = ("affine_landmarks", "landmarks_tps")


def find_pair(data: Path) -> list[Path]:
    """The four files of the pair under ``data`` (or ``data/itk-right-lung-two-volumes``)."""

    data = Path(data)
    for folder in (data, data / FOLDER):
        if all((folder / f).is_file() for f in FILES):
            return [folder / f for f in FILES]
    missing = [f for f in FILES if not (data / f).is_file() and not (data / FOLDER / f).is_file()]
    raise ReadError(f"{data}: not the ITK lung pair folder (missing {', '.join(missing)})")


def pair_config(*, grid: bool = True, stiffness: bool = True, max_evaluations: int = 300, landmark_fit: bool = True,
                folds: int = 5, direction_degree: int = DEFAULT_DEGREE) -> FitConfig:
    """The experiment's fit: the given switches, and with ``landmark_fit`` the landmark-informed
    comparison fits too (:attr:`lungdeform.fit.config.FitConfig.landmark_comparisons`)."""

    return FitConfig(grid=grid, stiffness=stiffness, max_evaluations=max_evaluations, landmark_fit=landmark_fit,
                     folds=folds, direction_degree=direction_degree, landmark_comparisons=landmark_fit,
                     command=COMMAND)


def run_itk_pair(files, out: Path, config: FitConfig | None = None, *,
                 progress: Progress | None = None) -> dict:
    """Fit the right lung of the pair ``files`` (:func:`find_pair`) with ``config`` (default
    :func:`pair_config`) into the folder ``out``; measure the ray-casting throughput and the
    targets (:func:`targets_met`); rewrite ``out/metrics.json`` with them; return the metrics."""

    fixed, moving, lm_fixed, lm_moving = files
    fitted = run_fit(FitInputs([fixed, moving], "right", landmarks=[lm_fixed, lm_moving]), out,
                     pair_config() if config is None else config, progress=progress)
    rate, faces = rays_per_second(itk_right_lung(), RAYS)
    metrics = {**fitted, "ray_throughput": {"rays_per_s": rate, "rays": RAYS, "faces": faces,
                                            "surface": "embedded itk_right_lung"},
               "targets_met": targets_met(fitted)}
    write_json(Path(out) / "metrics.json", metrics, strict=True, default=str)
    return metrics


def targets_met(metrics: dict) -> dict[str, bool]:
    """The pair's targets, measured: the headline model's held-out landmark mean error below 2 mm
    and below every surface baseline's, its surface mean error below 1.4 mm; plus the like-for-like
    comparison with the landmark-informed references when the headline model used landmarks."""
    base = [k for k in BASELINES if k in metrics]
    model = metrics["model"]
    out = {
        "model landmark_mean_mm < 2.0": model["landmark_mean_mm"] < 2.0,
        "model landmark_mean_mm below every baseline": all(
            model["landmark_mean_mm"] < metrics[b]["landmark_mean_mm"] for b in base),
        "model surface_mean_mm < 1.4": model["surface_mean_mm"] < 1.4,
    }
    refs = [k for k in REFERENCES if k in metrics]
    if refs:
        out["model landmark_mean_mm below the landmark-informed references"] = all(
            model["landmark_mean_mm"] < metrics[r]["landmark_mean_mm"] for r in refs)
    return out
