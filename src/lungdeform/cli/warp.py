"""``lungdeform warp``: the image the model was built from resampled at a breathing state of the model (synthetic 4-D CT)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from lungdeform.atomic import atomic_dir, atomic_paths
from lungdeform.errors import InputError
from lungdeform.io.dicom import series as DS
from lungdeform.io.grid import Image
from lungdeform.io.image import WRITE_SUFFIXES, read_image, resample_image, write_image, write_suffix
from lungdeform.io.modelfile import load_model
from lungdeform.playback import density as M
from lungdeform.playback import displacement_field as D
from lungdeform.playback.trajectory import extrapolation_note

from .common import (
    BREATH_HINT,
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
class WarpOptions:
    """The options of ``lungdeform warp`` (:func:`register`)."""

    image: Annotated[Path, typer.Argument(help="Image in the model's frame (the scan the model was built from, or its mask).")]
    model: Annotated[Path, typer.Argument(help="Model file (.npz) written by fit, build or demo.")]
    out: Annotated[Path, typer.Option("--out", help="Output image (.mha, .nii.gz, .nii, .nrrd); with --phases: OUT_phase00 …. A folder (a name without suffix): DICOM CT series, with --phases one per phase in OUT/phase00 … OUT/phase90.")]
    volume_ml: Annotated[float | None, typer.Option("--volume-ml", callback=bounded(0, MAX_LUNGS_ML, "mL", low_open=True), help="Absolute volume of the model's lungs together (mL).")] = None
    scan: Annotated[int | None, typer.Option("--scan", help="Input scan K of the fit (0 = rest): its volume, in its own frame.")] = None
    breath: BreathFlags = BreathFlags()
    label: Annotated[bool, typer.Option("--label", help="A label image: nearest-neighbour, values kept.")] = False
    node_mm: Annotated[float, typer.Option("--node-mm", callback=bounded(0, D.MAX_NODE_MM, "mm", low_open=True), help="Lattice spacing (mm) of the interior field.")] = D.NODE_SPACING_MM
    density: Annotated[bool, typer.Option("--density", help="Conserve mass: HU + 1000 scaled by the Jacobian determinant of the resampling field, so an inhaled lung gets darker (docs/RADIOTHERAPY.md, \"Density and projections\").")] = False
    lung_mask: Annotated[list[Path] | None, typer.Option("--lung-mask", help="With --density: the lung mask on IMAGE's grid (non-zero = lung; repeat for left and right): lung voxels are resampled from lung tissue only and the chest wall from the rest, so each keeps its mass (docs/RADIOTHERAPY.md, \"Density and projections\"). Without it the model's own lungs at rest, rasterised on IMAGE's grid, stand in (less exact along the surface).")] = None
    no_lung_mask: Annotated[bool, typer.Option("--no-lung-mask", help="With --density: no lung mask at all, the whole image resampled linearly (the lung's edge voxels mix in chest-wall density: the lungs gain about 1.6 % of mass at +500 mL on POPI), as --density did before the model's mask became its default.")] = False
    projections: Annotated[str | None, typer.Option("--projections", help="With --phases and an image-file --out: also OUT_mip, OUT_aip, OUT_minip (maximum, mean, minimum over the phases); e.g. mip,aip,minip.")] = None
    rigid: RigidFlags = RigidFlags()
    grid: Annotated[Path | None, typer.Option("--grid", help="Write on this image's grid instead of IMAGE's (e.g. the target scan's, so an inhaled lung is not cropped); same LPS world.")] = None
    no_rigid: Annotated[bool, typer.Option("--no-rigid", help="With --scan: leave the fit's alignment of that scan out (the image stays in the model's frame).")] = False
    dicom: SeriesFlags = SeriesFlags()  # --series / --series-description: which CT series of IMAGE's folder


def register(apps) -> None:
    @apps.root.command("warp")
    @takes(WarpOptions)
    def warp_command(opts: WarpOptions) -> None:
        """Resample IMAGE at a breathing state of MODEL on IMAGE's own grid (docs/RADIOTHERAPY.md)."""

        inputs = [opts.image, opts.model, *opts.breath.inputs, *opts.rigid.inputs, opts.grid, *(opts.lung_mask or [])]
        rigid = RigidOptions.of(opts.rigid)
        kinds = M.parse_projections(opts.projections)
        if opts.out.is_dir() and any(opts.out.name.lower().endswith(x) for x in WRITE_SUFFIXES):
            check_output(opts.out)  # an existing folder named like an image file: refused
        dicom = DS.is_series_output(opts.out)
        DS.check_series_output(opts.out) if dicom else write_suffix(opts.out)
        check_output(opts.out, inputs, folder=dicom, whole=dicom)
        check_breath(opts.breath, opts.volume_ml is not None or opts.scan is not None)
        _check_combinations(opts.out, dicom, dict(label=opts.label, density=opts.density, kinds=kinds, phases=opts.breath.phases,
                                             phase=opts.breath.phase, grid=opts.grid,
                                             lung=bool(opts.lung_mask), no_lung=opts.no_lung_mask))
        m = load_model(opts.model)
        breath = breath_states(m, opts.breath, (opts.volume_ml, opts.scan, opts.no_rigid))
        states = breath.states
        if breath.count is not None and opts.breath.phase is None:  # every phase: one output each
            paths = [Path(DS.phase_folder(i, breath.count)) if dicom else phase_path(opts.out, i) for i in breath.indices]
            paths += [projection_path(opts.out, k) for k in kinds]
            for path in [] if dicom else paths:
                check_output(path, inputs)
        else:
            paths = [Path() if dicom else opts.out]
        series = opts.dicom.choice()
        dicom_input(opts.image, series, "IMAGE")
        img = read_image(opts.image, series=series)
        lungs = _lungs(opts, m, img)
        target = img if opts.grid is None else read_image(opts.grid)
        region = rigid_region(rigid, D.Grid.of(target), ("IMAGE", opts.image), series)
        projector = M.Projector() if kinds else None
        header = DS.study_header(opts.image, series) if dicom else None
        note = extrapolation_note(m, [s.delta_ml for s in states])
        if note:
            typer.echo(f"note: {note}")
        # the whole set or nothing: a DICOM folder renamed at the end, image files renamed together
        with atomic_dir(opts.out) if dicom else atomic_paths(paths, [write_suffix(p) for p in paths]) as tmp:
            for i, (state, path) in enumerate(zip(states, paths)):
                say(f"resampling at {state.source}")
                result = D.displacement_field(m, D.Grid.of(target), state.delta_ml, alignment=state.alignment,
                                              inverse=True, spacing_mm=opts.node_mm)
                lines = field_lines(result) + apply_rigid(result, D.Grid.of(target), region, rigid)
                warped, more = _resampled(img, target, result, (opts.label, opts.density), lungs)
                lines += more
                if projector is not None:
                    projector.add(warped.array)
                if dicom:
                    temporal = None if breath.count is None else (breath.indices[i], breath.count)
                    _write_series(tmp / path, warped, header, temporal)
                else:
                    write_image(tmp[i], warped.array, warped.spacing, warped.origin, warped.direction)
                typer.echo(f"{state.source}:")
                for line in lines:
                    typer.echo(f"  {line}")
                typer.echo(f"wrote {opts.out / path if dicom else path}")
            for n, kind in enumerate(kinds):
                write_image(tmp[len(states) + n], M.as_pixel_type(projector.result(kind), img.array.dtype),
                            target.spacing, target.origin, target.direction)
                typer.echo(f"wrote {paths[len(states) + n]} ({kind.upper()} over {len(states)} phases)")


def _check_combinations(out: Path, dicom: bool, given: dict) -> None:
    """Refuse, before any work, options that do not go together (``given``: label, density, kinds,
    phases, phase, grid, lung, no_lung; the breath's own options: :func:`lungdeform.cli.common.check_breath`)."""
    if dicom and given["label"]:
        raise InputError(f"--out {out}: a label image is not written as a DICOM CT series; use .mha, .nii.gz or .nrrd")
    if given["density"] and given["label"]:
        raise InputError("--density scales CT numbers; a --label image has none")
    if given["lung"] and not given["density"]:
        raise InputError("--lung-mask goes with --density (it says which voxels are lung tissue)")
    if given["no_lung"] and not given["density"]:
        raise InputError("--no-lung-mask goes with --density (it says how CT numbers are resampled)")
    if given["no_lung"] and given["lung"]:
        raise InputError("--lung-mask with --no-lung-mask: give one (the mask, or the whole image resampled linearly)")
    if given["kinds"] and (given["phases"] is None or given["phase"] is not None):
        raise InputError(f"--projections needs --phases N without --phase (the phases it projects, of {BREATH_HINT})")
    if given["kinds"] and dicom:
        raise InputError(f"--out {out}: --projections are written as image files; give --out OUT.mha")
    if dicom and given["grid"] is not None:
        raise InputError("--grid with a DICOM --out: the series keeps IMAGE's slices; give --out OUT.mha")


def projection_path(out: Path, kind: str) -> Path:
    """``OUT_kind`` with OUT's own suffix: ``ct.mha`` → ``ct_mip.mha``."""
    suffix = write_suffix(out)
    return out.with_name(f"{out.name[:-len(suffix)]}_{kind}{suffix}")


#: How the output names the mask that :func:`_lungs` made from the model.
MODEL_MASK = "the model's lungs at rest, rasterised"


@dataclass(frozen=True)
class Lungs:
    """The lung voxels of IMAGE for ``--density`` (``mask : (z, y, x) bool`` on IMAGE's grid) and which
    mask they are (``name``: ``--lung-mask`` or :data:`MODEL_MASK`)."""

    mask: np.ndarray
    name: str


def _lungs(opts: WarpOptions, model, img: Image) -> Lungs | None:
    """The lung mask ``--density`` resamples by (:func:`lungdeform.playback.density.resample_by_tissue`):
    ``--lung-mask``'s, else the model's rest lungs rasterised on IMAGE's grid
    (:func:`lungdeform.playback.density.model_lung_mask`: IMAGE is the model's rest scan, whatever
    the state and its alignment); None without --density or with ``--no-lung-mask``."""
    if not opts.density or opts.no_lung_mask:
        return None
    if opts.lung_mask:
        return Lungs(read_lungs(opts.lung_mask, img), "--lung-mask")
    mask = M.model_lung_mask(model, img)
    rest = sum(lung.volume_ee_ml for lung in model.lungs.values())
    typer.echo(f"lung mask for --density: {MODEL_MASK} on IMAGE's grid ({mask.sum() * img.voxel_ml:.0f} mL against the "
               f"model's {rest:.0f} mL; --lung-mask with the segmented lungs is more exact)")
    return Lungs(mask, MODEL_MASK)


def read_lungs(paths: list[Path] | None, img: Image) -> np.ndarray | None:
    """``(z, y, x) bool``: the union of the ``--lung-mask`` images' non-zero voxels, each on IMAGE's
    own grid (the tissue partition is of IMAGE's voxels: a mask on another grid is refused, not
    resampled); None without one."""
    if not paths:
        return None
    lungs = np.zeros(img.array.shape, bool)
    for path in paths:
        m = read_image(path)
        same = (m.array.shape == img.array.shape and np.allclose(m.spacing, img.spacing, atol=1e-4)
                and np.allclose(m.origin, img.origin, atol=1e-3)
                and np.allclose(np.reshape(m.direction, (3, 3)), np.reshape(img.direction, (3, 3)), atol=1e-6))
        if not same:
            raise InputError(f"--lung-mask {path}: its grid ({m.array.shape[::-1]} voxels of {np.round(m.spacing, 4)} mm "
                             f"at {np.round(m.origin, 3)}) is not IMAGE's ({img.array.shape[::-1]} of "
                             f"{np.round(img.spacing, 4)} mm at {np.round(img.origin, 3)}); give the mask segmented on IMAGE")
        lungs |= m.array != 0
    if not lungs.any():
        raise InputError(f"--lung-mask {', '.join(map(str, paths))}: no non-zero voxel (no lung)")
    return lungs


def _resampled(img: Image, target: Image, result, kind: tuple[bool, bool], lungs=None) -> tuple[Image, list[str]]:
    """IMAGE resampled through the inverse field on ``target``'s grid; ``kind`` = (label, density):
    with density its HU scaled to conserve mass (:func:`lungdeform.playback.density.conserve_mass`),
    with ``lungs`` (:class:`Lungs`, :func:`_lungs`) lung and the rest resampled each from its own tissue
    (:func:`lungdeform.playback.density.resample_by_tissue`), and the masses before and after in lines."""
    label, density = kind
    other = None if target is img else target
    if not density:
        return resample_image(img, result.field, label=label, grid=other), []
    if lungs is None:  # in float32: an integer image resampled in its own type is truncated toward zero
        as_float = Image(img.array.astype(np.float32), img.spacing, img.origin, img.direction, img.source)
        hu, at_state = resample_image(as_float, result.field, default=float(np.min(img.array)), grid=other).array, None
    else:
        hu, at_state = M.resample_by_tissue(img, lungs.mask, result.field, grid=other)
    jac = D.jacobian_determinant(result.field, target.spacing, target.direction)
    hu = M.as_pixel_type(M.conserve_mass(hu, jac), img.array.dtype)
    voxel = [img.voxel_ml, target.voxel_ml]
    before, after = M.mass_g(img.array, voxel[0]), M.mass_g(hu, voxel[1])
    lines = [(f"density: HU scaled by the Jacobian (mass conserved); mass of the image {before / 1000:.3f} kg "
              f"→ {after / 1000:.3f} kg ({100 * (after / before - 1):+.2f} %; tissue leaving the grid counts)")]
    if at_state is None:  # said, not silent: the lungs' own mass is off by the edge voxels' mixing
        lines.append("note: --no-lung-mask: voxels at the lung's edge mix in chest-wall density (the lungs "
                     "gain about 1.6 % of mass at +500 mL on POPI); without it a lung mask keeps that within 1 % "
                     "(docs/RADIOTHERAPY.md, \"Density and projections\")")
    else:
        b, a = M.mass_g(img.array, voxel[0], lungs.mask), M.mass_g(hu, voxel[1], at_state)
        lines.append(f"lungs ({lungs.name}, at this state by nearest neighbour): {lungs.mask.sum() * voxel[0]:.0f} mL → "
                     f"{at_state.sum() * voxel[1]:.0f} mL, mass {b:.1f} g → {a:.1f} g ({100 * (a / b - 1):+.2f} %)")
    return Image(hu, target.spacing, target.origin, target.direction, img.source), lines


def _write_series(folder: Path, image, header, temporal) -> None:
    """One DICOM CT series: a phase ``"<source description> phase 30%"`` of a 4-D CT, or one state."""
    base = header.get("SeriesDescription", "")
    if temporal is None:
        description, number = DS.state_description(base), 100
    else:
        description, number = DS.phase_description(base, *temporal), 100 + temporal[0]
    DS.write_ct_series(folder, Image(image.array, image.spacing, image.origin, image.direction), header,
                       description=description, series_number=number, temporal=temporal)
