"""``lungdeform demo --out DIR``: the main job on the embedded default lungs."""

from __future__ import annotations

from pathlib import Path

import typer

from .common import output_dir, parse_orientation, say


def register(apps) -> None:
    @apps.root.command("demo")
    def demo(
        out: Path = typer.Option(Path("demo-out"), "--out", "-o", help="Output folder."),
        duration_s: float = typer.Option(5.0, "--duration", help="Length of the breath (s)."),
        tidal_ml: float = typer.Option(500.0, "--tidal-ml", help="Tidal volume, both lungs (mL)."),
        orientation: str = typer.Option("supine", "--orientation", help="supine, prone, upright, left-decubitus, right-decubitus or 'x,y,z'."),
    ):
        """Build both embedded lungs (Table I, supine) and play one breath."""
        from lungdeform.demo import run_demo

        folder = output_dir(out)
        r = run_demo(folder, duration_s=duration_s, tidal_ml=tidal_ml,
                     orientation=parse_orientation(orientation), progress=say)
        for name, lung in r.summary_data["lungs"].items():
            vols = lung["volume_ml"]
            typer.echo(f"{name:>5}: {lung['vertices']} vertices, V_EE {lung['volume_ee_ml']:.0f} mL → "
                       f"peak {max(vols):.0f} mL (+{max(vols) - lung['volume_ee_ml']:.0f}), "
                       f"max volume error {lung['max_volume_error_percent']:.3f} %")
        typer.echo(f"model:       {r.model}")
        typer.echo(f"time series: {r.series}")
        typer.echo(f"summary:     {r.summary}")
        typer.echo(f"snapshot:    {r.snapshot}")
