"""``lungdeform build SURFACE [SURFACE …] --out MODEL``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lungdeform.constants import gravity_vector
from lungdeform.errors import InputError
from lungdeform.fit.lungsplit import load_lungs
from lungdeform.geometry.frame import SIDES, check_side, clear_side, guess_sides
from lungdeform.io.modelfile import provenance, save_model
from lungdeform.model import stiffness as st
from lungdeform.model.lung import build_model

from .common import SIDE_CHECK_HELP, check_tidal_ml, parse_orientation, say


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
        tidal_ml: float = typer.Option(500.0, "--tidal-ml", help="Tidal volume for both lungs together (mL); calibration is exact there."),
        stiffness: str = typer.Option("uniform", "--stiffness", help="uniform | gradient:DEPENDENT,NONDEPENDENT | sphere:X,Y,Z,RADIUS,E (mm, LPS)."),
        solver: str = typer.Option("bicgstab", "--solver", help="Linear solver: bicgstab, gmres or direct."),
        d_min: float = typer.Option(1.0, "--d-min", help="Minimum transfer distance (mm)."),
    ):
        """Build a breathing lung model from one or two lung surfaces."""

        check_tidal_ml(tidal_ml)  # before the (slow) reading, with the options' own names
        if solver not in SOLVERS:
            raise InputError(f"--solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
        if not d_min > 0:
            raise InputError(f"--d-min must be > 0 mm, got {d_min:g}")
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
                loaded.append((src, surface))
        sides = resolve_sides([s for _, s in loaded], side, check=side_check)
        if len(set(sides)) != len(sides):
            raise InputError(f"two surfaces for the same side: {', '.join(sides)}")
        surfaces = {sd: s for sd, (_, s) in zip(sides, loaded)}
        gravity = parse_orientation(orientation)
        stiff = {sd: stiffness_field(stiffness, s, gravity) for sd, s in surfaces.items()}
        prov = provenance(
            "build", sources=[str(p) for p, _ in loaded], sides=sides, orientation=orientation,
            stiffness=stiffness, solver=solver, units=units,
        )
        model = build_model(surfaces, tidal_ml=tidal_ml, stiffness=stiff, gravity=gravity,
                            solver=solver, d_min=d_min, provenance=prov, progress=say)
        path = save_model(out, model)
        for sd, lung in model.lungs.items():
            typer.echo(f"{sd}: {lung.n_vertices} vertices, V_EE {lung.volume_ee_ml:.0f} mL, "
                       f"calibrated at +{lung.calibration_ml:.0f} mL")
        typer.echo(f"model written to {path}")


SOLVERS = ("bicgstab", "gmres", "direct")


def resolve_sides(surfaces, given: list[str] | None, check: bool = True) -> list[str]:
    """Sides from --side, from names ending in -left/-right, from position (two lungs) or from the
    shape (one lung: :func:`lungdeform.geometry.frame.side_from_shape`). Each lung's side is checked
    against its shape (:func:`lungdeform.geometry.frame.check_side`) unless ``check`` is False.

    Given or named sides of a left and a right surface are checked against their positions: in
    LPS the left lung lies at larger x. A pair the other way round (sides or labels swapped, or
    meshes in RAS) is refused rather than built with the wrong sides and the wrong gravity frame.
    """

    by_position = False
    if given:
        if len(given) != len(surfaces):
            raise InputError(f"--side given {len(given)} times for {len(surfaces)} surfaces")
        bad = [s for s in given if s not in SIDES]
        if bad:
            raise InputError(f"--side must be left or right, got {bad[0]!r}")
        sides = list(given)
    else:
        named = [next((sd for sd in SIDES if s.name.lower().endswith(sd)), None) for s in surfaces]
        if all(named):
            sides = named
        elif len(surfaces) == 2:  # from position (so the position check below has nothing to add)
            sides, by_position = guess_sides([float(s.vertices[:, 0].mean()) for s in surfaces]), True
        elif len(surfaces) == 1:  # one lung: its shape (the concave medial face) tells, when it is clear
            shape_side, _ = clear_side(surfaces[0].vertices, surfaces[0].faces)
            if shape_side is None:
                raise InputError(f"cannot tell the side of {surfaces[0].name} (its shape is not clear enough): "
                                 "pass --side left or --side right")
            return [shape_side]
        else:
            raise InputError(f"cannot tell the sides of {len(surfaces)} surfaces: pass --side for each")
    for sd, s in zip(sides, surfaces) if check else ():  # each lung is the side its shape says, when that is clear
        check_side(s.vertices, s.faces, sd, s.name)
    if sorted(sides) == ["left", "right"] and not by_position:
        x = {sd: float(s.vertices[:, 0].mean()) for sd, s in zip(sides, surfaces)}
        if x["left"] <= x["right"]:
            name = {sd: s.name for sd, s in zip(sides, surfaces)}
            raise InputError(f"the surface taken as left ({name['left']}, mean x {x['left']:.0f} mm) lies to the "
                             f"patient's right of the one taken as right ({name['right']}, {x['right']:.0f} mm); in "
                             "LPS the left lung has the larger x: sides or labels swapped, or the meshes are in RAS")
    return sides


def stiffness_field(spec: str, surface, gravity):
    """Per-vertex moduli from the --stiffness option (None = uniform)."""

    kind, _, args = spec.partition(":")
    kind = kind.strip().lower()
    if kind == "uniform" and not args:
        return None
    if kind == "gradient":
        vals = _floats(args)
        if vals is None or len(vals) != 2:
            raise InputError("--stiffness gradient needs DEPENDENT,NONDEPENDENT moduli, e.g. gradient:0.5,1.5")
        return st.gravity_gradient(surface.vertices, gravity_vector(gravity), *vals)
    if kind == "sphere":
        nums = _floats(args)
        if nums is None or len(nums) != 5:
            raise InputError("--stiffness sphere needs X,Y,Z,RADIUS,E (mm, LPS; relative modulus)")
        return st.sphere_override(st.uniform(surface.n_vertices), surface.vertices, nums[:3], nums[3], nums[4])
    raise InputError(f"--stiffness must be uniform, gradient:D,N or sphere:X,Y,Z,R,E, got {spec!r}")


def _floats(text: str):
    try:
        return [float(x) for x in text.split(",")] if text else []
    except ValueError:
        return None
