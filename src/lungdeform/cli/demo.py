"""``lungdeform demo --out DIR``: the main job on the embedded default lungs."""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.errors import InputError
from lungdeform.playback.demo import run_demo

from .common import (
    BREATHING_HELP,
    CONSTANTS_HELP,
    DOME_MM_HELP,
    check_number,
    check_tidal_ml,
    dome_lines,
    dome_request,
    parse_orientation,
    say,
    tidal_option,
)

#: Longest playback the demo writes (s): its ParaView series is 20 files (~2.7 MB) per second.
MAX_DURATION_S = 300.0


def register(apps) -> None:
    @apps.root.command("demo")
    def demo(
        out: Path = typer.Option(Path("demo-out"), "--out", "-o", help="Output folder."),
        preset: str = typer.Option("normal", "--preset", help="Breathing preset of the PV model (lungdeform.breathing.presets, as in 'lungdeform breathe --preset'); an unknown name lists them."),
        duration_s: float | None = typer.Option(None, "--duration", callback=_duration_option, help="Length played (s); default one breath of the preset."),
        tidal_ml: float | None = typer.Option(None, "--tidal-ml", callback=tidal_option, help="Tidal volume, both lungs (mL); default the preset's."),
        orientation: str = typer.Option("supine", "--orientation", help="supine, prone, upright, left-decubitus, right-decubitus or 'x,y,z'."),
        constants: str = typer.Option("population", "--constants", help=CONSTANTS_HELP),
        dome_mm: str | None = typer.Option(None, "--dome-mm", help=DOME_MM_HELP),
        breathing: str | None = typer.Option(None, "--breathing", help=BREATHING_HELP),
    ):
        """Build both embedded lungs (population default, supine) and play one breath of a PV-model preset."""

        check_tidal_ml(tidal_ml)
        dome = dome_request(dome_mm, breathing)
        gravity = parse_orientation(orientation)
        r = run_demo(out, preset=preset, duration_s=duration_s, tidal_ml=tidal_ml,
                     orientation=gravity, constants=constants, dome=dome, progress=say)
        b = r.summary_data["breathing"]
        typer.echo(f"breathing: preset '{b['preset']}' ({b['description']}), {r.summary_data['duration_s']:g} s "
                   f"at {r.summary_data['frames_per_second']:.2f} frames/s, {r.summary_data['tidal_ml']:g} mL")
        for name, lung in r.summary_data["lungs"].items():
            vols = lung["volume_ml"]
            typer.echo(f"{name:>5}: {lung['vertices']} vertices, V_EE {lung['volume_ee_ml']:.0f} mL → "
                       f"peak {max(vols):.0f} mL (+{max(vols) - lung['volume_ee_ml']:.0f}), "
                       f"max volume error {lung['max_volume_error_percent']:.2g} % "
                       f"(linear reading {lung['linear_reading_max_error_percent']:.3f} %)")
        shares = {name: lung["tidal_share_ml"] for name, lung in r.summary_data["lungs"].items()}
        for line in dome_lines(r.summary_data.get("dome"), shares):
            typer.echo(line)
        typer.echo(f"model:       {r.model}")
        typer.echo(f"time series: {r.series}")
        typer.echo(f"summary:     {r.summary}")
        typer.echo(f"snapshot:    {r.snapshot}")


def _duration_option(value: float | None) -> float | None:
    """The ``callback=`` of ``--duration``: a finite length in (0, :data:`MAX_DURATION_S`] s."""
    if value is not None and value > MAX_DURATION_S:
        raise InputError(f"--duration must be at most {MAX_DURATION_S:g} s, got {value:g}: the demo writes "
                         "20 mesh files per second of playback; for long playback use 'lungdeform export "
                         "--format glb --preset NAME --cycles N' (one file)")
    return check_number(value, "--duration", 0, MAX_DURATION_S, "s", low_open=True)


_duration_option.bounds = (0.0, MAX_DURATION_S)
