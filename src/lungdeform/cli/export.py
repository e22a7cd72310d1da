"""``lungdeform export``: a model file as glTF 2.0 binary (3-D engines) or a VTK time series (ParaView)."""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.breathing.presets import get_preset
from lungdeform.errors import InputError
from lungdeform.io.modelfile import load_model
from lungdeform.playback import export as E
from lungdeform.playback import markers as M
from lungdeform.playback import schedule as S
from lungdeform.playback.trajectory import read_markers_csv

from .common import bounded, check_cycles, check_output, check_tidal_ml, read_curve, tidal_option


def register(apps) -> None:
    @apps.root.command("export")
    def export_command(
        model: Path = typer.Argument(..., help="Model file (.npz) written by build, fit or demo."),
        fmt: str = typer.Option(..., "--format", help="glb (glTF 2.0 binary, morph targets) or pvd (VTK .pvd + .vtp)."),
        out: Path = typer.Option(..., "--out", help="Output file (.glb or .pvd; frames go beside a .pvd), or an existing folder (MODEL's name is used)."),
        curve: Path | None = typer.Option(None, "--curve", help="Breathing curve CSV (t_s, volume_ml, …) from 'lungdeform breathe'."),
        preset: str | None = typer.Option(None, "--preset", help="Breathing preset of the PV model, simulated: normal, deep, copd, restrictive, dyspnoea or pneumothorax (not with --curve)."),
        cycles: int | None = typer.Option(None, "--cycles", help="With --preset: whole breaths played (default 1)."),
        markers: Path | None = typer.Option(None, "--markers", help="Markers CSV: x_mm,y_mm,z_mm[,label] (LPS, end-exhale); they move with the lung's interior field; glb only."),
        tidal_ml: float | None = typer.Option(None, "--tidal-ml", callback=tidal_option, help="Tidal volume, both lungs (mL): of the plain cycle (default 500), or the --preset rescaled to it (same shape; default the preset's)."),
        period_s: float | None = typer.Option(None, "--period", callback=bounded(0, 60, "s", low_open=True), help="Plain cycle only (no --curve, no --preset): period (s), default 4."),
        fps: float = typer.Option(10.0, "--fps", callback=bounded(0, 1000, "Hz", low_open=True), help="pvd only: frames per second of the time series."),
    ) -> None:
        """Export MODEL for engines (glb: one mesh, morph targets, breathing animation) or ParaView (pvd)."""

        kind = fmt.strip().lower()
        if kind not in ("glb", "pvd"):
            raise InputError(f"--format must be glb or pvd, got {fmt!r}")
        if markers is not None and kind != "glb":
            raise InputError("--markers applies to --format glb only")
        if out.is_dir():  # an existing folder: the file goes inside it, named after the model
            out = out / f"{Path(model).stem}.{kind}"
        out_path = out if out.suffix.lower() == f".{kind}" else out.with_name(f"{out.name}.{kind}")
        check_output(out_path, [model, curve, markers])
        if curve is not None and preset is not None:
            raise InputError("--curve and --preset are mutually exclusive: give one breathing curve")
        if curve is not None and (tidal_ml, period_s, cycles) != (None, None, None):
            raise InputError("--tidal-ml, --period and --cycles do not apply to --curve (the curve file sets them)")
        if preset is not None and period_s is not None:
            raise InputError("--period applies to the plain cycle; a --preset has its own period")

        check_cycles(cycles, preset)
        check_tidal_ml(tidal_ml)
        if preset is not None:
            chosen = get_preset(preset)  # an unknown name: InputError listing the names
        m = load_model(model)
        if curve is not None:
            trace = read_curve(curve, m)
        elif preset is not None:
            params, _curve, trace = S.preset_trace(chosen, cycles or 1, tidal_ml)
            typer.echo(f"preset {chosen.name}: {cycles or 1} × {params.period_s:g} s, PV model end-exhale "
                       f"{trace.shifted_ml:.0f} mL; playing the volume above it")
        else:
            given = {"tidal_ml": tidal_ml, "period_s": period_s}
            trace = S.plain_cycle(**{k: v for k, v in given.items() if v is not None})  # defaults 500 mL, 4 s
        shares = S.lung_shares(m)
        typer.echo(f"curve: {trace.source}, {trace.t_s[-1]:.2f} s, {len(trace.t_s)} samples, "
                   f"ΔV {trace.volume_ml.min():.0f}…{trace.volume_ml.max():.0f} mL split "
                   + ", ".join(f"{k} {v:.2f}" for k, v in shares.items()))
        if kind == "glb":
            anchors = None
            if markers is not None:
                pts, labels = read_markers_csv(markers)
                anchors = M.marker_anchors(m, pts, labels, source=str(markers))
                shown = [f"{a['label']} in {a['lung']}" + ("" if a["inside"] else f" ({a['distance_mm']:.0f} mm outside)")
                         for a in anchors[:6]]
                typer.echo(f"markers: {len(anchors)} ({'; '.join(shown)}{' …' if len(anchors) > 6 else ''}), "
                           "moving with each lung's interior field")
            E.export_glb(m, out_path, trace, anchors)
            typer.echo(f"wrote {out_path} ({out_path.stat().st_size / 1e6:.2f} MB: "
                       f"{sum(l.n_vertices for l in m.lungs.values())} vertices, 5 morph targets per lung, "
                       "animation 'breathing')")
        else:
            E.export_pvd(m, out_path, trace, fps=fps)
            frames = out_path.parent / f"{out_path.stem}_frames"
            size = sum(f.stat().st_size for f in frames.iterdir())
            typer.echo(f"wrote {out_path} and {len(list(frames.iterdir()))} frames in {frames} ({size / 1e6:.1f} MB)")
