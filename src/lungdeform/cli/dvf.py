"""``lungdeform dvf``: the model's motion as a displacement-field image on a reference image's grid."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.atomic import atomic_paths
from lungdeform.errors import InputError
from lungdeform.io.dicom.guard import is_dicom_file
from lungdeform.io.dicom.registration import check_pair, write_registration
from lungdeform.io.dicom.rtstruct import read_ct_series
from lungdeform.io.dicom.series import phase_folder
from lungdeform.io.image import read_image, write_image, write_suffix
from lungdeform.io.modelfile import load_model
from lungdeform.playback import displacement_field as D
from lungdeform.playback.field_grid import REG_SPACING_MM, coarse_grid, coarsened, interpolation_error
from lungdeform.playback.trajectory import extrapolation_note

from .common import (
    MAX_LUNGS_ML,
    BreathFlags,
    RigidFlags,
    RigidOptions,
    SeriesFlags,
    apply_rigid,
    bounded,
    breath_states,
    check_breath,
    check_output,
    dicom_input,
    field_lines,
    phase_path,
    rigid_region,
    say,
    takes,
)


@dataclass(frozen=True, kw_only=True)
class DvfOptions:
    """The options of ``lungdeform dvf`` (:func:`register`)."""

    model: Annotated[Path, typer.Argument(help="Model file (.npz) written by fit, build or demo.")]
    reference: Annotated[Path, typer.Option("--reference", help="Image whose grid (origin, spacing, direction) the field takes: the scan the model was built from.")]
    out: Annotated[Path, typer.Option("--out", help="Field image: .mha, .nii.gz, .nii or .nrrd (3 float32 components, mm LPS).")]
    volume_ml: Annotated[float | None, typer.Option("--volume-ml", callback=bounded(0, MAX_LUNGS_ML, "mL", low_open=True), help="Absolute volume of the model's lungs together (mL).")] = None
    scan: Annotated[int | None, typer.Option("--scan", help="Input scan K of the fit (0 = rest): its volume, in its own frame.")] = None
    inverse: Annotated[bool, typer.Option("--inverse", help="Write the resampling field (ITK/elastix convention) instead of the forward one.")] = False
    out_reg: Annotated[Path | None, typer.Option("--out-reg", help="Also write the field as a DICOM Deformable Spatial Registration object (fixed: --reference, a DICOM CT series; docs/RADIOTHERAPY.md).")] = None
    moving: Annotated[Path | None, typer.Option("--moving", help="With --out-reg: the moving state's DICOM series (e.g. a phase of 'warp --phases'), of --reference's patient and Frame of Reference.")] = None
    node_mm: Annotated[float, typer.Option("--node-mm", callback=bounded(0, D.MAX_NODE_MM, "mm", low_open=True), help="Lattice spacing (mm) at which the interior field is evaluated.")] = D.NODE_SPACING_MM
    grid: Annotated[Path | None, typer.Option("--grid", help="Write the field on this image's grid instead of --reference's (e.g. the target scan's, so an inhaled lung is not cropped); same LPS world.")] = None
    no_rigid: Annotated[bool, typer.Option("--no-rigid", help="With --scan: leave the fit's alignment of that scan out (the field stays in the model's frame).")] = False
    rigid: RigidFlags = RigidFlags()
    breath: BreathFlags = BreathFlags()
    reg_spacing_mm: Annotated[float, typer.Option("--reg-spacing-mm", callback=bounded(0, 20, "mm"), help="With --out-reg: the REG's grid, the field's grid coarsened to nodes at most this far apart (a REG on a 512 x 512 x 141 grid is 443 MB; planning systems interpolate it trilinearly), its interpolation error against the full field printed; 0 keeps the field's own grid (--grid IMAGE chooses that).")] = REG_SPACING_MM
    dicom: SeriesFlags = SeriesFlags()  # --series / --series-description: which CT series of --reference's folder


def register(apps) -> None:
    @apps.root.command("dvf")
    @takes(DvfOptions)
    def dvf_command(opts: DvfOptions) -> None:
        """Displacement field of the model at a breathing state (docs/RADIOTHERAPY.md).

        Forward (default): a point at x in the reference is at x + u(x) at that state, as 'lungdeform
        track' moves it. --inverse: for each point y at that state, y + w(y) in the reference."""

        write_suffix(opts.out)
        inputs = [opts.model, opts.reference, opts.grid, *opts.rigid.inputs, *opts.breath.inputs]
        check_output(opts.out, inputs)
        if opts.out_reg is not None:
            check_output(opts.out_reg, [*inputs, opts.moving, opts.out], option="--out-reg")
        check_breath(opts.breath, opts.volume_ml is not None or opts.scan is not None)
        rigid = RigidOptions.of(opts.rigid)
        m = load_model(opts.model)
        breath = breath_states(m, opts.breath, (opts.volume_ml, opts.scan, opts.no_rigid))
        fields, regs = _output_paths(opts.out, opts.out_reg, breath, opts.breath.phase)
        for path in fields + regs:
            check_output(path, [*inputs, opts.moving], option="--out" if path in fields else "--out-reg")
        choice = opts.dicom.choice()
        dicom_input(opts.reference, choice, "--reference")
        movings = [_moving(opts.moving, breath, n) for n in range(len(breath.states))]
        for moving in dict.fromkeys(movings if opts.out_reg else []):  # each phase's series once
            dicom_input(moving, None, "--moving")
        series = [_registration_series((opts.reference, choice), mov, opts.inverse, state)
                  for mov, state in zip(movings, breath.states)] if opts.out_reg else []
        image = read_image(opts.reference, series=choice) if opts.grid is None else read_image(opts.grid)
        grid = D.Grid.of(image)
        region = rigid_region(rigid, grid, ("--reference", opts.reference), choice)
        note = extrapolation_note(m, [state.delta_ml for state in breath.states])
        if note:
            typer.echo(f"note: {note}")
        paths = fields + regs
        with atomic_paths(paths, [write_suffix(p) for p in fields] + [None] * len(regs)) as tmp:  # all or nothing
            for n, state in enumerate(breath.states):
                say(f"evaluating the field at {state.source}")
                result = D.displacement_field(m, grid, state.delta_ml, alignment=state.alignment,
                                              inverse=opts.inverse, spacing_mm=opts.node_mm)
                lines = field_lines(result) + apply_rigid(result, grid, region, rigid)
                write_image(tmp[n], result.field, image.spacing, image.origin, image.direction)
                typer.echo(f"{'inverse' if opts.inverse else 'forward'} field at {state.source}")
                for line in lines:
                    typer.echo(line)
                if series:
                    _write_reg(tmp[len(fields) + n], (result.field, grid), series[n], opts.reg_spacing_mm,
                               _description(state))
        for n in range(len(breath.states)):  # said once all are in place
            typer.echo(f"wrote {fields[n]}")
            if series:
                typer.echo(f"wrote {regs[n]}")


def _output_paths(out: Path, out_reg: Path | None, breath, phase: int | None) -> tuple[list[Path], list[Path]]:
    """The field files and REG files: ``--out`` and ``--out-reg`` for one state (or ``--phase K``),
    ``OUT_phaseNN`` and ``REG_phaseNN`` (NN the phase index, as ``warp --phases`` names image files)
    for every phase of a breath."""
    if breath.count is None or phase is not None:
        return [out], [] if out_reg is None else [out_reg]
    fields = [phase_path(out, i) for i in breath.indices]
    regs = [] if out_reg is None else [out_reg.with_name(f"{out_reg.stem}_phase{i:02d}{out_reg.suffix}")
                                       for i in breath.indices]
    return fields, regs


def _description(state) -> str:
    """The REG's SeriesDescription: the state in short and its volume above end-exhale
    (``lungdeform phase 5 of 10, +0 mL above end-exhale``; ``volume 3968 mL``, ``scan 1 of the fit``)."""
    return f"lungdeform {state.source.split(' (')[0].split(' at t =')[0]}, {state.delta_ml:+.0f} mL above end-exhale"


def _moving(moving: Path | None, breath, n: int) -> Path | None:
    """The moving series of state ``n``: with phases, ``MOVING/phaseNN`` when ``--moving`` is a 4-D CT
    folder of ``warp --phases`` (NN the phase's percentage), else ``--moving`` itself (one series:
    one state, or ``--phase K``)."""
    if moving is None or breath.count is None:
        return moving
    inside = moving / phase_folder(breath.indices[n], breath.count)
    if inside.is_dir():
        return inside
    if len(breath.states) > 1:
        raise InputError(f"--moving {moving}: with --phases {breath.count} give the 4-D CT folder of 'warp --phases "
                         f"{breath.count}' (its {phase_folder(breath.indices[n], breath.count)} is missing), or one "
                         "phase with --phase K")
    return moving


def _write_reg(path: Path, full: tuple, series: tuple, spacing_mm: float, description: str) -> None:
    """The REG of the field ``full`` = ``(field, grid)`` on its grid coarsened to ``spacing_mm``
    (:mod:`lungdeform.playback.field_grid`; 0: the field's own grid), saying its grid, its size
    against the full grid's and the interpolation error of the coarse grid."""
    field, grid = full
    coarse = grid if spacing_mm == 0 else coarse_grid(grid, spacing_mm)
    vectors = coarsened(field, grid, coarse)
    write_registration(path, vectors, coarse, *series, description=description)
    size = " x ".join(str(n) for n in coarse.shape[::-1])
    step = " x ".join(f"{h:.3g}" for h in coarse.spacing)
    line = f"REG grid {size} nodes of {step} mm ({vectors.nbytes / 1e6:.1f} MB of vectors"
    if coarse is grid:
        typer.echo(f"{line}: the field's own grid)")
        return
    err = interpolation_error(field, vectors)
    typer.echo(f"{line}; the full grid's {field.nbytes / 1e6:.1f} MB): trilinear interpolation of it differs from the "
               f"full field by at most {err.max_mm:.3f} mm (99th percentile {err.p99_mm:.3f} mm, mean {err.mean_mm:.4f} mm "
               f"over the {err.moving} voxels that move; --reg-spacing-mm 0 keeps the full grid)")


def _registration_series(fixed: tuple, moving: Path | None, inverse: bool, state):
    """The fixed and moving series of ``--out-reg`` (``fixed`` = (--reference, its --series choice)),
    checked before the field is evaluated: the REG holds the forward field (fixed → moving,
    docs/RADIOTHERAPY.md), so --inverse is refused; a state in a fitted scan's own frame (an
    alignment) needs that scan's series as --moving."""
    reference, choice = fixed
    if inverse:
        raise InputError("--out-reg holds the forward field (fixed → moving, DICOM's resampling direction); "
                         "drop --inverse")
    if not (reference.is_dir() or is_dicom_file(reference)):
        raise InputError(f"--out-reg needs --reference to be a DICOM CT series (the fixed one), got {reference}")
    if moving is None and state.alignment is not None:
        raise InputError("--out-reg: this state lies in a fitted scan's own frame; give that scan's series as --moving")
    fixed_ct = read_ct_series(reference, choice)
    mov = None if moving is None else read_ct_series(moving)
    check_pair(fixed_ct, mov)
    return fixed_ct, mov
