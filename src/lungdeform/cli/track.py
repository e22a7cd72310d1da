"""``lungdeform track``: where interior points (a tumour, fiducials) go as the model breathes."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from lungdeform.atomic import staged_outputs, write_bytes
from lungdeform.errors import InputError
from lungdeform.geometry.moments import solid_moments
from lungdeform.io.dicom.rtstruct import (
    build_rtstruct,
    check_ct_is_scan,
    check_structure_on_ct,
    check_structure_on_scan,
    read_ct_series,
    save_rtstruct,
)
from lungdeform.io.dicom.series import MAX_PHASES
from lungdeform.io.modelfile import load_model
from lungdeform.playback import structures as R
from lungdeform.playback import trajectory as T
from lungdeform.playback.displacement_field import scan_state, volume_state
from lungdeform.playback.phases import check_zero, phase_schedule, scan_phase_text

from .common import (
    BREATH_HINT,
    BreathFlags,
    SeriesFlags,
    bounded,
    breath_trace,
    check_output,
    check_phase_index,
    check_trace_options,
    dicom_input,
    takes,
    without_alignment,
)

#: Bounds on the schedule: frames per second and points × frames (rows of trajectories.csv); preset
#: cycles: common.MAX_CYCLES
MAX_FPS = 1000.0
MAX_POINT_FRAMES = 5_000_000


@dataclass(frozen=True, kw_only=True)
class TrackOptions:
    """The options of ``lungdeform track`` (:func:`register`)."""

    model: Annotated[Path, typer.Argument(help="Model file (.npz) written by fit, build or demo.")]
    points: Annotated[Path | None, typer.Option("--points", help="Points to track, mm LPS of the scan the model was built from: CSV x_mm,y_mm,z_mm[,label] or an elastix 'point' file.")] = None
    out: Annotated[Path, typer.Option("--out", help="Output folder: trajectories.csv, points.json, motion.png.")]
    volume_ml: Annotated[list[float], typer.Option("--volume-ml", help="Absolute volume of the model's lungs together (mL); repeat for several.")] = field(default_factory=list)
    breath: BreathFlags = BreathFlags()  # --curve, --preset, --cycles, --tidal-ml, --phases, --phase, --phase-zero
    fps: Annotated[float, typer.Option("--fps", help="Frames per second sampled from a curve, preset or plain cycle (without --phases).")] = 25.0
    lung: Annotated[str | None, typer.Option("--lung", help="Put every point in this lung (default: the lung containing it, else the nearest).")] = None
    skip_invalid: Annotated[bool, typer.Option("--skip-invalid", help="Track the valid rows of a points CSV, leaving out (and listing) rows without finite x_mm,y_mm,z_mm; by default such a row is an error.")] = False
    rtstruct: Annotated[Path | None, typer.Option("--rtstruct", help="DICOM RTSTRUCT file (instead of --points): track the contour points of --structure.")] = None
    structure: Annotated[str | None, typer.Option("--structure", help="With --rtstruct: the ROI name (e.g. GTV).")] = None
    rigid_structure: Annotated[str | None, typer.Option("--rigid-structure", help="With --rtstruct: this ROI (e.g. GTV, usually --structure itself) moves rigidly, keeping its volume, as 'warp --rigid-structure' keeps it in the image; points near it follow its motion over --rigid-border-mm (docs/RADIOTHERAPY.md, \"A rigid tumour\").")] = None
    rigid_border_mm: Annotated[float, typer.Option("--rigid-border-mm", callback=bounded(0, 100, "mm", low_open=True), help="With --rigid-structure: width (mm) over which its rigid motion is blended back into the field.")] = 10.0
    out_rtstruct: Annotated[Path | None, typer.Option("--out-rtstruct", help="Write the moved structure, one ROI per volume or phase (NAME@TAG), as an RTSTRUCT on --reference-ct.")] = None
    reference_ct: Annotated[Path | None, typer.Option("--reference-ct", help="With --out-rtstruct: the DICOM CT series (folder) the structure was drawn on.")] = None
    scan: Annotated[int | None, typer.Option("--scan", help="Input scan K of the fit (0 = rest): its volume, in its own frame (the fit's alignment undone), as 'dvf --scan K'.")] = None
    no_rigid: Annotated[bool, typer.Option("--no-rigid", help="With --scan: leave the fit's alignment out (positions in the model's frame).")] = False
    dicom: SeriesFlags = SeriesFlags()  # --series / --series-description: which CT series of --reference-ct's folder


def register(apps) -> None:
    @apps.root.command("track")
    @takes(TrackOptions)
    def track_command(opts: TrackOptions) -> None:
        """Move interior points with the model: positions at given volumes or over a breathing curve.

        Without --volume-ml, --curve or --preset: one plain 4 s cosine breath of the model's tidal volume (500 mL)."""


        _check_schedule(opts.volume_ml, opts.breath, opts.fps)
        _check_phase(opts.breath.phases, opts.breath.phase, opts.breath.phase_zero)
        _check_rigid(opts.rigid_structure, opts.rtstruct)
        _check_scan(opts.scan, opts.no_rigid, opts.volume_ml or opts.breath.curve or opts.breath.preset, opts.breath.phases)
        _check_structure_options(opts.points, opts.rtstruct, opts.structure, opts.out_rtstruct, opts.reference_ct, opts.breath.phases,
                                 opts.volume_ml or ([] if opts.scan is None else [opts.scan]))
        _check_out_rtstruct(opts.out_rtstruct, opts.model, opts.points, opts.rtstruct, opts.breath.curve)
        check_output(opts.out, [opts.model, opts.points, opts.rtstruct, opts.breath.curve, opts.reference_ct], folder=True,
                     writes=("trajectories.csv", "points.json", "motion.png", "structure_motion.csv"))
        series = opts.dicom.choice()
        dicom_input(opts.reference_ct, series, "--reference-ct")
        m = load_model(opts.model)
        tracked = R.read_structure(opts.rtstruct, opts.structure) if opts.rtstruct is not None else None
        ct = _reference_ct(tracked, opts.rtstruct, opts.out_rtstruct, (opts.reference_ct, series), (m, opts.scan, opts.no_rigid))
        if tracked is not None:
            pts, labels, source = tracked.points, tracked.labels, str(opts.rtstruct)
        else:
            (pts, labels), source = _read_points(opts.points, opts.skip_invalid), str(opts.points)
        placement = T.place_points(m, pts, opts.lung, source=source)
        frames, tags, matrix = _frames(m, dict(volume_ml=opts.volume_ml, scan=opts.scan, no_rigid=opts.no_rigid, fps=opts.fps),
                                       opts.breath, len(pts), source)
        rigid_read = tracked if opts.rigid_structure in (None, opts.structure) else R.read_structure(opts.rtstruct, opts.rigid_structure)
        rigid = None if opts.rigid_structure is None else R.rigid_structure(
            m, opts.rtstruct, opts.rigid_structure, opts.rigid_border_mm, rigid_read)
        _check_rows(len(pts), len(frames.delta_ml), source)
        note = T.extrapolation_note(m, frames.delta_ml)
        if note:
            typer.echo(f"note: {note}")
        positions = _in_frame(R.moved_points(m, pts, placement, frames.delta_ml, rigid), matrix)
        built = None
        if opts.out_rtstruct is not None:  # made and checked (names, extent on the CT) before any output
            surfaces = [(n, _in_frame(v, matrix), f, k) for n, v, f, k in
                        R.moved_surfaces(m, tracked, frames.delta_ml, tags, opts.lung, source=f"{opts.rtstruct} {opts.structure}",
                                         rigid=rigid)]
            motion = R.motion_table(surfaces)
            surfaces.append(R.itv_surface(surfaces, opts.structure))  # the union over the states
            built = build_rtstruct(ct, surfaces, label=f"{opts.structure} moved", source=str(opts.rtstruct))
        meta = {"model": str(opts.model), "schedule": frames.source, "end_exhale_ml": T.end_exhale_ml(m),
                "scan_ml": T.scan_ml(m), "scan_state": m.scan.record(), **T.interior_meta(m),
                **({} if rigid is None else {"rigid_structure": rigid.name, "rigid_border_mm": rigid.border_mm})}
        ee = None if m.scan.is_end_exhale else R.moved_points(m, pts, placement, [0.0], rigid)[0]
        _say_fixed([tracked, rigid_read], surfaces if built is not None else [], built)
        with staged_outputs() as staging:  # every output staged, and renamed into place together at the end
            folder = staging.folder(opts.out)
            written = T.write_trajectories(folder, pts, labels, placement, positions, frames, meta=meta, end_exhale=ee)
            if built is not None:
                save_rtstruct(staging.file(opts.out_rtstruct), built[0])
                written["motion"] = write_bytes(folder / "structure_motion.csv", R.motion_csv({opts.structure: motion}))
        paths = {key: opts.out / Path(path).name for key, path in written.items()}
        if built is not None:
            typer.echo(f"wrote {opts.out_rtstruct}: " + ", ".join(f"{k} ({n} contours)" for k, n in built[1].items()))
            _print_motion(opts.structure, motion, surfaces[-1])
        typer.echo(f"{len(pts)} point(s), {len(frames.delta_ml)} frame(s): {frames.source}")
        if rigid is not None:
            typer.echo(f"  {rigid.name}: rigid (its best rigid motion under the field at each state, blended back over "
                       f"{rigid.border_mm:g} mm), as 'warp --rigid-structure {rigid.name}' moves it")
        origin = "end-exhale" if m.scan.is_end_exhale else f"the scan ({m.scan.describe()})"
        if tracked is None:
            _print_points(labels, placement, T.motion_summary(positions, pts), paths, origin)
        else:
            _print_structure(opts.structure, placement, T.motion_summary(positions, pts), origin)
        typer.echo(f"wrote {paths['csv']}, {paths['json']}, {paths['png']}")


def _say_fixed(read: list, surfaces: list, built) -> None:
    """What was done to the input, once every check has passed (stderr, ``note:``): each contour left
    out because it encloses no area (of each structure ``read``: --structure's, --rigid-structure's;
    None where not given), each ROI name cut to fit a ROI Name (its whole in ROIDescription)."""
    for line in dict.fromkeys(line for s in read if s is not None for line in s.skipped):
        typer.echo(f"note: {line}", err=True)
    for (name, *_rest), written in zip(surfaces, built[1] if built is not None else ()):
        if written != name:
            typer.echo(f"note: ROI name {name!r} ({len(name.encode())} bytes of UTF-8) is longer than a ROI Name holds "
                       f"(64 bytes): written as {written!r}, the whole name in ROIDescription", err=True)


def _print_motion(name: str, motion: list[dict], itv) -> None:
    """The structure's volume and centroid motion over the states, and its ITV's volume."""
    vols = [r["volume_ml"] for r in motion]
    amp = ", ".join(f"{x:.1f}" for x in motion[0]["amplitude_mm"])
    far = max(motion, key=lambda r: r["distance_mm"])
    itv_ml = solid_moments(itv[1], itv[2])[0] / 1000.0
    typer.echo(f"  {name}: volume {min(vols):.2f} to {max(vols):.2f} mL over {len(motion)} state(s); centroid "
               f"amplitude (x, y, z) ({amp}) mm LPS, farthest from {motion[0]['state']} at {far['state']} "
               f"({far['distance_mm']:.1f} mm); {itv[0]} {itv_ml:.2f} mL (structure_motion.csv)")


def _frames(m, given: dict, breath: BreathFlags, points: int, source: str):
    """``(frames, ROI tags, matrix)``: the states the options name (``given``: volume_ml, scan,
    no_rigid, fps; else the breath of ``breath``); ``matrix`` the 4×4 alignment (scan → model frame)
    whose inverse puts positions in scan K's frame (``--scan``, as ``dvf --scan``), or None."""
    if given["scan"] is not None:
        state = without_alignment(scan_state(m, given["scan"]), given["no_rigid"])
        return T.FrameSchedule(np.array([state.delta_ml]), None, state.source), [f"scan{given['scan']}"], state.alignment
    if given["volume_ml"]:
        for v in given["volume_ml"]:  # finite, and a volume the lungs reach (as dvf and warp check it)
            volume_state(m, v)
        return T.volume_frames(m, given["volume_ml"]), R.volume_tags(given["volume_ml"]), None
    trace = breath_trace(m, breath.curve, breath.preset, breath.cycles, breath.tidal_ml)
    if breath.phases is not None:
        frames, tags = R.phase_frames(trace, breath.phases, breath.phase_zero)
        typer.echo(scan_phase_text(trace, phase_schedule(trace, breath.phases, breath.phase_zero), m.scan))
        if breath.phase is not None:  # one phase of the breath, tagged as in the whole set
            k = breath.phase
            frames = T.FrameSchedule(frames.delta_ml[k:k + 1], frames.t_s[k:k + 1], f"{frames.source}, phase {k}")
            tags = tags[k:k + 1]
        return frames, tags, None
    _check_rows(points, (trace.t_s[-1] - trace.t_s[0]) * given["fps"] + 1, source)  # before the frames are made
    return T.trace_frames(trace, given["fps"]), [], None


def _in_frame(positions, matrix):
    """``positions : (…, 3)`` mm in the model's frame moved into a scan's by ``matrix⁻¹`` (4×4 scan →
    model, the fit's alignment); unchanged without one."""
    if matrix is None:
        return positions
    inv = np.linalg.inv(np.asarray(matrix, float))
    return np.asarray(positions, float) @ inv[:3, :3].T + inv[:3, 3]


def _check_rows(points: int, frames: float, source: str) -> None:
    """Refuse more than :data:`MAX_POINT_FRAMES` points × frames (rows of trajectories.csv)."""
    if not points * frames <= MAX_POINT_FRAMES:
        raise InputError(f"{source}: {points} point(s) x {frames:.0f} frame(s), more than {MAX_POINT_FRAMES} rows of "
                         "trajectories; lower --fps, or give --phases or --volume-ml")


def _reference_ct(tracked, rtstruct, out_rtstruct, reference_ct: tuple, state):
    """The reference CT (None without --out-rtstruct; ``reference_ct`` = (--reference-ct, its --series
    choice)), read and the structure checked on it before anything is written; warnings (another
    study; no frame of reference at all) on stderr.
    ``state`` = ``(model, --scan, --no-rigid)``: with ``--scan K`` the CT must be the scan whose
    frame the contours are in (:func:`_check_scan_ct`)."""
    if tracked is not None and not tracked.roi.frame_uid and out_rtstruct is None:
        typer.echo(f"warning: {rtstruct}: structure {tracked.roi.name!r} has no Frame of Reference UID: nothing shows "
                   "it was drawn in the frame of the model's end-exhale scan", err=True)
    if out_rtstruct is None:
        return None
    ct = read_ct_series(*reference_ct)
    if state[1] is not None and _check_scan_ct(ct, tracked, rtstruct, *state):
        return ct
    for line in check_structure_on_ct(tracked.roi, ct, str(rtstruct)):
        typer.echo(f"warning: {line}", err=True)
    return ct


def _check_scan_ct(ct, tracked, rtstruct, m, scan: int, no_rigid: bool) -> bool:
    """With ``--scan K``: ``ct`` must be the fitted scan whose frame the contours are in (the model's
    provenance ``scans``, :func:`~lungdeform.io.dicom.rtstruct.check_ct_is_scan`): scan K where the
    fit aligned it (its alignment undone), else scan K or, with --no-rigid, scan 0 (the model's
    frame). True when the structure was checked here instead (drawn on scan 0, written on scan K's
    CT in another frame: :func:`~lungdeform.io.dicom.rtstruct.check_structure_on_scan`)."""
    scans = (m.provenance or {}).get("scans")
    aligned = scan_state(m, scan).alignment is not None
    check_ct_is_scan(ct, scans, 0 if aligned and no_rigid else scan)
    if aligned and not no_rigid:
        check_structure_on_scan(tracked.roi, scans, str(rtstruct))
        return True
    return False


def _check_out_rtstruct(out_rtstruct: Path | None, *inputs: Path | None) -> None:
    """--out-rtstruct must name a file that is none of the inputs (it would be overwritten) and
    not an existing folder."""
    if out_rtstruct is None:
        return
    if out_rtstruct.is_dir():
        raise InputError(f"--out-rtstruct {out_rtstruct}: is a folder; give a file name (e.g. moved_rs.dcm)")
    for given in inputs:
        if given is not None and given.exists() and out_rtstruct.exists() and out_rtstruct.samefile(given):
            raise InputError(f"--out-rtstruct {out_rtstruct}: is the input {given}, which it would overwrite")
    check_output(out_rtstruct, inputs, option="--out-rtstruct")  # also a path under a regular file


def _check_phase(phases, phase, zero: str) -> None:
    """--phase K of --phases N; --phase-zero one of its names."""
    check_zero(zero)
    if phase is not None and phases is None:
        raise InputError(f"--phase goes with --phases N (the phases of {BREATH_HINT})")
    if phase is not None:
        check_phase_index(phases, phase)


def _check_rigid(name, rtstruct) -> None:
    """--rigid-structure names a ROI of --rtstruct."""
    if name is not None and rtstruct is None:
        raise InputError("--rigid-structure names a structure of --rtstruct: give --rtstruct and --structure")


def _check_scan(scan, no_rigid: bool, other_schedule, phases) -> None:
    """--scan alone (no other schedule, no --phases); --no-rigid only with it."""
    if scan is not None and (other_schedule or phases is not None):
        raise InputError("--scan names one state: not with --volume-ml, --curve, --preset or --phases")
    if no_rigid and scan is None:
        raise InputError("--no-rigid applies to --scan (the fit's alignment of that scan)")


def _check_schedule(volume_ml, breath: BreathFlags, fps) -> None:
    """One volume schedule at most (``--volume-ml`` or the breath of ``breath``,
    :func:`~lungdeform.cli.common.check_trace_options`), and its options in range."""
    given = [name for name, v in (("--volume-ml", volume_ml or None), ("--curve", breath.curve),
                                  ("--preset", breath.preset)) if v]
    if len(given) > 1:
        raise InputError(f"{' and '.join(given)} are mutually exclusive: give one volume schedule")
    check_trace_options(breath.curve, breath.preset, breath.cycles, breath.tidal_ml)
    if breath.tidal_ml is not None and volume_ml:
        raise InputError("--tidal-ml applies to --preset or the plain cycle")
    if not (np.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise InputError(f"--fps must be > 0 and at most {MAX_FPS}, got {fps}")


def _check_structure_options(points, rtstruct, structure, out_rtstruct, reference_ct, phases, volume_ml) -> None:
    """--points or --rtstruct with --structure; --out-rtstruct with --reference-ct, --rtstruct and
    a few states (--volume-ml or --phases)."""
    if (points is None) == (rtstruct is None):
        raise InputError("give either --points or --rtstruct (with --structure)")
    if (rtstruct is None) != (structure is None):
        raise InputError("--rtstruct and --structure go together")
    if (out_rtstruct is None) != (reference_ct is None):
        raise InputError("--out-rtstruct and --reference-ct go together")
    if out_rtstruct is not None and rtstruct is None:
        raise InputError("--out-rtstruct writes the structure of --rtstruct: give --rtstruct and --structure")
    if out_rtstruct is not None and not volume_ml and phases is None:
        raise InputError("--out-rtstruct needs --volume-ml, --scan or --phases (one ROI per state)")
    if phases is not None and volume_ml:
        raise InputError("--phases applies to --curve, --preset or the plain cycle, not --volume-ml")
    if phases is not None and not 1 <= phases <= MAX_PHASES:
        raise InputError(f"--phases must be 1 to {MAX_PHASES}, got {phases}")


def _read_points(points: Path, skip_invalid: bool):
    """The points of a CSV or elastix file, saying which rows were skipped."""
    skipped: list[int] = []
    pts, labels = T.read_points(points, skip_invalid=skip_invalid, skipped=skipped)
    if skipped:
        shown = ", ".join(map(str, skipped[:10])) + (", …" if len(skipped) > 10 else "")
        typer.echo(f"{points}: skipped {len(skipped)} row(s) without finite x_mm,y_mm,z_mm, at line(s) {shown}")
    return pts, labels


def _print_structure(name: str, placement, summary: dict, origin: str = "end-exhale") -> None:
    """One line for a tracked structure: its points, lungs, how many inside, its largest motion
    (from ``origin``, the scan's state in words)."""
    lungs = ", ".join(sorted(set(placement.lungs.tolist())))
    typer.echo(f"  {name}: {len(placement.lungs)} contour point(s) in the {lungs} lung(s), "
               f"{int(placement.inside.sum())} inside; largest excursion from {origin} "
               f"{max(summary['max_excursion_mm']):.1f} mm")


def _print_points(labels, placement, summary: dict, paths: dict, origin: str = "end-exhale") -> None:
    """One line per point (the first 20): its lung, inside or how far outside, its motion."""
    for j, label in enumerate(labels[:20]):
        where = "inside" if placement.inside[j] else f"outside by {placement.distance_mm[j]:.1f} mm"
        ptp = " ".join(f"{a} {summary['peak_to_peak_mm'][a][j]:.1f}" for a in T.AXES)
        # peak-to-peak alone reads 0 for a single --volume-ml: also the excursion from the scan
        typer.echo(f"  {label}: {placement.lungs[j]} lung ({where}); peak-to-peak mm {ptp}; "
                   f"largest excursion from {origin} {summary['max_excursion_mm'][j]:.1f} mm")
    if len(labels) > 20:
        typer.echo(f"  … {len(labels) - 20} more in {paths['json']}")
