"""``lungdeform bench dvf``: a displacement-field image against a trilinear resampling of the same grid."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lungdeform.bench.displacement_field import bench_dvf
from lungdeform.errors import InputError
from lungdeform.playback import displacement_field as D

from .common import bounded, say, write_bench_json


def register(apps) -> None:
    @apps.bench.command("dvf")
    def dvf(
        shape: str = typer.Option("150,512,512", "--shape", help="Grid size z,y,x (voxels)."),
        repeats: int = typer.Option(3, "--repeats", help="Timed runs of each, after a warm-up (the median)."),
        node_mm: float = typer.Option(4.0, "--node-mm", callback=bounded(0, D.MAX_NODE_MM, "mm", low_open=True), help="Lattice spacing (mm) of the interior field."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write results here."),
    ):
        """A displacement-field image of the embedded lungs against a trilinear resampling of the same grid."""

        try:
            zyx = tuple(int(x) for x in shape.split(","))
        except ValueError:
            raise InputError(f"--shape must be three whole numbers z,y,x, got {shape!r}") from None
        say(f"building the embedded lungs' model and a {'x'.join(map(str, zyx))} grid")
        r = bench_dvf(zyx, repeats, node_mm)
        typer.echo(f"grid {' x '.join(map(str, r['shape_zyx']))} voxels: field {r['field_seconds']:.2f} s "
                   f"({r['field_threads']} threads; {r['nodes_evaluated']} of {r['nodes']} lattice nodes evaluated), "
                   f"trilinear resampling "
                   f"{r['resample_seconds']:.2f} s ({r['threads']} threads): ratio {r['ratio']:.1f}x")
        typer.echo(f"CPU seconds (the process, every thread): field {r['field_cpu_seconds']:.2f}, resampling "
                   f"{r['resample_cpu_seconds']:.2f}: ratio {r['cpu_ratio']:.1f}x")
        typer.echo(f"Jacobian determinant {r['jacobian_min']:.3f} to {r['jacobian_max']:.3f}, margin "
                   f"{r['margin_mm']:.0f} mm, lattice {node_mm:g} mm, its error {r['lattice_error_mm']:.3f} mm")
        if json_path:
            write_bench_json(json_path, [r], "dvf")
            typer.echo(f"results written to {json_path}")
