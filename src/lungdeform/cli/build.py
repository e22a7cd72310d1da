"""``lungdeform build SURFACE [SURFACE …] --out MODEL``."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Optional

import typer

from lungdeform.constants import gravity_vector
from lungdeform.errors import InputError
from lungdeform.geometry.frame import resolve_sides
from lungdeform.io.modelfile import provenance, save_model
from lungdeform.model.lung import BuildSettings, build_model
from lungdeform.model.population import resolve_default
from lungdeform.model.scan_state import HELP as SCAN_STATE_HELP
from lungdeform.model.scan_state import parse_scan_state
from lungdeform.model.stiffness import parse_stiffness
from lungdeform.model.tidal import ONE_LUNG_SHARE, ONE_LUNG_SOURCE, tidal_split
from lungdeform.playback.schedule import MAX_GROWTH, lung_shares
from lungdeform.playback.trajectory import end_exhale_ml, scan_ml
from lungdeform.segment.split import load_lungs

from .common import (
    BREATHING_HELP,
    CONSTANTS_HELP,
    DOME_MM_HELP,
    SIDE_CHECK_HELP,
    bounded,
    check_output,
    check_tidal_ml,
    dicom_input,
    dome_lines,
    dome_request,
    option_names,
    parse_orientation,
    say,
    takes,
    tidal_option,
)


@dataclass(frozen=True, kw_only=True)
class BuildOptions:
    """The options of ``lungdeform build`` (:func:`register`)."""

    sources: Annotated[list[Path], typer.Argument(help="Mesh files (STL, OBJ, PLY, VTK, VTP, OFF, glTF/GLB) or masks (NIfTI, MHA/MHD, NRRD, DICOM folder).")]
    out: Annotated[Path, typer.Option("--out", "-o", help="Model file to write (.npz).")]
    side: Annotated[Optional[list[str]], typer.Option("--side", help="Side of each surface in order: left|right (given once per input, it picks that lung of a mask holding both lungs in one label; without it such a mask gives both lungs). Default: from label names, from position for two surfaces, or from the shape (the concave medial face) for one.")] = None
    labels: Annotated[Optional[str], typer.Option("--labels", help="Mask labels: 'lungs' (lobe map → left, right), 'left=1,2;right=3,4,5', or '1,2'.")] = None
    units: Annotated[str, typer.Option("--units", help="Units of mesh files: mm, cm or m (converted to mm).")] = "mm"
    repair: Annotated[bool, typer.Option("--repair", help="Repair fixable surface defects and report them.")] = False
    target_vertices: Annotated[Optional[int], typer.Option("--target-vertices", help="Decimate mask surfaces to about this many vertices.")] = None
    side_check: Annotated[bool, typer.Option("--side-check/--no-side-check", help=SIDE_CHECK_HELP)] = True
    orientation: Annotated[str, typer.Option("--orientation", help="supine, prone, upright, left-decubitus, right-decubitus, or a gravity vector 'x,y,z' (LPS).")] = "supine"
    tidal_ml: Annotated[float, typer.Option("--tidal-ml", callback=tidal_option, help="Tidal volume for both lungs together (mL); calibration is exact there. Two lungs share it by end-exhale volume; one lung alone takes its side's usual share (right 53.6 %, left 46.4 %; docs/DEFAULTS.md).")] = 500.0
    stiffness: Annotated[str, typer.Option("--stiffness", help="uniform | gradient:DEPENDENT,NONDEPENDENT | sphere:X,Y,Z,RADIUS,E (mm, LPS).")] = "uniform"
    solver: Annotated[str, typer.Option("--solver", help="Linear solver: bicgstab, gmres or direct.")] = "bicgstab"
    d_min: Annotated[float, typer.Option("--d-min", callback=bounded(0, 100, "mm", low_open=True), help="Minimum transfer distance (mm).")] = 1.0
    constants: Annotated[str, typer.Option("--constants", help=CONSTANTS_HELP)] = "population"
    scan_state: Annotated[str, typer.Option("--scan-state", help=SCAN_STATE_HELP)] = "end-exhale"
    dome_mm: Annotated[Optional[str], typer.Option("--dome-mm", help=DOME_MM_HELP)] = None
    breathing: Annotated[Optional[str], typer.Option("--breathing", help=BREATHING_HELP)] = None


def check_breath_fits(sources: dict, surfaces: dict, tidal_ml: float) -> None:
    """Refuse, naming its file, a lung whose part of ``tidal_ml`` (mL, both lungs;
    :func:`~lungdeform.model.tidal.tidal_split`) would take it past :data:`MAX_GROWTH` times its own
    volume: no lung breathes that (total lung capacity is about twice the end-exhale volume), and
    dvf, warp and track would refuse every state of the breath. Usually a surface in other units
    (a lung in centimetres passes the size check at 20–40 "mm" across) or not a lung."""
    parts = tidal_split({side: s.volume_ml for side, s in surfaces.items()}, tidal_ml)
    for side, surface in surfaces.items():
        if parts[side] > (MAX_GROWTH - 1.0) * surface.volume_ml:
            raise InputError(f"{sources[side]}: the {side} lung encloses {surface.volume_ml:.4g} mL; its part "
                             f"{parts[side]:.0f} mL of --tidal-ml {tidal_ml:g} would take it past {MAX_GROWTH:g} times "
                             "that, which no lung breathes: is it in other units (--units cm or m) or not a lung?")


def register(apps) -> None:
    @apps.root.command("build")
    @takes(BuildOptions)
    def build(opts: BuildOptions) -> None:
        """Build a breathing lung model from one or two lung surfaces."""

        check_tidal_ml(opts.tidal_ml)  # before the (slow) reading, with the options' own names
        scan = parse_scan_state(opts.scan_state, opts.tidal_ml)
        dome = dome_request(opts.dome_mm, opts.breathing)
        check_output(opts.out, opts.sources)
        if opts.solver not in SOLVERS:
            raise InputError(f"--solver must be one of {', '.join(SOLVERS)}, got {opts.solver!r}")
        with option_names({"constants": "--constants"}):
            chosen = resolve_default(opts.constants)
        if opts.target_vertices is not None and opts.target_vertices < 100:
            raise InputError(f"--target-vertices must be at least 100, got {opts.target_vertices}")
        loaded = []
        # --side once per source also picks that lung of a mask holding both lungs in one label
        per_source = opts.side if opts.side and len(opts.side) == len(opts.sources) else [None] * len(opts.sources)
        for src in opts.sources:  # a DICOM folder: what it holds besides the image series, said
            dicom_input(src)
        for src, src_side in zip(opts.sources, per_source):
            got, notes = load_lungs(src, src_side, labels=opts.labels, units=opts.units, repair=opts.repair,
                                    target_vertices=opts.target_vertices, progress=say)
            for text in notes:
                typer.echo(f"note: {text}")
            for surface, report in got:
                for line in report.repairs:
                    say(f"{surface.name}: {line}")
                for line in report.warnings:  # suspicious but usable: printed also without --verbose
                    typer.echo(f"warning: {src}: {line}", err=True)
                loaded.append((src, surface))
        with option_names({"sides": "--side"}):
            sides = resolve_sides([s for _, s in loaded], opts.side, check=opts.side_check)
        if len(set(sides)) != len(sides):
            raise InputError(f"two surfaces for the same side: {', '.join(sides)}")
        surfaces = {sd: s for sd, (_, s) in zip(sides, loaded)}
        check_breath_fits({sd: src for sd, (src, _) in zip(sides, loaded)}, surfaces, opts.tidal_ml)
        gravity = parse_orientation(opts.orientation)
        with option_names({"stiffness": "--stiffness"}):
            stiff = {sd: parse_stiffness(opts.stiffness, s.vertices, gravity_vector(gravity)) for sd, s in surfaces.items()}
        prov = provenance(
            "build", sources=[str(p) for p, _ in loaded], sides=sides, orientation=opts.orientation,
            stiffness=opts.stiffness, solver=opts.solver, units=opts.units,
        )
        model = build_model(surfaces, tidal_ml=opts.tidal_ml, stiffness=stiff, gravity=gravity,
                            settings=BuildSettings(solver=opts.solver, d_min=opts.d_min), provenance=prov, default=chosen,
                            progress=say, dome=dome)
        model = replace(model, scan=scan)  # the surfaces are that scan
        path = save_model(opts.out, model)
        shares = lung_shares(model)
        for sd, lung in model.lungs.items():
            at_scan = "" if scan.is_end_exhale else f" (at the scan {lung.volume_ee_ml:.0f} mL)"
            typer.echo(f"{sd}: {lung.n_vertices} vertices, V_EE {lung.volume_ee_ml - shares[sd] * scan.above_ee_ml:.0f} mL"
                       f"{at_scan}, calibrated at +{lung.calibration_ml:.0f} mL")
            if len(model.lungs) == 1:  # a lone lung does not breathe the whole tidal volume
                typer.echo(f"{sd}: one lung: its share {ONE_LUNG_SHARE[sd]:.1%} of --tidal-ml {opts.tidal_ml:g} mL "
                           f"= {lung.calibration_ml:.0f} mL ({ONE_LUNG_SOURCE}; docs/DEFAULTS.md)")
        if not scan.is_end_exhale:  # the rest surfaces are that scan; the breath reaches below it
            typer.echo(f"scan: {scan.describe()}: the lungs together {scan_ml(model):.0f} mL at the scan, "
                       f"{end_exhale_ml(model):.0f} mL at end-exhale; the model breathes out below the scan and in above it")
        for line in dome_lines(model.provenance.get("dome"), {sd: lg.calibration_ml for sd, lg in model.lungs.items()}):
            typer.echo(line)
        typer.echo(f"constants: {chosen.name} ({chosen.provenance.get('source', chosen.name)})")
        typer.echo(f"model written to {path}")


SOLVERS = ("bicgstab", "gmres", "direct")
