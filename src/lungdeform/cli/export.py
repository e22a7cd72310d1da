"""``lungdeform export``: a model file as glTF 2.0 binary (3-D engines) or a VTK time series (ParaView)."""

from __future__ import annotations

from pathlib import Path

import typer


def register(apps) -> None:
    @apps.root.command("export")
    def export_command(
        model: Path = typer.Argument(..., help="Model file (.npz) written by build, fit or demo."),
        fmt: str = typer.Option(..., "--format", help="glb (glTF 2.0 binary, morph targets) or pvd (VTK .pvd + .vtp)."),
        out: Path = typer.Option(..., "--out", help="Output file (.glb or .pvd; frames go beside a .pvd)."),
        curve: Path | None = typer.Option(None, "--curve", help="Breathing curve CSV (t_s, volume_ml, …) from 'lungdeform breathe'."),
        markers: Path | None = typer.Option(None, "--markers", help="Markers CSV: x_mm,y_mm,z_mm[,label] (LPS, end-exhale); glb only."),
        tidal_ml: float = typer.Option(500.0, "--tidal-ml", help="Plain cycle without --curve: tidal volume (mL)."),
        period_s: float = typer.Option(4.0, "--period", help="Plain cycle without --curve: period (s)."),
        fps: float = typer.Option(10.0, "--fps", help="pvd only: frames per second of the time series."),
    ) -> None:
        """Export MODEL for engines (glb: one mesh, morph targets, breathing animation) or ParaView (pvd)."""
        from lungdeform import export as E
        from lungdeform.errors import InputError
        from lungdeform.modelfile import load_model

        kind = fmt.strip().lower()
        if kind not in ("glb", "pvd"):
            raise InputError(f"--format must be glb or pvd, got {fmt!r}")
        if markers is not None and kind != "glb":
            raise InputError("--markers applies to --format glb only")
        m = load_model(model)
        trace = E.read_volume_csv(curve) if curve is not None else E.plain_cycle(tidal_ml, period_s)
        if trace.shifted_ml:
            typer.echo(f"{curve}: volume_ml reads as absolute; subtracted its minimum {trace.shifted_ml:.1f} mL")
        shares = E.lung_shares(m)
        typer.echo(f"curve: {trace.source}, {trace.t_s[-1]:.2f} s, {len(trace.t_s)} samples, "
                   f"ΔV {trace.volume_ml.min():.0f}…{trace.volume_ml.max():.0f} mL split "
                   + ", ".join(f"{k} {v:.2f}" for k, v in shares.items()))
        if kind == "glb":
            out_path = out if out.suffix.lower() == ".glb" else out.with_name(out.name + ".glb")
            anchors = None
            if markers is not None:
                pts, labels = E.read_markers_csv(markers)
                anchors = E.marker_anchors(m, pts, labels)
            E.export_glb(m, out_path, trace, anchors)
            typer.echo(f"wrote {out_path} ({out_path.stat().st_size / 1e6:.2f} MB: "
                       f"{sum(l.n_vertices for l in m.lungs.values())} vertices, 5 morph targets per lung, "
                       "animation 'breathing')")
        else:
            out_path = out if out.suffix.lower() == ".pvd" else out.with_name(out.name + ".pvd")
            E.export_pvd(m, out_path, trace, fps=fps)
            frames = out_path.parent / f"{out_path.stem}_frames"
            size = sum(f.stat().st_size for f in frames.iterdir())
            typer.echo(f"wrote {out_path} and {len(list(frames.iterdir()))} frames in {frames} ({size / 1e6:.1f} MB)")
