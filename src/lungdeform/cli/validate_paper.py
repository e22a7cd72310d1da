"""``lungdeform validate paper``: the paper's own validation (Sec. IV-A, Figs. 7–9)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from lungdeform.atomic import write_text
from lungdeform.errors import InputError
from lungdeform.validate import paper as P

from .common import bounded


def register(apps) -> None:
    @apps.validate.command("paper")
    def paper_command(
        out: Path = typer.Option(..., "--out", help="Output folder: metrics.json and the PNG figures go there."),
        grid: int = typer.Option(41, "--grid", help="Planar mesh vertices per side (Figs. 7–8)."),
        rings: int = typer.Option(12, "--rings", help="Rings of the circular mesh (Fig. 9)."),
        spacing: float = typer.Option(3.0, "--spacing", callback=bounded(0, 100, "mm", low_open=True), help="Mesh spacing, mm."),
        tol: float = typer.Option(1e-6, "--tol", callback=bounded(0, 1, low_open=True, high_open=True), help="Relative residual that counts as converged (Fig. 7)."),
    ) -> None:
        """Transfer model vs a mass–spring–damper run to rest; variable-E disc; convergence curves."""


        out = Path(out)
        if out.exists() and not out.is_dir():
            raise InputError(f"--out {out}: exists and is not a directory")
        if grid < 3:
            raise InputError(f"--grid must be ≥ 3 vertices per side, got {grid}")
        if rings < 2:
            raise InputError(f"--rings must be ≥ 2, got {rings}")
        out.mkdir(parents=True, exist_ok=True)

        t0 = time.perf_counter()
        planar = P.planar_experiment(grid, grid, spacing, tol=min(1e-10, tol))
        circular = P.circular_experiment(rings, spacing)
        conv = P.convergence_experiment(grid, grid, spacing, tol=tol, curve_tol=min(1e-10, tol))
        elapsed = time.perf_counter() - t0
        figures = {
            "fig7_convergence": P.write_convergence_figure(conv, out / "fig7_convergence.png"),
            "fig8_planar": P.write_planar_figure(planar, out / "fig8_planar.png"),
            "fig9_circular": P.write_circular_figure(circular, out / "fig9_circular.png"),
        }
        metrics = {
            "planar": planar.to_dict(),
            "circular": circular.to_dict(),
            "convergence": conv.to_dict(),
            "figures": {k: v.name for k, v in figures.items()},
            "elapsed_s": elapsed,
        }
        path = out / "metrics.json"

        write_text(path, json.dumps(metrics, indent=2) + "\n")

        typer.echo(f"Fig. 8  planar {grid}×{grid}, uniform E: MSD vs transfer RMS {planar.rms_percent:.3g} % "
                   f"of max (paper < 0.1 %); MSD settled in {planar.msd.steps} steps")
        typer.echo(f"Fig. 9  disc, {rings} rings, variable E: stiff/soft radial displacement ratio "
                   f"{circular.stiff_to_soft_displacement_ratio:.3g}; all nodes outward: "
                   f"{circular.min_radial_displacement > 0}")
        typer.echo(f"Fig. 7  to {tol:g}: push {conv.push_iterations} pushes ({conv.push_sweeps:.1f} sweeps), "
                   f"MSD {conv.msd_iterations} steps ({conv.msd_sweeps:.0f} sweeps) on {conv.n_nodes} nodes")
        typer.echo(f"wrote {path} and {len(figures)} figures in {out} ({elapsed:.2f} s)")
