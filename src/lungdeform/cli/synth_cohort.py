"""``lungdeform synth-cohort``: a synthetic cohort with known truth.

Writes lung surfaces deformed by the model itself from the shipped real lung shapes, a
``manifest.csv`` for ``lungdeform cohort`` and ``truth.json`` (see :mod:`lungdeform.cohort.synthetic`).
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.atomic import staged_dir
from lungdeform.cohort.synthetic import SyntheticLungSpec, synthetic_cohort, write_cohort
from lungdeform.errors import InputError

from .common import bounded, check_output, say, takes


def _floats(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{option} must be numbers in mL separated by commas, got {text!r}") from None
    if not values or any(not v > 0 for v in values) or any(b <= a for a, b in zip(values, values[1:])):
        raise InputError(f"{option} must list volume changes in mL, positive and increasing, got {text!r}")
    return values


@dataclass(frozen=True, kw_only=True)
class SynthCohortOptions:
    """The options of ``lungdeform synth-cohort`` (:func:`register`)."""

    out: Annotated[Path, typer.Option("--out", help="Output folder: surfaces/, landmarks/, truth/, manifest.csv, truth.json.")]
    subjects: Annotated[int, typer.Option("--subjects", help="Number of subjects (one left and one right lung each).")] = 4
    noise_mm: Annotated[float, typer.Option("--noise-mm", callback=bounded(0, 50, "mm"), help="SD of Gaussian noise along the vertex normal of the larger-volume surfaces, mm.")] = 0.0
    seed: Annotated[int, typer.Option("--seed", help="Seed of every random draw (constants, shape scale, noise, landmarks).")] = 0
    volumes: Annotated[str, typer.Option("--volumes", help="Volume changes above end-exhale, mL, increasing, comma-separated.")] = "300,500"
    law: Annotated[str, typer.Option("--law", help="'exact': each surface encloses exactly V_EE + ΔV; 'linear': p + (ΔV/ΔV1)·u, the fit's playback.")] = "exact"
    spread: Annotated[float, typer.Option("--spread", callback=bounded(0, 2), help="Log-normal SD of c1…c6 around Table I.")] = 0.2
    shape_spread: Annotated[float, typer.Option("--shape-spread", callback=bounded(0, 0.9), help="Anisotropic scale of each shape, uniform in 1 ± this, per axis.")] = 0.1
    landmarks: Annotated[int, typer.Option("--landmarks", help="Surface landmarks per lung at their true positions (0: none).")] = 50
    table_shift_mm: Annotated[float, typer.Option("--table-shift-mm", callback=bounded(0, 200, "mm"), help="SD per axis of a known random translation of each larger-volume scan, mm (tests --align joint).")] = 0.0


def register(apps) -> None:
    @apps.root.command("synth-cohort")
    @takes(SynthCohortOptions)
    def synth_cohort_command(opts: SynthCohortOptions) -> None:
        """Generate a synthetic cohort with known constants, volumes and noise (truth.json)."""

        check_output(opts.out, folder=True)  # a file or a folder that takes no file: refused before the work
        deltas = _floats(opts.volumes, "--volumes")
        spec = SyntheticLungSpec(noise_mm=opts.noise_mm, law=opts.law, landmarks=opts.landmarks, table_shift_mm=opts.table_shift_mm)
        lungs = synthetic_cohort(opts.subjects, delta_ml=deltas, spec=spec, seed=opts.seed, spread=opts.spread,
                                 shape_spread=opts.shape_spread, progress=say)
        folder = opts.out
        with staged_dir(folder) as staged:  # every file appears at the end, together, or none does
            info = write_cohort(lungs, staged, seed=opts.seed, progress=say)
        info = {k: (folder / Path(v).relative_to(staged) if isinstance(v, Path) and Path(v).is_relative_to(staged) else v)
                for k, v in info.items()}
        typer.echo(f"{'subject':<10} {'side':<6} {'source':<22} {'V_EE mL':>8}  c1…c9")
        for lung in lungs:
            cs = " ".join(f"{c:.3f}" for c in lung.constants)
            typer.echo(f"{lung.subject:<10} {lung.side:<6} {lung.source:<22} {lung.volume_ee_ml:8.1f}  {cs}")
        typer.echo(f"wrote {info['rows']} surfaces for {len(lungs)} lungs under {folder}")
        typer.echo(f"wrote {info['manifest']} and {info['truth']}")
        how = "joint" if opts.table_shift_mm > 0 else "none"

        typer.echo(f"fit with: lungdeform cohort {shlex.quote(str(info['manifest']))} --out OUT --align {how} "
                   f"(the files are in one frame{'' if how == 'none' else ' up to the table shifts'})")
