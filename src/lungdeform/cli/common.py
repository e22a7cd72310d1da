"""Helpers shared by CLI commands: the options dataclass of a command (:func:`takes`), progress output, output folders, option parsing, the rigid-structure options of dvf and warp, the dome options of build and demo (``--dome-mm``, ``--breathing``)."""

from __future__ import annotations

import dataclasses
import inspect
import math
import os
import platform
import re
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, get_type_hints

import numpy as np
import typer

from lungdeform.atomic import write_json
from lungdeform.breathing.presets import get_preset
from lungdeform.constants import GRAVITY, TIDAL_VOLUME_ML
from lungdeform.errors import InputError
from lungdeform.geometry.frame import SIDES
from lungdeform.io.dicom import folder as DF
from lungdeform.io.dicom.folder import SeriesChoice
from lungdeform.io.dicom.rtstruct import check_structure_on_ct, read_ct_series
from lungdeform.io.grid import MAX_VOXELS, MAX_VOXELS_ENV, voxel_limit
from lungdeform.io.image import is_dicom_series_path, read_image, resample_image, write_suffix
from lungdeform.model.dome import BREATHING, DomeRequest, check_excursion
from lungdeform.playback import rigid as RG
from lungdeform.playback import schedule as S
from lungdeform.playback.displacement_field import (
    FieldResult,
    State,
    check_phases,
    phase_states,
    scan_state,
    volume_state,
)
from lungdeform.playback.phases import PHASE_ZERO_HELP, check_zero, phase_schedule, scan_phase_text
from lungdeform.playback.schedule import check_reachable, read_volume_csv
from lungdeform.playback.structures import read_structure

try:  # typer ≥ 0.2x runs on its own copy of click and imports the context getter here
    from typer.main import get_current_context
except ImportError:  # an older typer runs on click itself
    from click import get_current_context


@dataclass(frozen=True)
class Verbosity:
    """The root command's typer context object (``ctx.obj``): ``--verbose`` given. Progress lines go
    to stderr when it is a terminal, or always after ``lungdeform --verbose``; so that in pipes and
    CI an error is the only line on stderr."""

    verbose: bool = False


def takes(options: type):
    """Decorator of a typer command ``body(opts)`` whose options are the fields of the dataclass
    ``options``, each annotated ``Annotated[type, typer.Option(...)]`` (or ``typer.Argument``) with
    its default (none: required). Typer gets a function whose signature lists those fields (a field
    whose type is itself such a dataclass contributes its fields, so option groups are shared between
    commands) and which calls ``body`` with one ``options(**fields)``. The command keeps ``body``'s
    name and docstring (its help)."""
    params = _option_parameters(options)

    def wrap(body):
        def command(**given):
            return body(_options_of(options, given))

        command.__name__, command.__qualname__ = body.__name__, body.__qualname__
        command.__doc__, command.__module__ = body.__doc__, body.__module__
        command.__signature__ = inspect.Signature(params, return_annotation=None)
        command.__annotations__ = {p.name: p.annotation for p in params} | {"return": None}
        return command

    return wrap


def _option_parameters(options: type) -> list[inspect.Parameter]:
    """The keyword parameters of :func:`takes` for ``options``: its fields, nested option groups
    flattened; a name given twice is refused."""
    hints = get_type_hints(options, include_extras=True)
    out = []
    for f in dataclasses.fields(options):
        kind = hints[f.name]
        if dataclasses.is_dataclass(kind):
            out += _option_parameters(kind)
            continue
        default = f.default
        if default is dataclasses.MISSING:
            default = inspect.Parameter.empty if f.default_factory is dataclasses.MISSING else f.default_factory()
        out.append(inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=kind))
    names = [p.name for p in out]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise TypeError(f"{options.__name__}: option field(s) {', '.join(twice)} given twice")
    return out


def _options_of(options: type, given: dict):
    """``options`` built from the flat keyword values ``given`` (nested groups built from theirs)."""
    hints = get_type_hints(options)
    values = {}
    for f in dataclasses.fields(options):
        kind = hints[f.name]
        values[f.name] = _options_of(kind, given) if dataclasses.is_dataclass(kind) else given[f.name]
    return options(**values)


def progress_enabled() -> bool:
    """Whether progress goes to stderr: ``--verbose`` given to the running command (its root
    context's :class:`Verbosity`), or else stderr is a terminal."""
    ctx = get_current_context(silent=True)
    settings = None if ctx is None else ctx.find_root().obj
    return (isinstance(settings, Verbosity) and settings.verbose) or sys.stderr.isatty()


def say(message: str) -> None:
    """Progress line on stderr (stdout stays for results), when :func:`progress_enabled`."""
    if progress_enabled():
        typer.echo(message, err=True)


def output_dir(path: Path, option: str = "--out") -> Path:
    """Create the output folder, or refuse a path that is an existing file or lies under one."""
    path = check_output(path, folder=True, option=option)
    path.mkdir(parents=True, exist_ok=True)
    return path


#: Help of ``lungdeform --max-voxels``.
MAX_VOXELS_HELP = (f"Largest image grid read or written, in voxels (default {MAX_VOXELS:,}: 512 x 512 x 2000 fits; "
                   f"also ${MAX_VOXELS_ENV}).")


def set_max_voxels(value: str | None) -> None:
    """``--max-voxels``: the grid-size cap of every image read or written
    (:func:`lungdeform.io.grid.voxel_limit`), passed on as :data:`~lungdeform.io.grid.MAX_VOXELS_ENV`
    so that worker processes (cohort) see it too. None leaves it as it is."""
    if value is None:
        return
    try:
        limit = voxel_limit(value)
    except InputError:
        raise InputError(f"--max-voxels must be a positive whole number of voxels, got {value!r}") from None
    os.environ[MAX_VOXELS_ENV] = str(limit)


def check_output(out: Path, inputs=(), *, folder: bool = False, writes=(), whole: bool = False,
                 option: str = "--out") -> Path:
    """Refuse, before any work, an output ``out`` that cannot be written or would destroy an input:
    a path under a regular file; a file output (``folder`` False) that is an existing folder, or a
    folder output that is an existing file; one of ``inputs`` (None entries skipped) itself, or, for
    a folder, an input at a name the command writes in it (``writes``) or anywhere in it when the
    folder is replaced as a whole (``whole``); a folder that takes no new file (read-only, no
    permission, a pseudo file system), tried with a temporary file in the nearest existing folder
    above ``out``, so that a command writing several outputs does not fail at the last one. Returns
    ``out`` as a :class:`Path`."""
    out = Path(out)
    for above in out.parents:
        if above.exists():
            if not above.is_dir():
                raise InputError(f"{option} {out}: {above} is a file, not a folder")
            _check_writable(out, above, option)
            break
    if out.exists() and out.is_dir() != folder:
        raise InputError(f"{option} {out}: an existing {'file' if folder else 'folder'} where a "
                         f"{'folder' if folder else 'file'} is meant")
    targets = [out, *(out / name for name in writes)] if folder else [out]
    for given in (Path(p) for p in inputs if p is not None):
        inside = whole and given.resolve().is_relative_to(out.resolve())
        if inside or any(_same_path(given, t) for t in targets):
            raise InputError(f"{option} {out} would overwrite the input {given}; give another output path")
    return out


def _check_writable(out: Path, folder: Path, option: str) -> None:
    """Refuse ``out`` when ``folder`` (its nearest existing folder) takes no new file."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".lungdeform-probe-"):
            pass
    except OSError as exc:
        raise InputError(f"{option} {out}: cannot write in {folder} ({exc.strerror or exc})") from None


def _same_path(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file or folder (links followed), existing or not."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def parse_vector(text: str, name: str) -> np.ndarray:
    """'x,y,z' → (3,) float."""
    try:
        v = np.array([float(t) for t in text.split(",")])
    except ValueError:
        raise InputError(f"{name} must be three numbers 'x,y,z', got {text!r}") from None
    if v.shape != (3,):
        raise InputError(f"{name} must be three numbers 'x,y,z', got {text!r}")
    return v


def parse_orientation(text: str):
    """A named orientation (supine, prone, upright, left-decubitus, right-decubitus) or 'x,y,z' (LPS)."""

    if text.strip().lower() in GRAVITY:
        return text.strip().lower()
    if not any(c.isdigit() for c in text):  # a misspelt name, not a vector: list the names
        raise InputError(f"--orientation must be one of {', '.join(GRAVITY)} or a gravity vector 'x,y,z' (LPS), "
                         f"got {text!r}")
    v = parse_vector(text, "--orientation")
    if not (np.isfinite(v).all() and np.linalg.norm(v) > 0):
        raise InputError(f"--orientation must be a non-zero finite vector 'x,y,z' (LPS), got {text!r}")
    return v


#: Largest tidal volume the commands accept, mL: above any vital capacity (a typo, e.g. a volume in µL).
MAX_TIDAL_ML = 10000.0
#: Largest volume of both lungs the commands accept, mL: above any total lung capacity.
MAX_LUNGS_ML = 20000.0


def check_number(value: float | None, option: str, lo: float, hi: float, unit: str = "", *,
                 low_open: bool = False, high_open: bool = False) -> float | None:
    """``value`` when it is a finite number in the range from ``lo`` to ``hi`` (open at an end with
    ``low_open`` / ``high_open``); None passes. Otherwise :class:`InputError` naming ``option``, the
    range and the value."""
    if value is None:
        return None
    v = float(value)
    inside = (lo < v if low_open else lo <= v) and (v < hi if high_open else v <= hi)
    if not (math.isfinite(v) and inside):
        span = f"{'(' if low_open else '['}{lo:g}, {hi:g}{')' if high_open else ']'}{' ' + unit if unit else ''}"
        raise InputError(f"{option} must be a finite number in {span}, got {value:g}")
    return value


def bounded(lo: float, hi: float, unit: str = "", *, low_open: bool = False, high_open: bool = False):
    """A typer ``callback=`` for a float option: :func:`check_number` with the option's own name, run
    as the command line is parsed, before any work. Every float option of the CLI has one
    (tests/cli/test_common.py checks)."""

    def check(param: typer.CallbackParam, value: float | None) -> float | None:
        return check_number(value, _long_name(param), lo, hi, unit, low_open=low_open, high_open=high_open)

    check.bounds = (lo, hi)
    return check


def _long_name(param) -> str:
    return max(param.opts, key=len)


def tidal_option(param: typer.CallbackParam, value: float | None) -> float | None:
    """The ``callback=`` of a tidal-volume option: :func:`check_tidal_ml` with the option's name."""
    check_tidal_ml(value, _long_name(param))
    return value


tidal_option.bounds = (0.0, MAX_TIDAL_ML)


def check_tidal_ml(value: float | None, option: str = "--tidal-ml") -> None:
    """Refuse a tidal volume that is not finite, not positive, or above :data:`MAX_TIDAL_ML` (None passes)."""
    if value is None:
        return
    if not (np.isfinite(value) and 0 < value <= MAX_TIDAL_ML):
        raise InputError(f"{option} must be a tidal volume in mL in (0, {MAX_TIDAL_ML:g}] (both lungs; quiet "
                         f"breathing ≈ 500, a vital capacity 3000–6000), got {value:g}")


def renamed_tidal_ml(tidal_ml: float | None, old: float | None, default: float = 500.0) -> float:
    """The tidal volume (mL) of a command whose ``--tidal-volume-ml`` is now ``--tidal-ml`` (as in build,
    export, track): the old name still works, hidden from the help, with a note on stderr; both
    together are refused. Neither: ``default``."""
    if old is None:
        return default if tidal_ml is None else tidal_ml
    if tidal_ml is not None:
        raise InputError("--tidal-volume-ml is the old name of --tidal-ml: give one of them")
    typer.echo("note: --tidal-volume-ml is now --tidal-ml (the old name still works)", err=True)
    return old


#: Most breaths a ``--cycles`` plays (export, track, breathe): 100 breaths of the slowest preset
#: (12 s) are 20 minutes; a million ran for hours without a word.
MAX_CYCLES = 100


def check_cycles(cycles: int | None, preset: str | None) -> None:
    """Refuse ``--cycles`` without ``--preset`` (export, track), or outside 1 to :data:`MAX_CYCLES`
    (:func:`check_cycle_count`)."""
    if cycles is not None and preset is None:
        raise InputError("--cycles applies to --preset only")
    check_cycle_count(cycles)


def check_cycle_count(cycles: int | None) -> None:
    """Refuse a ``--cycles`` below 1 or above :data:`MAX_CYCLES` (None passes)."""
    if cycles is not None and cycles < 1:
        raise InputError(f"--cycles must be >= 1, got {cycles}")
    if cycles is not None and cycles > MAX_CYCLES:
        raise InputError(f"--cycles must be at most {MAX_CYCLES}, got {cycles}")


def read_curve(curve: Path, model):
    """A ``--curve`` volume CSV (:func:`lungdeform.playback.schedule.read_volume_csv`) that ``model``'s
    lungs can follow (:func:`lungdeform.playback.schedule.check_reachable`), saying when its volumes
    read as absolute and were shifted (export, track)."""

    trace = read_volume_csv(curve)
    check_reachable(trace, model)
    if trace.shifted_ml:
        typer.echo(f"{curve}: volume_ml reads as absolute; subtracted its minimum {trace.shifted_ml:.1f} mL")
    return trace


#: Exit code of a validation command run with ``--strict`` when a target is not met.
STRICT_EXIT = 3

CONSTANTS_HELP = ("Where c1…c9 and the directions come from: 'population' (the default learned from real "
                  "subjects at two volumes, docs/DEFAULTS.md), 'paper' (Table I of Santhanam et al. 2008) or a "
                  "file written by 'lungdeform learn-default'.")
#: Help of ``--side-check/--no-side-check`` (fit, build, cohort).
SIDE_CHECK_HELP = ("Check each lung's side against its shape (the concave medial face); --no-side-check for a "
                   "lung whose shape misleads the check.")
#: Help of ``--direction-degree`` (fit, validate itk-pair, cohort).
DIRECTION_DEGREE_HELP = ("Degree of the smooth correction of the paper's directions fitted to the surfaces "
                         "(lungdeform.fit.direction_correction; 0: the paper's directions only).")


#: Library parameters of a fit (:class:`lungdeform.fit.config.FitInputs`, :class:`~lungdeform.fit.config.FitConfig`)
#: → the options that set them (fit, validate itk-pair, cohort).
FIT_OPTIONS = {"side": "--side", "volumes_ml": "--volumes", "landmarks": "--landmarks", "folds": "--folds",
               "align": "--align", "direction_degree": "--direction-degree", "max_evaluations": "--evaluations",
               "interior": "--interior", "prior": "--motion-prior", "refine_mm": "--refine-mm"}


@contextmanager
def option_names(options: dict[str, str]):
    """Say the command's option where a library error names the parameter it sets: an
    :class:`InputError` whose message begins with a key of ``options`` (``"folds must be …"``) is
    raised again with that key replaced by its option (``"--folds must be …"``)."""

    try:
        yield
    except InputError as exc:
        text = str(exc)
        for name, option in options.items():
            if re.match(rf"{re.escape(name)}\b", text):
                raise type(exc)(option + text[len(name):]) from exc
        raise


def print_fit_table(m: dict) -> None:
    """The fit metrics (``metrics.json`` of :func:`lungdeform.evaluate.pipeline.run_fit`): one table per
    target, one row per method, on stdout."""
    for tname, per in m["targets"].items():
        typer.echo(f"target {tname}: surface mean/rms/p95 mm, landmark mean/median/max mm")
        for name, v in per.items():
            typer.echo(f"  {name:<26} {v['surface_mean_mm']:6.2f} {v['surface_rms_mm']:6.2f} {v['surface_p95_mm']:6.2f}"
                       f"   {v['landmark_mean_mm']:6.2f} {v.get('landmark_median_mm', float('nan')):6.2f}"
                       f" {v['landmark_max_mm']:6.2f}")


def print_fit_warnings(m: dict) -> None:
    """One line on stderr per input warning of a fit's metrics ``m`` and per fit that stopped
    before converging (metrics.json holds them too)."""
    for text in m.get("warnings") or []:
        typer.echo(f"warning: {text}", err=True)
    for name, fit in (m.get("fit") or {}).items():
        if isinstance(fit, dict) and fit.get("success") is False:
            advice = ("it is the paper's comparison search, not the saved model" if name == "grid"
                      else "the model is its best point so far: raise --evaluations")
            typer.echo(f"warning: the {name} fit did not converge ({fit.get('message', 'no message')}); {advice}",
                       err=True)


def pick_state(model, volume_ml: float | None, scan: int | None) -> State:
    """The state ``--volume-ml`` or ``--scan`` names (exactly one)."""
    if (volume_ml is None) == (scan is None):
        raise InputError("give exactly one of --volume-ml or --scan")
    return volume_state(model, volume_ml) if scan is None else scan_state(model, scan)


def field_lines(result: FieldResult) -> list[str]:
    """What a field is, in lines for the terminal: margin, lattice, Jacobian, inversion residual."""
    i = result.info
    lines = [f"interior field on {i['nodes_evaluated']} of {i['nodes']} lattice nodes "
             f"({' x '.join(f'{x:.2g}' for x in i['node_spacing_mm'])} mm; largest lattice error inside the lungs "
             f"{i['lattice_error_mm']:.3f} mm), faded to zero {i['margin_mm']:.0f} mm outside the lungs",
             f"Jacobian determinant: min {result.jacobian_min:.3f}, max {result.jacobian_max:.3f} (no folding)"]
    if result.inverse:
        lines.append(f"inverse by fixed-point iteration: residual {i['inversion_residual_mm']:.3f} mm (largest)")
    return lines


def write_bench_json(path: Path, results: list[dict], kind: str) -> None:
    """A benchmark's records with the machine they ran on (``--json`` of ``lungdeform bench …``)."""
    doc = {"benchmark": kind, "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                          "platform": platform.platform()}, "results": results}
    write_json(path, doc)


def figure_or_na(value, digits: int = 2) -> str:
    """A summary figure for the terminal: ``n/a`` where it is undefined (None: no finite score)."""
    return "n/a" if value is None else f"{value:.{digits}f}"


def without_alignment(state: State, no_rigid: bool) -> State:
    """``state`` without the fit's alignment with ``--no-rigid`` (the field then stays in the model's
    frame, the end-exhale scan's, rather than scan K's); unchanged otherwise."""
    if not no_rigid or state.alignment is None:
        return state
    return State(state.delta_ml, None, f"{state.source}; its alignment left out (--no-rigid: the model's frame)")


# --series UID / --series-description TEXT: which CT series of a folder that holds several

SERIES_HELP = "Where a DICOM folder holds several CT series: the SeriesInstanceUID of the one to read (the refusal lists them)."
SERIES_DESCRIPTION_HELP = ("Where a DICOM folder holds several CT series: the SeriesDescription of the one to read "
                           "(equal ignoring case, else the one that contains it).")


@dataclass(frozen=True, kw_only=True)
class SeriesFlags:
    """``--series`` / ``--series-description`` (an option group of :func:`takes`): which CT series to read
    of a DICOM folder that holds several (other reconstructions, the phases of a 4-D CT)."""

    series: Annotated[str | None, typer.Option("--series", help=SERIES_HELP)] = None
    series_description: Annotated[str | None, typer.Option("--series-description", help=SERIES_DESCRIPTION_HELP)] = None

    def choice(self, several_only: bool = False) -> SeriesChoice | None:
        """The :class:`~lungdeform.io.dicom.folder.SeriesChoice` given, None without; both refused."""
        return series_choice(self.series, self.series_description, several_only)


def series_choice(uid: str | None, description: str | None, several_only: bool = False) -> SeriesChoice | None:
    """``--series`` / ``--series-description`` as a :class:`~lungdeform.io.dicom.folder.SeriesChoice`
    (None when neither is given; both together, or an empty one, refused)."""
    if uid is not None and description is not None:
        raise InputError("--series and --series-description both choose the series: give one")
    for option, value in (("--series", uid), ("--series-description", description)):
        if value is not None and not value.strip():
            raise InputError(f"{option} is empty; give the series' {'UID' if option == '--series' else 'description'}")
    if uid is None and description is None:
        return None
    return SeriesChoice(uid, description, several_only)


def dicom_input(path: Path | None, series: SeriesChoice | None = None, option: str = "") -> None:
    """For an input that is a DICOM folder: refuse it now, before any work, when the series to read
    cannot be told (several CT series and no ``--series``; :func:`lungdeform.io.dicom.folder.pick`),
    and say in one line (``note:``) what else it holds that is left out: an RTSTRUCT, RTPLAN,
    RTDOSE, a DICOMDIR followed, localizers, other series, files that are no DICOM."""
    if path is None or not Path(path).is_dir():
        return
    found = DF.survey(path)
    if not found.series and all(what == "no DICOM" for _, what in found.ignored):
        return  # no DICOM here (an archive, a dataset folder): its reader says what it makes of it
    line = DF.ignored_line(found, [DF.pick(found, series)])
    if line:
        typer.echo(f"note: {option + ' ' if option else ''}{line}")


# --rigid-structure NAME --rtstruct FILE / --rigid-mask MASK of dvf and warp: a tumour that moves
# rigidly (lungdeform.playback.rigid)

@dataclass(frozen=True, kw_only=True)
class RigidFlags:
    """The rigid-structure options of dvf and warp as given (an option group of :func:`takes`;
    :meth:`RigidOptions.of` checks them)."""

    rigid_structure: Annotated[str | None, typer.Option("--rigid-structure", help="With --rtstruct: this ROI (e.g. GTV) moves rigidly, keeping its volume (docs/RADIOTHERAPY.md, \"A rigid tumour\").")] = None
    rtstruct: Annotated[Path | None, typer.Option("--rtstruct", help="RTSTRUCT holding --rigid-structure, drawn on the input image's frame (dvf: --reference; warp: IMAGE).")] = None
    rigid_mask: Annotated[Path | None, typer.Option("--rigid-mask", help="A mask (non-zero voxels, in the input image's LPS world) that moves rigidly; instead of --rigid-structure.")] = None
    rigid_border_mm: Annotated[float, typer.Option("--rigid-border-mm", callback=bounded(0, 100, "mm", low_open=True), help="Width (mm) over which the rigid motion is blended back into the field.")] = 10.0

    @property
    def inputs(self) -> list[Path | None]:
        """The files these options read (None where not given), for :func:`check_output`."""
        return [self.rtstruct, self.rigid_mask]


@dataclass(frozen=True)
class RigidOptions:
    """The rigid-structure options: a ROI ``name`` of ``rtstruct``, or a ``mask`` image; ``border_mm``."""

    name: str | None
    rtstruct: Path | None
    mask: Path | None
    border_mm: float

    @staticmethod
    def of(flags: RigidFlags) -> RigidOptions | None:
        """Checked before any work: --rigid-structure with --rtstruct, or --rigid-mask; None without
        (``--rigid-border-mm`` is range-checked as the command line is parsed, :func:`bounded`)."""
        name, rtstruct, mask, border_mm = flags.rigid_structure, flags.rtstruct, flags.rigid_mask, flags.rigid_border_mm
        if (name is None) != (rtstruct is None):
            raise InputError("--rigid-structure and --rtstruct go together")
        if name is not None and mask is not None:
            raise InputError("--rigid-structure and --rigid-mask are mutually exclusive: give one rigid region")
        if name is None and mask is None:
            return None
        return RigidOptions(name, rtstruct, mask, float(border_mm))

    @property
    def label(self) -> str:
        return self.name if self.name is not None else str(self.mask)


def rigid_region(options: RigidOptions | None, grid, reference: tuple[str, Path] | None = None,
                 series: SeriesChoice | None = None) -> np.ndarray | None:
    """``(z, y, x) bool`` on ``grid``: the structure's voxels (inside its closed surface through the
    contours) or the mask's non-zero voxels (a mask on another grid of the same LPS world taken by
    nearest neighbour); None without options. ``reference`` = ``(option, path)``: the image whose
    world ``grid`` is in; when it is a DICOM series the structure must be drawn on it (patient,
    Frame of Reference, extent: :func:`lungdeform.io.dicom.rtstruct.check_structure_on_ct`), ``series``
    the series of it that was read (``--series``)."""
    if options is None:
        return None
    if options.name is not None:
        s = read_structure(options.rtstruct, options.name)
        for line in s.skipped:  # contours enclosing no area (a tool's tips): skipped, said
            typer.echo(f"note: {line}", err=True)
        if reference is not None and is_dicom_series_path(reference[1]):
            ct = read_ct_series(reference[1], series)
            for line in check_structure_on_ct(s.roi, ct, str(options.rtstruct), option=reference[0]):
                typer.echo(f"warning: {line}", err=True)
        region = RG.surface_mask(s.vertices, s.faces, grid)
        where = f"{options.rtstruct} {options.name}"
    else:
        img = read_image(options.mask)
        same = (img.array.shape == tuple(grid.shape) and np.allclose(img.spacing, grid.spacing, atol=1e-4)
                and np.allclose(img.origin, grid.origin, atol=1e-3)
                and np.allclose(np.asarray(img.direction).reshape(3, 3), grid.direction, atol=1e-6))
        if not same:  # another grid of the same world: its voxels, nearest neighbour, on this grid
            img = resample_image(img, np.zeros(tuple(grid.shape) + (3,)), label=True, grid=grid)
        region = img.array != 0
        where = f"--rigid-mask {options.mask}"
    if region.sum() < 4:
        raise InputError(f"{where}: covers {int(region.sum())} voxel(s) of the grid; a rigid structure needs at "
                         "least 4 (is it in the image's frame, mm LPS?)")
    return region


def apply_rigid(result, grid, region, options: RigidOptions | None) -> list[str]:
    """Make the field rigid over ``region`` (in place) and say so in lines for the terminal."""
    if options is None:
        return []
    r = RG.rigid_field(result, grid, region, options.border_mm)
    angle = np.degrees(np.arccos(np.clip((np.trace(r.motion.rotation) - 1) / 2, -1, 1)))
    t = ", ".join(f"{x:.2f}" for x in r.motion.translation)
    return [(f"rigid {options.label}: {r.volume_ml:.2f} mL; at this state {r.rigid_ml:.2f} mL "
             f"({100 * (r.rigid_ml / r.volume_ml - 1):+.2f} %; the elastic field gave {r.elastic_ml:.2f} mL, "
             f"{100 * (r.elastic_ml / r.volume_ml - 1):+.2f} %); centroid moved ({t}) mm, rotated {angle:.2f}°, "
             f"blended over {options.border_mm:g} mm"),
            "Jacobian determinant after the rigid structure: checked (no folding)"]


# One breath for every command: the breathing options of warp, dvf and track (docs/RADIOTHERAPY.md,
# "One breath, every command"). A command plays one named state (--volume-ml, --scan) or the phases of
# one breath: --phases N states evenly over a cycle of --curve CSV, of --preset NAME (--cycles,
# --tidal-ml) or, given neither, of the plain cycle (a 4 s cosine breath of --tidal-ml, by default the
# tidal volume the model was built for, else 500 mL); --phase K keeps phase K of those N. Phase 0 is
# end-inhale unless --phase-zero says otherwise (lungdeform.playback.phases). The same options give
# the same states in every command.

#: Where a refusal that needs a breath says one comes from.
BREATH_HINT = ("a breath: --curve CSV ('lungdeform breathe --out DIR' writes DIR/curve.csv), --preset NAME, or, "
               "given neither, the plain cycle")
PRESETS_HELP = "normal, deep, copd, restrictive, dyspnoea or pneumothorax"


@dataclass(frozen=True, kw_only=True)
class BreathFlags:
    """The breathing options of warp, dvf and track (an option group of :func:`lungdeform.cli.common.takes`;
    track also samples a breath at ``--fps`` without ``--phases``)."""

    curve: Annotated[Path | None, typer.Option("--curve", help="Breathing curve CSV (t_s, volume_ml above end-exhale, …; 'lungdeform breathe' writes one); with --phases (track: or frames at --fps).")] = None
    preset: Annotated[str | None, typer.Option("--preset", help=f"Breathing preset of the PV model ({PRESETS_HELP}); with --phases (track: or frames at --fps).")] = None
    cycles: Annotated[int | None, typer.Option("--cycles", help="With --preset: whole breaths (default 1).")] = None
    tidal_ml: Annotated[float | None, typer.Option("--tidal-ml", callback=tidal_option, help="Tidal volume, both lungs (mL): of the plain cycle (default the model's own, else 500) or the --preset rescaled to it.")] = None
    phases: Annotated[int | None, typer.Option("--phases", help="This many states evenly over one breath of --curve, --preset or the plain cycle (phase 0 end-inhale).")] = None
    phase: Annotated[int | None, typer.Option("--phase", help="With --phases N: only phase K (0 to N-1) of them.")] = None
    phase_zero: Annotated[str, typer.Option("--phase-zero", help=PHASE_ZERO_HELP)] = "end-inhale"

    @property
    def inputs(self) -> list[Path | None]:
        """The files these options read, for :func:`lungdeform.cli.common.check_output`."""
        return [self.curve]


def check_breath(flags: BreathFlags, state_given: bool) -> None:
    """Refuse, before any work, breathing options that do not go together (``state_given``:
    ``--volume-ml`` or ``--scan``)."""
    if flags.phases is None:
        given = [name for name, v in (("--curve", flags.curve), ("--preset", flags.preset), ("--phase", flags.phase),
                                      ("--tidal-ml", flags.tidal_ml), ("--cycles", flags.cycles)) if v is not None]
        if given:
            raise InputError(f"{given[0]} goes with --phases N (how many states of the breath)")
        if not state_given:
            raise InputError(f"give --volume-ml, --scan or --phases N (states over {BREATH_HINT})")
        return
    if state_given:
        raise InputError("--phases with --volume-ml or --scan: give one breathing state or the phases of one breath")
    check_phases(flags.phases)
    check_phase_index(flags.phases, flags.phase)
    check_zero(flags.phase_zero)
    check_trace_options(flags.curve, flags.preset, flags.cycles, flags.tidal_ml)


def check_phase_index(phases: int, phase: int | None) -> None:
    """``--phase K`` (None: every phase) is one of the ``--phases N``: 0 to N − 1."""
    if phase is not None and not 0 <= phase < phases:
        raise InputError(f"--phase must be 0 to {phases - 1} (a phase of --phases {phases}), got {phase}")


def check_trace_options(curve, preset, cycles, tidal_ml) -> None:
    """One breath at most (``--curve`` or ``--preset``), its options in range."""
    if curve is not None and preset is not None:
        raise InputError("--curve and --preset are mutually exclusive: give one breath")
    check_cycles(cycles, preset)
    check_tidal_ml(tidal_ml)
    if tidal_ml is not None and curve is not None:
        raise InputError("--tidal-ml applies to --preset or the plain cycle; a --curve has its own volumes")


def breath_trace(model, curve: Path | None, preset: str | None, cycles: int | None, tidal_ml: float | None):
    """The volume trace (:class:`lungdeform.playback.schedule.VolumeTrace`, mL above end-exhale) the
    options name: ``--curve``, ``--preset`` (``cycles`` breaths, rescaled to ``tidal_ml``) or the plain
    cycle of ``tidal_ml``, by default the tidal volume the model was built for (provenance
    ``tidal_ml``; 500 mL for a model without one, a fit). Each one the model's lungs can follow
    (:func:`lungdeform.playback.schedule.check_reachable`: a --tidal-ml far beyond the lungs' size is refused)."""
    if curve is not None:
        return read_curve(curve, model)
    if preset is not None:
        _params, _curve, trace = S.preset_trace(get_preset(preset), cycles or 1, tidal_ml)
    else:
        built = (model.provenance or {}).get("tidal_ml")
        trace = S.plain_cycle(float(tidal_ml or built or TIDAL_VOLUME_ML))
    check_reachable(trace, model)
    return trace


@dataclass(frozen=True)
class Breath:
    """The states a command plays: ``states`` (one :class:`~lungdeform.playback.displacement_field.State`
    per output); for phases ``indices`` (each state's phase index) and ``count`` (N), else None."""

    states: list[State]
    indices: list[int] | None = None
    count: int | None = None


def breath_states(model, flags: BreathFlags, named: tuple) -> Breath:
    """The states of the options: ``named`` = ``(--volume-ml, --scan, --no-rigid)`` for one state, or
    the phases of the breath (:func:`phase_states`), saying the cycle and which phase the scan is."""
    if flags.phases is None:
        volume_ml, scan, no_rigid = named
        return Breath([without_alignment(pick_state(model, volume_ml, scan), no_rigid)])
    trace = breath_trace(model, flags.curve, flags.preset, flags.cycles, flags.tidal_ml)
    states, period = phase_states(trace, flags.phases, flags.phase_zero)
    typer.echo(f"{len(states)} phase(s) over a cycle of {period:.2f} s of {trace.source} (phase 0 at {flags.phase_zero})")
    typer.echo(scan_phase_text(trace, phase_schedule(trace, flags.phases, flags.phase_zero), model.scan))
    indices = list(range(flags.phases)) if flags.phase is None else [flags.phase]
    return Breath([states[i] for i in indices], indices, flags.phases)


def phase_path(out: Path, index: int) -> Path:
    """``OUT_phaseNN`` with OUT's own suffix: ``ct.mha`` → ``ct_phase03.mha`` (warp's and dvf's image files)."""
    suffix = write_suffix(out)
    return out.with_name(f"{out.name[:-len(suffix)]}_phase{index:02d}{suffix}")


# The dome options of build and demo: --dome-mm and --breathing (lungdeform.model.dome).
DOME_MM_HELP = ("How far the diaphragm dome descends relative to the apex over the breath --tidal-ml describes "
                "(mm; ultrasound, fluoroscopy, a 4-D CT; docs/DEFAULTS.md 'Dome excursion'): one number for "
                "both domes, or 'left=MM,right=MM'. The breath is split so that each dome moves that far, the "
                "rest of the lung following the default's pattern. Default: the default's own.")
BREATHING_HELP = ("A breathing pattern for a scene without a measurement: "
                  + ", ".join(f"{k} (the dome sweeps {v:.0%} of each lung's breath)" for k, v in BREATHING.items())
                  + " (docs/DEFAULTS.md 'Dome excursion'). Not with --dome-mm.")


def dome_request(dome_mm: str | None, breathing: str | None) -> DomeRequest | None:
    """The :class:`DomeRequest` of ``--dome-mm`` / ``--breathing`` (None: neither), or :class:`InputError`
    naming the option: both given, a side other than left/right, or a value that is not a number of mm
    in [0, :data:`lungdeform.model.dome.MAX_DOME_MM`]."""
    if dome_mm is not None and breathing is not None:
        raise InputError("give --dome-mm or --breathing, not both")
    if breathing is not None:
        if breathing not in BREATHING:
            raise InputError(f"--breathing must be one of {', '.join(BREATHING)}, got {breathing!r}")
        return DomeRequest.breathing(breathing)
    if dome_mm is None:
        return None
    text = dome_mm.strip()
    if "=" not in text:
        return DomeRequest(mm={"both": check_excursion(text, "--dome-mm")}, source=f"--dome-mm {text}")
    mm = {}
    for part in text.split(","):
        side, _, value = part.partition("=")
        side = side.strip().lower()
        if side not in SIDES or side in mm:
            raise InputError(f"--dome-mm must be MM or 'left=MM,right=MM' (each side once), got {dome_mm!r}")
        mm[side] = check_excursion(value.strip(), f"--dome-mm {side}")
    return DomeRequest(mm=mm, source=f"--dome-mm {text}")


def dome_lines(record: dict | None, volumes_ml: dict) -> list[str]:
    """One line per lung of a model built with a dome request: the excursion asked and measured over its
    volume change ``volumes_ml[side]`` (mL); ``record``: the model's ``provenance["dome"]`` (None: no lines)."""
    if not record:
        return []
    return [f"{side}: dome excursion {record['measured_mm'][side]:.1f} mm relative to the apex over +{ml:.0f} mL "
            f"(asked {record['asked_mm'][side]:.1f} mm: {record['source']})" for side, ml in volumes_ml.items()]
