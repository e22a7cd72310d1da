"""``lungdeform bench fit``: the model's fit of a patient against the registration it would replace.

On the two lung masks of one two-volume subject (a DIR-Lab COPDgene case: expiration and
inspiration, both lungs in one label, landmarks), in one run:

- **the model**: both lungs fitted by :func:`lungdeform.evaluate.pipeline.run_fit` with the
  configuration the caller passes (``lungdeform bench fit`` passes ``validate copd``'s own,
  :func:`lungdeform.validate.copd.copd_config`), timed as ``validate copd`` times it
  (``model_fit_seconds``: reading and splitting the masks, the fit, the refinement, the correspondence
  field, the landmark correction held out, the model file and report; the pipeline's baselines, timed
  apart inside it, left out); what it achieved: each lung's model surface mean distance
  (``metrics["model"]["surface_mean_mm"]``);
- **elastix** (``itk-elastix``, the optional extra ``bench``): the model zoo's lung settings Par0011
  (:data:`PAR0011_AFFINE` then :data:`PAR0011_BSPLINE`) registering the expiration mask onto the
  inspiration mask, both smoothed by a Gaussian of :data:`SMOOTH_SIGMA_MM` (timed: reading, smoothing,
  registration); what it achieved: per lung, the symmetric surface distance (area-weighted mean, mm)
  between the warped expiration mask (≥ 0.5) and the inspiration mask, each split into its lungs and
  each lung's surface extracted as the fit extracts it (:func:`warped_surface_distance`).

Both run with the same number of threads: ITK's pool threader (global default threader and thread
count), numba's thread count and the BLAS of NumPy and SciPy (each bundles its own OpenBLAS; bounded
by :func:`lungdeform.blas.limited`, inside which the fit's dense steps bound themselves to one).
Each is run once untimed on a small phantom first (:func:`write_phantom_case`: imports, compiled
kernels, ITK's lazily loaded modules; the fit without its baselines and with at most 20
evaluations, elastix on its finest resolution at 5 iterations), then ``repeats`` times; the figure
is the ratio of the medians. Each side's CPU time (the process's, every thread: user +
system) is recorded too, and its ratio: on a shared machine the wall times of both grow with the
load, their CPU times much less (a thread waiting for a core costs no CPU; one spinning at a
barrier does).
"""

from __future__ import annotations

import os
import tempfile
import time
import warnings
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path

import numba
import numpy as np
import SimpleITK as sitk

from lungdeform import blas
from lungdeform.errors import InputError
from lungdeform.evaluate.pipeline import run_fit
from lungdeform.evaluate.workers import LungWorkers
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.geometry.distance import symmetric_distance
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from lungdeform.io.landmarks import write_elastix_points
from lungdeform.io.mask import mask_to_surface
from lungdeform.segment.split import SIDES, SplitCache, require_split

#: Gaussian (mm, standard deviation) that smooths both masks before elastix registers them.
SMOOTH_SIGMA_MM = 1.5

#: elastix model zoo entry Par0011 (SuperElastix ElastixModelZoo, ``models/Par0011``; Staring, Klein,
#: Reiber, Niessen and Stoel, "Pulmonary image registration with elastix using a standard
#: intensity-based algorithm", EMPIRE10 workshop, MICCAI 2010): its affine stage,
#: ``Parameters.Par0011.affine``, as settings (the output-writing flags left out: nothing is written).
PAR0011_AFFINE = {
    "FixedInternalImagePixelType": ("float",), "MovingInternalImagePixelType": ("float",),
    "FixedImageDimension": ("3",), "MovingImageDimension": ("3",),
    "Registration": ("MultiResolutionRegistration",),
    "FixedImagePyramid": ("FixedRecursiveImagePyramid",), "MovingImagePyramid": ("MovingRecursiveImagePyramid",),
    "Interpolator": ("BSplineInterpolator",), "Metric": ("AdvancedNormalizedCorrelation",),
    "Optimizer": ("AdaptiveStochasticGradientDescent",), "ResampleInterpolator": ("FinalBSplineInterpolator",),
    "Resampler": ("DefaultResampler",), "Transform": ("AffineTransform",),
    "NumberOfResolutions": ("5",), "ImagePyramidSchedule": tuple(str(n) for n in (16,) * 3 + (8,) * 3 + (4,) * 3 + (2,) * 3 + (1,) * 3),
    "AutomaticScalesEstimation": ("true",), "AutomaticTransformInitialization": ("true",),
    "HowToCombineTransforms": ("Compose",), "MaximumNumberOfIterations": ("1000",),
    "AutomaticParameterEstimation": ("true",), "UseAdaptiveStepSizes": ("true",),
    "ErodeMask": ("false",), "UseDirectionCosines": ("true",), "ShowExactMetricValue": ("false",),
    "ImageSampler": ("RandomCoordinate",), "NumberOfSpatialSamples": ("2000",), "NewSamplesEveryIteration": ("true",),
    "UseRandomSampleRegion": ("false",), "MaximumNumberOfSamplingAttempts": ("5",),
    "BSplineInterpolationOrder": ("1",), "FinalBSplineInterpolationOrder": ("3",), "DefaultPixelValue": ("0",),
}
#: Par0011's first B-spline stage, ``Parameters.Par0011.bspline1_s`` (same source): normalised
#: correlation plus 0.05 × bending energy, final grid 10 mm, five resolutions.
PAR0011_BSPLINE = {
    **{k: PAR0011_AFFINE[k] for k in ("FixedInternalImagePixelType", "MovingInternalImagePixelType",
                                      "FixedImageDimension", "MovingImageDimension", "FixedImagePyramid",
                                      "MovingImagePyramid", "Interpolator", "Optimizer", "ResampleInterpolator",
                                      "Resampler", "NumberOfResolutions", "ImagePyramidSchedule",
                                      "HowToCombineTransforms", "MaximumNumberOfIterations",
                                      "AutomaticParameterEstimation", "UseAdaptiveStepSizes", "ErodeMask",
                                      "UseDirectionCosines", "ShowExactMetricValue", "ImageSampler",
                                      "NumberOfSpatialSamples", "NewSamplesEveryIteration", "UseRandomSampleRegion",
                                      "BSplineInterpolationOrder", "FinalBSplineInterpolationOrder",
                                      "DefaultPixelValue")},
    "Registration": ("MultiMetricMultiResolutionRegistration",),
    "Metric": ("AdvancedNormalizedCorrelation", "TransformBendingEnergyPenalty"),
    "Transform": ("BSplineTransform",),
    "FinalGridSpacingInPhysicalUnits": ("10.0", "10.0", "10.0"), "GridSpacingSchedule": ("8.0", "8.0", "4.0", "2.0", "1.0"),
    "UseRelativeWeights": ("true",), "Metric0RelativeWeight": ("1.0",), "Metric1RelativeWeight": ("0.05",),
    "SampleRegionSize": ("50.0", "50.0", "50.0"), "MaximumNumberOfSamplingAttempts": ("50",),
}


@dataclass(frozen=True)
class ElastixSchedule:
    """How much of Par0011 runs: every stage as published (the default), or, for a quick check, the
    last ``resolutions`` resolutions and at most ``iterations`` iterations each (None: as published)."""

    resolutions: int | None = None
    iterations: int | None = None

    def maps(self) -> list[dict[str, tuple[str, ...]]]:
        """The affine and B-spline parameter maps of this schedule."""
        return [self._cut(PAR0011_AFFINE), self._cut(PAR0011_BSPLINE)]

    def _cut(self, published: dict) -> dict:
        m = dict(published)
        if self.iterations is not None:
            m["MaximumNumberOfIterations"] = (str(int(self.iterations)),)
        if self.resolutions is not None:
            r = int(self.resolutions)
            m["NumberOfResolutions"] = (str(r),)
            m["ImagePyramidSchedule"] = published["ImagePyramidSchedule"][-3 * r:]
            if "GridSpacingSchedule" in m:
                m["GridSpacingSchedule"] = published["GridSpacingSchedule"][-r:]
        return m


@dataclass(frozen=True)
class CaseFiles:
    """One two-volume subject: ``exp_mask``, ``insp_mask`` (both lungs in one label) and their
    landmark files (elastix points, mm, row i ↔ row i); ``name`` for the report."""

    name: str
    exp_mask: Path
    insp_mask: Path
    exp_landmarks: Path
    insp_landmarks: Path


def _itk():
    """The ``itk`` package with the modules the bench uses loaded. ITK's SWIG modules warn
    (DeprecationWarning, no ``__module__``) while they load, and a warning turned into an error
    there crashes the interpreter (pytest's ``filterwarnings = error``): they load with those
    warnings silenced."""
    try:
        import itk
    except ImportError:
        raise InputError("bench fit needs itk-elastix for its registration yardstick: "
                         "pip install 'lungdeform[bench]' (or itk-elastix)") from None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        for name in ("MultiThreaderBase", "ParameterObject", "elastix_registration_method", "GetImageFromArray",
                     "matrix_from_array", "array_from_image", "Image"):
            getattr(itk, name)
    return itk


def set_threads(threads: int) -> str:
    """ITK's global default threader to its pool threader with ``threads`` threads, numba's thread
    count to ``threads``; returns the threader's name as ITK reports it."""
    itk = _itk()
    mt = itk.MultiThreaderBase
    mt.SetGlobalDefaultThreader(mt.ThreaderTypeFromString("Pool"))
    mt.SetGlobalMaximumNumberOfThreads(int(threads))
    mt.SetGlobalDefaultNumberOfThreads(int(threads))
    numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
    return str(mt.ThreaderTypeToString(mt.GetGlobalDefaultThreader()))


def blas_threads(threads: int):
    """``(context manager, description)``: inside it, the BLAS libraries loaded (NumPy's and SciPy's
    OpenBLAS) use at most ``threads`` threads (:func:`lungdeform.blas.limited`; the fit's dense steps
    bound themselves to one inside it)."""
    return blas.limited(int(threads)), f"at most {int(threads)} per library (the fit's dense steps 1)"


def _itk_image(itk, image: sitk.Image):
    out = itk.GetImageFromArray(np.ascontiguousarray(sitk.GetArrayViewFromImage(image), dtype=np.float32))
    out.SetSpacing(image.GetSpacing())
    out.SetOrigin(image.GetOrigin())
    out.SetDirection(itk.matrix_from_array(np.asarray(image.GetDirection(), float).reshape(3, 3)))
    return out


def smoothed_mask(path: Path, sigma_mm: float = SMOOTH_SIGMA_MM) -> sitk.Image:
    """The mask of ``path`` (non-zero = lung) as float32, smoothed by a Gaussian of ``sigma_mm`` mm."""
    image = sitk.Cast(sitk.ReadImage(str(path)) != 0, sitk.sitkFloat32)
    return sitk.SmoothingRecursiveGaussian(image, float(sigma_mm))


def elastix_register(fixed: Path, moving: Path, threads: int, schedule: ElastixSchedule = ElastixSchedule()):
    """``(seconds, cpu_seconds, warped (z, y, x) float32 on the fixed grid)``: the mask ``moving``
    registered onto ``fixed`` by elastix with :class:`ElastixSchedule`'s Par0011 maps, both smoothed
    (:func:`smoothed_mask`); the seconds (wall, and the process's CPU) count reading, smoothing and
    registering."""
    itk = _itk()
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        f, m = (_itk_image(itk, smoothed_mask(p)) for p in (fixed, moving))
    with warnings.catch_warnings():  # any SWIG module still to load (see _itk)
        warnings.simplefilter("ignore", DeprecationWarning)
        params = itk.ParameterObject.New()
        for pm in schedule.maps():
            params.AddParameterMap(pm)
        warped, _ = itk.elastix_registration_method(f, m, parameter_object=params, log_to_console=False,
                                                    number_of_threads=int(threads))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    return seconds, cpu, np.asarray(itk.array_from_image(warped), np.float32)


def warped_surface_distance(warped: np.ndarray, reference: Path) -> dict[str, float]:
    """Per lung, the area-weighted mean symmetric surface distance (mm) between ``warped ≥ 0.5`` on
    the grid of the mask ``reference`` and that mask: each split into its lungs
    (:func:`lungdeform.segment.split.require_split`), each lung's surface from
    :func:`lungdeform.io.mask.mask_to_surface`, as the fit reads them."""
    ref = read_image(reference)
    moved = Image((np.asarray(warped) >= 0.5).astype(np.uint8), ref.spacing, ref.origin, ref.direction,
                  f"{reference} (warped)")
    splits = [require_split(im) for im in (moved, ref)]
    out = {}
    for k, side in enumerate(SIDES, start=1):
        a, b = (mask_to_surface(Image((sp.labels == k).astype(np.uint8), ref.spacing, ref.origin, ref.direction,
                                      f"{im.source} ({side})")) for sp, im in zip(splits, (moved, ref)))
        out[side] = float(symmetric_distance(a, b).stats.mean)
    return out


def model_fit(case: CaseFiles, config: FitConfig, work: Path,
              workers: LungWorkers | None = None) -> tuple[float, float, dict[str, float]]:
    """``(seconds, cpu_seconds, {side: model surface mean distance mm})``: both lungs of ``case``
    fitted with ``config`` into ``work/<side>`` (one :class:`~lungdeform.segment.split.SplitCache` for
    the two), timed as ``validate copd``'s ``model_fit_seconds`` (module docstring), wall and CPU, the
    baselines' left out of each. With ``workers`` (:class:`~lungdeform.evaluate.workers.LungWorkers`)
    the two lungs are fitted at once, as ``validate copd --workers 2`` fits them: the masks split here
    first, then the wall time is the split and the slower lung, the CPU time this process's and the
    workers' (``model_fit_wall_seconds``, :func:`lungdeform.validate.copd.case_seconds`)."""
    splits = SplitCache()
    if workers is not None:
        return _model_fit_at_once(case, config, work, workers, splits)
    seconds, cpu, surface = 0.0, 0.0, {}
    for side in SIDES:
        t0, c0 = time.perf_counter(), time.process_time()
        metrics = _fit_side(case, side, config, work / side, splits)
        seconds += time.perf_counter() - t0 - float(metrics["baseline_seconds"])
        cpu += time.process_time() - c0 - float(metrics["baseline_cpu_seconds"])
        surface[side] = float(metrics["model"]["surface_mean_mm"])
    return seconds, cpu, surface


def _model_fit_at_once(case: CaseFiles, config: FitConfig, work: Path, workers: LungWorkers,
                       splits: SplitCache) -> tuple[float, float, dict[str, float]]:
    """:func:`model_fit` with both lungs fitted at once by ``workers``."""
    t0, c0 = time.perf_counter(), time.process_time()
    splits.split_files([case.exp_mask, case.insp_mask])
    split_seconds = time.perf_counter() - t0
    done = workers.map(_fit_side, [(case, side, config, work / side, splits) for side in SIDES])
    seconds = split_seconds + max(d.seconds - float(d.value["baseline_seconds"]) for d in done)
    cpu = time.process_time() - c0 + sum(d.cpu_seconds - float(d.value["baseline_cpu_seconds"]) for d in done)
    return seconds, cpu, {side: float(d.value["model"]["surface_mean_mm"]) for side, d in zip(SIDES, done)}


def _fit_side(case: CaseFiles, side: str, config: FitConfig, folder: Path, splits: SplitCache) -> dict:
    """One lung of ``case`` fitted into ``folder`` (:func:`lungdeform.evaluate.pipeline.run_fit`): its metrics."""
    inputs = FitInputs([case.exp_mask, case.insp_mask], side, landmarks=[case.exp_landmarks, case.insp_landmarks],
                       splits=splits)
    return run_fit(inputs, folder, config)


@dataclass(frozen=True)
class BenchSettings:
    """``repeats`` timed runs of each (≥ 1) after one untimed warm-up on a phantom, ``threads`` for
    both, elastix's ``schedule`` (:class:`ElastixSchedule`); ``at_once``: with two threads or more,
    the model's two lungs fitted at once in two worker processes of one thread each
    (:func:`model_fit`), as ``validate copd --workers 2`` does; False: one after the other."""

    repeats: int = 3
    threads: int = os.cpu_count() or 1
    schedule: ElastixSchedule = ElastixSchedule()
    at_once: bool = True

    @property
    def workers(self) -> int:
        """Worker processes of the model's fit: 2 when ``at_once`` with 2 threads or more, else 0 (none: in this process)."""
        return 2 if self.at_once and self.threads >= 2 else 0


def bench_fit(case: CaseFiles, config: FitConfig, settings: BenchSettings = BenchSettings(), *,
              progress=None) -> dict:
    """Both sides on ``case`` (module docstring): the times of each repeat (wall and CPU), their
    medians, the ratios model / elastix, what each achieved (per lung, in the last repeat), the
    threads, threader, BLAS threads and the 1-minute load average at the start and the end."""
    if not (isinstance(settings.repeats, int) and settings.repeats >= 1):
        raise InputError(f"repeats must be a whole number >= 1, got {settings.repeats!r}")
    if not (isinstance(settings.threads, int) and settings.threads >= 1):
        raise InputError(f"threads must be a whole number >= 1, got {settings.threads!r}")
    threader = set_threads(settings.threads)
    limit, blas = blas_threads(settings.threads)
    load = [os.getloadavg()[0]]
    with limit, tempfile.TemporaryDirectory(prefix="lungdeform-bench-fit-") as tmp, \
            LungWorkers(settings.workers) if settings.workers else nullcontext() as workers:
        runs = _timed_runs(case, config, settings, Path(tmp), progress or (lambda _m: None), workers)
    load.append(os.getloadavg()[0])
    med = {k: float(np.median(runs[k])) for k in ("model", "elastix", "model_cpu", "elastix_cpu")}
    return {"case": case.name, "repeats": settings.repeats, "threads": settings.threads, "itk_threader": threader,
            "model_workers": settings.workers,
            "blas_threads": blas, "model_seconds": runs["model"], "elastix_seconds": runs["elastix"],
            "model_median_s": med["model"], "elastix_median_s": med["elastix"], "ratio": med["model"] / med["elastix"],
            "model_cpu_seconds": runs["model_cpu"], "elastix_cpu_seconds": runs["elastix_cpu"],
            "model_cpu_median_s": med["model_cpu"], "elastix_cpu_median_s": med["elastix_cpu"],
            "cpu_ratio": med["model_cpu"] / med["elastix_cpu"],
            "model_surface_mean_mm": runs["surface"], "elastix_surface_mean_mm": runs["ssd"],
            "elastix_schedule": {"resolutions": settings.schedule.resolutions, "iterations": settings.schedule.iterations},
            "load_average_1min": {"start": load[0], "end": load[1]}}


def _timed_runs(case: CaseFiles, config: FitConfig, settings: BenchSettings, work: Path, say,
                workers: LungWorkers | None) -> dict:
    """The warm-up on a phantom, then ``settings.repeats`` runs of each side: per side the wall and
    CPU seconds of every repeat, and what each achieved in the last."""
    say("warm-up on a phantom (untimed)" + (f"; the model in {workers.count} worker processes" if workers else ""))
    phantom = write_phantom_case(work / "phantom")
    model_fit(phantom, replace(config, baselines=False, max_evaluations=min(config.max_evaluations, 20)), work / "warm",
              workers)
    elastix_register(phantom.insp_mask, phantom.exp_mask, settings.threads, ElastixSchedule(1, 5))
    runs: dict = {"model": [], "elastix": [], "model_cpu": [], "elastix_cpu": [], "surface": {}, "ssd": {}}
    for k in range(settings.repeats):
        say(f"repeat {k + 1}/{settings.repeats}: the model's fit of both lungs")
        seconds, cpu, runs["surface"] = model_fit(case, config, work / f"fit{k}", workers)
        runs["model"].append(seconds)
        runs["model_cpu"].append(cpu)
        say(f"repeat {k + 1}/{settings.repeats}: elastix Par0011 (affine, then B-spline)")
        seconds, cpu, warped = elastix_register(case.insp_mask, case.exp_mask, settings.threads, settings.schedule)
        runs["elastix"].append(seconds)
        runs["elastix_cpu"].append(cpu)
        runs["ssd"] = warped_surface_distance(warped, case.insp_mask)
    return runs


def write_phantom_case(folder: Path, spacing_mm: float = 4.0) -> CaseFiles:
    """A small two-volume subject in ``folder``: two separate ellipsoid lungs (right larger) at
    expiration, the same scaled by (1.06, 1.06, 1.12) about each centre at inspiration, 8 landmarks
    per lung moved by its lung's scaling; voxels of ``spacing_mm`` (a few thousand per lung)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lungs = ((-42.0, np.array([38.0, 28.0, 50.0])), (42.0, np.array([32.0, 26.0, 48.0])))
    scale = np.array([1.06, 1.06, 1.12])
    shape = (40, 24, 36)  # z, y, x
    origin = -spacing_mm * (np.array(shape[::-1]) - 1) / 2.0
    zz, yy, xx = np.indices(shape)
    world = np.stack([xx, yy, zz], axis=-1) * spacing_mm + origin
    rng = np.random.default_rng(0)
    points: dict[str, list[np.ndarray]] = {"exp": [], "insp": []}
    for phase, sc in (("exp", np.ones(3)), ("insp", scale)):
        mask = np.zeros(shape, bool)
        for cx, axes in lungs:
            mask |= np.sum(((world - [cx, 0.0, 0.0]) / (axes * sc)) ** 2, axis=-1) <= 1.0
        im = sitk.GetImageFromArray(mask.astype(np.uint8))
        im.SetSpacing((spacing_mm,) * 3)
        im.SetOrigin(tuple(origin))
        sitk.WriteImage(im, str(folder / f"phantom_{phase}_mask.nii.gz"))
    for cx, axes in lungs:
        centre = np.array([cx, 0.0, 0.0])
        pts = centre + rng.uniform(-0.5, 0.5, (8, 3)) * axes
        points["exp"].append(pts)
        points["insp"].append(centre + (pts - centre) * scale)
    for phase in points:
        write_elastix_points(folder / f"phantom_{phase}_landmarks.txt", np.concatenate(points[phase]))
    return CaseFiles("phantom", folder / "phantom_exp_mask.nii.gz", folder / "phantom_insp_mask.nii.gz",
                     folder / "phantom_exp_landmarks.txt", folder / "phantom_insp_landmarks.txt")
