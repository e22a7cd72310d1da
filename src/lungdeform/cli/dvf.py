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
from lungdeform.io.image import read_image, write_image, write_suffix
from lungdeform.io.modelfile import load_model
from lungdeform.playback import displacement_field as D
from lungdeform.playback.trajectory import extrapolation_note

from .common import (
    MAX_LUNGS_ML,
    RigidFlags,
    RigidOptions,
    SeriesFlags,
    apply_rigid,
    bounded,
    check_output,
    dicom_input,
    field_lines,
    pick_state,
    rigid_region,
    say,
    takes,
    without_alignment,
)


@dataclass(frozen=True, kw_only=True)
class DvfOptions:
    """The options of ``lungdeform dvf`` (:func:`register`)."""

    model: Annotated[Path, typer.Argument(help="Model file (.npz) written by fit, build or demo.")]
    reference: Annotated[Path, typer.Option("--reference", help="Image whose grid (origin, spacing, direction) the field takes: the end-exhale scan.")]
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
    dicom: SeriesFlags = SeriesFlags()  # --series / --series-description: which CT series of --reference's folder


def register(apps) -> None:
    @apps.root.command("dvf")
    @takes(DvfOptions)
    def dvf_command(opts: DvfOptions) -> None:
        """Displacement field of the model at a breathing state (docs/RADIOTHERAPY.md).

        Forward (default): a point at x in the reference is at x + u(x) at that state, as 'lungdeform
        track' moves it. --inverse: for each point y at that state, y + w(y) in the reference."""

        write_suffix(opts.out)
        check_output(opts.out, [opts.model, opts.reference, opts.grid, *opts.rigid.inputs])
        if opts.out_reg is not None:
            check_output(opts.out_reg, [opts.model, opts.reference, opts.grid, *opts.rigid.inputs, opts.moving, opts.out], option="--out-reg")
        rigid = RigidOptions.of(opts.rigid)
        m = load_model(opts.model)
        state = without_alignment(pick_state(m, opts.volume_ml, opts.scan), opts.no_rigid)
        choice = opts.dicom.choice()
        dicom_input(opts.reference, choice, "--reference")
        dicom_input(opts.moving if opts.out_reg else None, None, "--moving")
        series = _registration_series((opts.reference, choice), opts.moving, opts.inverse, state) if opts.out_reg else None
        image = read_image(opts.reference, series=choice) if opts.grid is None else read_image(opts.grid)
        region = rigid_region(rigid, D.Grid.of(image), ("--reference", opts.reference), choice)
        note = extrapolation_note(m, [state.delta_ml])
        if note:
            typer.echo(f"note: {note}")
        say("evaluating the field")
        result = D.displacement_field(m, D.Grid.of(image), state.delta_ml, alignment=state.alignment,
                                      inverse=opts.inverse, spacing_mm=opts.node_mm)
        lines = field_lines(result) + apply_rigid(result, D.Grid.of(image), region, rigid)
        outputs = [opts.out] + ([opts.out_reg] if series is not None else [])
        with atomic_paths(outputs, [write_suffix(opts.out), None]) as tmp:  # the field and its REG together, or neither
            write_image(tmp[0], result.field, image.spacing, image.origin, image.direction)
            if series is not None:
                write_registration(tmp[1], result.field, image, *series, description=f"lungdeform {state.source}")
        typer.echo(f"{'inverse' if opts.inverse else 'forward'} field at {state.source}")
        for line in lines:
            typer.echo(line)
        for path in outputs:
            typer.echo(f"wrote {path}")


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
