"""``lungdeform build SURFACE [SURFACE …] --out MODEL``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lungdeform.constants import gravity_vector
from lungdeform.errors import InputError
from lungdeform.geometry.frame import resolve_sides
from lungdeform.io.modelfile import provenance, save_model
from lungdeform.model.lung import BuildSettings, build_model
from lungdeform.model.population import resolve_default
from lungdeform.model.stiffness import parse_stiffness
from lungdeform.segment.split import load_lungs

from .common import (
    CONSTANTS_HELP,
    SIDE_CHECK_HELP,
    bounded,
    check_output,
    check_tidal_ml,
    option_names,
    parse_orientation,
    say,
    tidal_option,
)


def register(apps) -> None:
    @apps.root.command("build")
    def build(
        sources: list[Path] = typer.Argument(..., help="Mesh files (STL, OBJ, PLY, VTK, VTP, OFF, glTF/GLB) or masks (NIfTI, MHA/MHD, NRRD, DICOM folder)."),
        out: Path = typer.Option(..., "--out", "-o", help="Model file to write (.npz)."),
        side: Optional[list[str]] = typer.Option(None, "--side", help="Side of each surface in order: left|right (given once per input, it picks that lung of a mask holding both lungs in one label; without it such a mask gives both lungs). Default: from label names, from position for two surfaces, or from the shape (the concave medial face) for one."),
        labels: Optional[str] = typer.Option(None, "--labels", help="Mask labels: 'lungs' (lobe map → left, right), 'left=1,2;right=3,4,5', or '1,2'."),
        units: str = typer.Option("mm", "--units", help="Units of mesh files: mm, cm or m (converted to mm)."),
        repair: bool = typer.Option(False, "--repair", help="Repair fixable surface defects and report them."),
        target_vertices: Optional[int] = typer.Option(None, "--target-vertices", help="Decimate mask surfaces to about this many vertices."),
        side_check: bool = typer.Option(True, "--side-check/--no-side-check", help=SIDE_CHECK_HELP),
        orientation: str = typer.Option("supine", "--orientation", help="supine, prone, upright, left-decubitus, right-decubitus, or a gravity vector 'x,y,z' (LPS)."),
        tidal_ml: float = typer.Option(500.0, "--tidal-ml", callback=tidal_option, help="Tidal volume for both lungs together (mL); calibration is exact there."),
        stiffness: str = typer.Option("uniform", "--stiffness", help="uniform | gradient:DEPENDENT,NONDEPENDENT | sphere:X,Y,Z,RADIUS,E (mm, LPS)."),
        solver: str = typer.Option("bicgstab", "--solver", help="Linear solver: bicgstab, gmres or direct."),
        d_min: float = typer.Option(1.0, "--d-min", callback=bounded(0, 100, "mm", low_open=True), help="Minimum transfer distance (mm)."),
        constants: str = typer.Option("population", "--constants", help=CONSTANTS_HELP),
    ):
        """Build a breathing lung model from one or two lung surfaces."""

        check_tidal_ml(tidal_ml)  # before the (slow) reading, with the options' own names
        check_output(out, sources)
        if solver not in SOLVERS:
            raise InputError(f"--solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
        with option_names({"constants": "--constants"}):
            chosen = resolve_default(constants)
        if target_vertices is not None and target_vertices < 100:
            raise InputError(f"--target-vertices must be at least 100, got {target_vertices}")
        loaded = []
        # --side once per source also picks that lung of a mask holding both lungs in one label
        per_source = side if side and len(side) == len(sources) else [None] * len(sources)
        for src, src_side in zip(sources, per_source):
            got, notes = load_lungs(src, src_side, labels=labels, units=units, repair=repair,
                                    target_vertices=target_vertices, progress=say)
            for text in notes:
                typer.echo(f"note: {text}")
            for surface, report in got:
                for line in report.repairs:
                    say(f"{surface.name}: {line}")
                for line in report.warnings:  # suspicious but usable: printed also without --verbose
                    typer.echo(f"warning: {src}: {line}", err=True)
                loaded.append((src, surface))
        with option_names({"sides": "--side"}):
            sides = resolve_sides([s for _, s in loaded], side, check=side_check)
        if len(set(sides)) != len(sides):
            raise InputError(f"two surfaces for the same side: {', '.join(sides)}")
        surfaces = {sd: s for sd, (_, s) in zip(sides, loaded)}
        gravity = parse_orientation(orientation)
        with option_names({"stiffness": "--stiffness"}):
            stiff = {sd: parse_stiffness(stiffness, s.vertices, gravity_vector(gravity)) for sd, s in surfaces.items()}
        prov = provenance(
            "build", sources=[str(p) for p, _ in loaded], sides=sides, orientation=orientation,
            stiffness=stiffness, solver=solver, units=units,
        )
        model = build_model(surfaces, tidal_ml=tidal_ml, stiffness=stiff, gravity=gravity,
                            settings=BuildSettings(solver=solver, d_min=d_min), provenance=prov, default=chosen,
                            progress=say)
        path = save_model(out, model)
        for sd, lung in model.lungs.items():
            typer.echo(f"{sd}: {lung.n_vertices} vertices, V_EE {lung.volume_ee_ml:.0f} mL, "
                       f"calibrated at +{lung.calibration_ml:.0f} mL")
        typer.echo(f"constants: {chosen.name} ({chosen.provenance.get('source', chosen.name)})")
        typer.echo(f"model written to {path}")


SOLVERS = ("bicgstab", "gmres", "direct")
