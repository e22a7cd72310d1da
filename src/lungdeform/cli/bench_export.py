"""``lungdeform bench export [--vertices N …]``: the OpenUSD / USDZ exports' size and time against the glb of
the same model and curve, measured in the same run (:mod:`lungdeform.bench.export`)."""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.bench.export import export_record
from lungdeform.bench.viewer import model_with_vertices
from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.model.lung import build_model
from lungdeform.playback.usd import require_usd

from .common import say, write_bench_json


def _print(row: dict) -> None:
    typer.echo(f"{row['model']}: {row['vertices']} vertices, {row['frames']} frames ({row['curve']})")
    for name, f in row["formats"].items():
        typer.echo(f"  {name:<13} {f['bytes'] / 1e6:9.3f} MB ({f['bytes_ratio_to_glb']:5.2f}× glb)  "
                   f"{f['seconds']:8.3f} s ({f['seconds_ratio_to_glb']:5.2f}× glb)")


def register(apps) -> None:
    @apps.bench.command("export")
    def export_command(
        vertices: list[int] = typer.Option([], "--vertices", "-n", help="Also models of about N vertices, both lungs (the embedded lungs subdivided; repeat the option)."),
        repeats: int = typer.Option(3, "--repeats", help="Exports of each format per model (the median time is reported)."),
        baked_max: int = typer.Option(100_000, "--baked-max-vertices", help="Skip the baked USDZ above this many vertices."),
        json_path: Path | None = typer.Option(None, "--json", help="Write results here."),
    ):
        """Bytes and seconds of glb, USD (blend shapes) and USDZ (blend shapes, baked) for the embedded lungs and N-vertex models."""

        for n in vertices:
            if n < 1000:
                raise InputError(f"--vertices must be at least 1000, got {n}")
        if repeats < 1:
            raise InputError(f"--repeats must be >= 1, got {repeats}")
        require_usd()
        say("building the embedded lungs' model")
        rows = [export_record(build_model(default_lungs()), "embedded lungs", repeats=repeats,
                              baked_max_vertices=baked_max)]
        _print(rows[0])
        for n in vertices:
            model = model_with_vertices(n, say)
            rows.append(export_record(model, f"{n} vertices", repeats=repeats, baked_max_vertices=baked_max))
            _print(rows[-1])
        if json_path:
            write_bench_json(json_path, rows, "export")
            typer.echo(f"results written to {json_path}")
