"""``lungdeform export``: a model file as glTF 2.0 binary (3-D engines), OpenUSD / USDZ (Apple AR, Omniverse,
Houdini, Blender) or a VTK time series (ParaView)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.breathing.presets import get_preset
from lungdeform.errors import InputError
from lungdeform.io.modelfile import load_model
from lungdeform.playback import export as E
from lungdeform.playback import markers as M
from lungdeform.playback import schedule as S
from lungdeform.playback import usd as U
from lungdeform.playback.trajectory import read_markers_csv

from .common import bounded, check_cycles, check_output, check_tidal_ml, read_curve, takes, tidal_option


@dataclass(frozen=True, kw_only=True)
class ExportOptions:
    """The options of ``lungdeform export`` (:func:`register`)."""

    model: Annotated[Path, typer.Argument(help="Model file (.npz) written by build, fit or demo.")]
    fmt: Annotated[str, typer.Option("--format", help="glb (glTF 2.0 binary, morph targets), usd, usdc, usda or usdz (OpenUSD: one blend shape per lung; usdz for Apple AR) or pvd (VTK .pvd + .vtp).")]
    out: Annotated[Path, typer.Option("--out", help="Output file ending in .glb, .usd, .usdc, .usda, .usdz or .pvd as --format says (a name without a suffix gets it; another suffix is refused; frames go beside a .pvd), or an existing folder (MODEL's name is used).")]
    curve: Annotated[Path | None, typer.Option("--curve", help="Breathing curve CSV (t_s, volume_ml, …) from 'lungdeform breathe'.")] = None
    preset: Annotated[str | None, typer.Option("--preset", help="Breathing preset of the PV model, simulated: normal, deep, copd, restrictive, dyspnoea or pneumothorax (not with --curve).")] = None
    cycles: Annotated[int | None, typer.Option("--cycles", help="With --preset: whole breaths played (default 1).")] = None
    markers: Annotated[Path | None, typer.Option("--markers", help="Markers CSV: x_mm,y_mm,z_mm[,label] (LPS, end-exhale); they move with the lung's interior field; glb only.")] = None
    tidal_ml: Annotated[float | None, typer.Option("--tidal-ml", callback=tidal_option, help="Tidal volume, both lungs (mL): of the plain cycle (default the model's own, else 500), or the --preset rescaled to it (same shape; default the preset's).")] = None
    period_s: Annotated[float | None, typer.Option("--period", callback=bounded(0, 60, "s", low_open=True), help="Plain cycle only (no --curve, no --preset): period (s), default 4.")] = None
    fps: Annotated[float | None, typer.Option("--fps", callback=bounded(0, 1000, "Hz", low_open=True), help="pvd: frames per second of the time series (default 10). USD: time codes per second, the curve resampled at it (default: the curve's own samples when evenly spaced, else 30).")] = None
    baked: Annotated[bool, typer.Option("--baked", help="USD only: time-sampled points at every frame (a vertex cache) instead of blend shapes.")] = False


def register(apps) -> None:
    @apps.root.command("export")
    @takes(ExportOptions)
    def export_command(opts: ExportOptions) -> None:
        """Export MODEL for engines (glb: morph targets; usd/usdc/usda/usdz: blend shapes, or --baked points) or ParaView (pvd)."""

        kind = opts.fmt.strip().lower()
        if kind not in FORMATS:
            raise InputError(f"--format must be one of {', '.join(FORMATS)}, got {opts.fmt!r}")
        if opts.markers is not None and kind != "glb":
            raise InputError("--markers applies to --format glb only")
        if opts.baked and kind not in USD_KINDS:
            raise InputError(f"--baked applies to the USD formats ({', '.join(USD_KINDS)}) only")
        if opts.fps is not None and kind == "glb":
            raise InputError("--fps does not apply to --format glb (it plays the curve's own samples)")
        if kind in USD_KINDS:
            U.require_usd()  # a missing extra is said before any work
        out = opts.out
        if out.is_dir():  # an existing folder: the file goes inside it, named after the model
            out = out / f"{Path(opts.model).stem}.{kind}"
        out_path = _out_path(out, kind)
        check_output(out_path, [opts.model, opts.curve, opts.markers])
        if opts.curve is not None and opts.preset is not None:
            raise InputError("--curve and --preset are mutually exclusive: give one breathing curve")
        if opts.curve is not None and (opts.tidal_ml, opts.period_s, opts.cycles) != (None, None, None):
            raise InputError("--tidal-ml, --period and --cycles do not apply to --curve (the curve file sets them)")
        if opts.preset is not None and opts.period_s is not None:
            raise InputError("--period applies to the plain cycle; a --preset has its own period")

        check_cycles(opts.cycles, opts.preset)
        check_tidal_ml(opts.tidal_ml)
        if opts.preset is not None:
            chosen = get_preset(opts.preset)  # an unknown name: InputError listing the names
        m = load_model(opts.model)
        if opts.curve is not None:
            trace = read_curve(opts.curve, m)
        elif opts.preset is not None:
            params, _curve, trace = S.preset_trace(chosen, opts.cycles or 1, opts.tidal_ml)
            typer.echo(f"preset {chosen.name}: {opts.cycles or 1} × {params.period_s:g} s, PV model end-exhale "
                       f"{trace.shifted_ml:.0f} mL; playing the volume above it")
        else:  # the model's own tidal volume (500 mL for a fit), 4 s, unless given
            given = {"tidal_ml": opts.tidal_ml or (m.provenance or {}).get("tidal_ml"), "period_s": opts.period_s}
            trace = S.plain_cycle(**{k: v for k, v in given.items() if v is not None})
        S.check_reachable(trace, m)  # a --tidal-ml far beyond the lungs' size: refused (a --curve was checked)
        shares = S.lung_shares(m)
        if not m.scan.is_end_exhale:  # the lungs are written at end-exhale, where the weights start
            typer.echo(f"the model's scan: {m.scan.describe()}; written at end-exhale, the scan at each lung's "
                       "morph weight 'scan_weight' (mesh extras)")
        typer.echo(f"curve: {trace.source}, {trace.t_s[-1]:.2f} s, {len(trace.t_s)} samples, "
                   f"ΔV {trace.volume_ml.min():.0f}…{trace.volume_ml.max():.0f} mL split "
                   + ", ".join(f"{k} {v:.2f}" for k, v in shares.items()))
        if kind == "glb":
            _write_glb(opts, m, out_path, trace)
        elif kind in USD_KINDS:
            _write_usd(opts, m, out_path, trace)
        else:
            E.export_pvd(m, out_path, trace, fps=10.0 if opts.fps is None else opts.fps)
            frames = out_path.parent / f"{out_path.stem}_frames"
            size = sum(f.stat().st_size for f in frames.iterdir())
            typer.echo(f"wrote {out_path} and {len(list(frames.iterdir()))} frames in {frames} ({size / 1e6:.1f} MB)")


#: ``--format`` values; each writes a file with that suffix.
FORMATS = ("glb", "usd", "usdc", "usda", "usdz", "pvd")
USD_KINDS = ("usd", "usdc", "usda", "usdz")


def _write_glb(opts: ExportOptions, m, out_path: Path, trace) -> None:
    anchors = None
    if opts.markers is not None:
        pts, labels = read_markers_csv(opts.markers)
        anchors = M.marker_anchors(m, pts, labels, source=str(opts.markers))
        shown = [f"{a['label']} in {a['lung']}" + ("" if a["inside"] else f" ({a['distance_mm']:.0f} mm outside)")
                 for a in anchors[:6]]
        typer.echo(f"markers: {len(anchors)} ({'; '.join(shown)}{' …' if len(anchors) > 6 else ''}), "
                   "moving with each lung's interior field")
    E.export_glb(m, out_path, trace, anchors)
    typer.echo(f"wrote {out_path} ({out_path.stat().st_size / 1e6:.2f} MB: "
               f"{sum(l.n_vertices for l in m.lungs.values())} vertices, 5 morph targets per lung, "
               "animation 'breathing')")


def _write_usd(opts: ExportOptions, m, out_path: Path, trace) -> None:
    frames = U.usd_frames(trace, opts.fps)
    n = len(frames.t_s)
    if frames.resampled:
        why = f"--fps {opts.fps:g}" if opts.fps is not None else "its samples are not evenly spaced"
        typer.echo(f"curve resampled ({why}): {n} frames at {frames.fps:g} per second")
    size = U.baked_bytes(m, U.lung_weights(m, frames), out_path.suffix) if opts.baked else 0
    if size > U.BAKED_WARN_BYTES:
        typer.echo(f"warning: the baked file will be about {size / 1e6:.0f} MB ({n} frames of every vertex); the "
                   "blend-shape file (no --baked) plays the same motion from one offset per vertex", err=True)
    U.export_usd(m, out_path, trace, fps=opts.fps, baked=opts.baked)
    motion = "points at every time code (baked)" if opts.baked else "one blend shape per lung, its weight at every time code"
    typer.echo(f"wrote {out_path} ({out_path.stat().st_size / 1e6:.2f} MB: "
               f"{sum(l.n_vertices for l in m.lungs.values())} vertices, {motion}; time codes 0…{n - 1} "
               f"at {frames.fps:g} per second, Y up, metres)")


def _out_path(out: Path, kind: str) -> Path:
    """The file ``--out`` names for ``--format kind``: ``.kind`` appended to a name without a suffix;
    a name ending in another suffix (``e3.pvd`` with ``--format glb``) is refused, not renamed."""
    if out.suffix.lower() == f".{kind}":
        return out
    if not out.suffix:
        return out.with_name(f"{out.name}.{kind}")
    other = out.suffix.lower()[1:]
    if other in FORMATS:
        raise InputError(f"--out {out}: --format {kind} writes a .{kind} file, not .{other}; name it "
                         f"{out.with_suffix(f'.{kind}').name} or give --format {other}")
    raise InputError(f"--out {out}: --format {kind} writes a .{kind} file, but the name ends in {out.suffix}; "
                     f"name it {out.name}.{kind}")
