"""Trajectories of interior points (a tumour, fiducials) of a lung model over a breathing schedule.

``lungdeform track`` behind it: points (mm, LPS of the end-exhale scan) are assigned to a lung
(:func:`place_points`), moved by that lung's interior field (:mod:`lungdeform.interior.field`) at the
same exact per-lung scales as surface playback (:func:`lung_scales`, as ``lungdeform export``) over
frames of absolute volumes or of a volume trace (:func:`volume_frames`, :func:`trace_frames`), and
written as a CSV of positions, a JSON summary of each point's motion and a plot
(:func:`write_trajectories`).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_bytes
from lungdeform.errors import InputError, ReadError, require_file
from lungdeform.geometry.distance import point_to_surface
from lungdeform.geometry.mesh import as_vertices, winding_numbers
from lungdeform.interior.field import KIND_TEXT
from lungdeform.io.landmarks import read_elastix_points
from lungdeform.model.displacement import positions_at, scales_for_volumes
from lungdeform.plot.figure import save_png
from lungdeform.plot.motion import motion

from .schedule import lung_shares

#: Points farther than this outside every lung are refused (a wrong frame or unit, not a tumour).
OUTSIDE_LIMIT_MM = 30.0


@dataclass(frozen=True, eq=False)
class PointPlacement:
    """Which lung each point belongs to.

    lungs : (q,) str — the lung's name in the model; inside : (q,) bool — inside that lung's
    end-exhale surface; distance_mm : (q,) float — distance to that surface, mm.
    """

    lungs: np.ndarray
    inside: np.ndarray
    distance_mm: np.ndarray


def place_points(model, points, lung: str | None = None, *, limit_mm: float = OUTSIDE_LIMIT_MM,
                 source: str = "points") -> PointPlacement:
    """Assign ``points : (q, 3)`` mm LPS (end-exhale) to the lungs of ``model``: the lung that
    contains the point, else the nearest; ``lung`` forces one. Points more than ``limit_mm`` outside
    their lung raise :class:`InputError` naming ``source`` and the points (1-based)."""

    q = as_vertices(points, "points")
    if len(q) == 0 or not np.all(np.isfinite(q)):
        raise InputError(f"{source}: need at least one point, all finite (mm, LPS)")
    names = list(model.lungs) if lung is None else [lung]
    if lung is not None and lung not in model.lungs:
        raise InputError(f"lung {lung!r} is not in the model (it has {', '.join(model.lungs)})")
    wind = np.stack([winding_numbers(q, model.lungs[n].surface.vertices, model.lungs[n].surface.faces) for n in names])
    dist = np.stack([point_to_surface(q, model.lungs[n].surface.vertices, model.lungs[n].surface.faces) for n in names])
    inside = wind > 0.5
    # containing lung first (if several, the deeper one), else the nearest surface
    key = np.where(inside, -dist, dist + 1e9)
    pick = np.argmin(key, axis=0)
    cols = np.arange(len(q))
    d, ins = dist[pick, cols], inside[pick, cols]
    far = np.flatnonzero(~ins & (d > limit_mm))
    if len(far):
        listed = ", ".join(f"{i + 1} ({d[i]:.0f} mm)" for i in far[:8]) + (" …" if len(far) > 8 else "")
        raise InputError(f"{source}: {len(far)} point(s) lie more than {limit_mm:g} mm outside "
                         f"{'lung ' + lung if lung else 'every lung'} of the model: {listed}. Points are mm "
                         f"in the model's frame (LPS world of the end-exhale scan)")
    return PointPlacement(np.array([names[i] for i in pick]), ins, d)


def lung_scales(model, delta_ml) -> dict[str, np.ndarray]:
    """Per lung, ``s : (f,) float`` units at which its volume is exactly ``V_EE + share·ΔV``, for
    ``delta_ml : (f,)`` mL of both lungs above end-exhale (the lung moves from its scan, which lies
    ``share · model.scan.above_ee_ml`` above its end-exhale ``V_EE``: :mod:`lungdeform.model.scan_state`)
    (:func:`lungdeform.model.displacement.scales_for_volumes` of each lung's share): the playback of
    ``lungdeform export`` (whose tidal weights :func:`lungdeform.playback.export.tidal_weights` are
    these over the calibration's units) and of ``lungdeform demo``."""

    dv = np.asarray(delta_ml, float).ravel() - model.scan.above_ee_ml  # from the scan the lungs are
    if not np.all(np.isfinite(dv)):
        raise InputError("volumes must be finite mL")
    shares = lung_shares(model)
    return {name: scales_for_volumes(lung.volume_poly, shares[name] * dv) for name, lung in model.lungs.items()}


def unit_displacements(model, points, placement: PointPlacement) -> np.ndarray:
    """``v : (q, 3) float`` mm per unit: each point's displacement by its own lung's interior field
    (:attr:`LungModel.interior`)."""
    q = as_vertices(points, "points")
    out = np.empty_like(q)
    for name, lung in model.lungs.items():
        idx = np.flatnonzero(placement.lungs == name)
        if len(idx):
            out[idx] = lung.interior.displacement(q[idx])
    return out


def point_trajectories(model, points, placement: PointPlacement, delta_ml) -> np.ndarray:
    """Positions ``(f, q, 3) float`` mm LPS of ``points : (q, 3)`` at ``delta_ml : (f,)`` mL of both
    lungs above end-exhale, each moved by its lung's interior field at its lung's scale."""
    q = as_vertices(points, "points")
    scales = lung_scales(model, delta_ml)
    v = unit_displacements(model, q, placement)
    s = np.stack([scales[str(name)] for name in placement.lungs], axis=1)  # (f, q) units
    return positions_at(q[None], v[None], s)


@dataclass(frozen=True, eq=False)
class FrameSchedule:
    """The frames points are tracked over.

    delta_ml : (f,) float — mL of both lungs above end-exhale; t_s : (f,) float — s, or None for
    volumes without times; source : the schedule in words (for the output's ``schedule``).
    """

    delta_ml: np.ndarray
    t_s: np.ndarray | None
    source: str


def scan_ml(model) -> float:
    """Volume of the model's lungs together at its scan (their rest surfaces), mL."""
    return sum(lung.volume_ee_ml for lung in model.lungs.values())


def end_exhale_ml(model) -> float:
    """Volume of the model's lungs together at end-exhale, mL: the scan's less each lung's share of
    the scan's height above end-exhale (:mod:`lungdeform.model.scan_state`)."""
    shares = lung_shares(model)
    return sum(lung.volume_ee_ml - shares[k] * model.scan.above_ee_ml for k, lung in model.lungs.items())


def above_end_exhale(model, volume_ml: float) -> float:
    """ΔV (mL of both lungs above end-exhale) of an absolute volume ``volume_ml`` of the model's lungs
    together: its difference from the scan's volume plus the scan's height above end-exhale."""
    return float(volume_ml) - scan_ml(model) + model.scan.above_ee_ml


def volumes_in_words(model) -> str:
    """The model's end-exhale volume, and where the scan lies when it is not end-exhale, in words:
    ``end-exhale 5336 mL`` or ``end-exhale 4836 mL; the scan 5336 mL, end-inhale (500 mL above end-exhale)``."""
    text = f"end-exhale {end_exhale_ml(model):.0f} mL"
    if model.scan.is_end_exhale:
        return text
    return f"{text}; the scan {scan_ml(model):.0f} mL, {model.scan.describe()}"


def volume_frames(model, volumes_ml) -> FrameSchedule:
    """One frame per absolute volume ``volumes_ml`` (mL, both lungs together; no times)."""
    if not all(np.isfinite(v) and v > 0 for v in volumes_ml):
        raise InputError(f"volumes_ml must be > 0 mL, got {volumes_ml}")
    delta = np.array([above_end_exhale(model, v) for v in volumes_ml])
    source = f"volumes {', '.join(f'{v:g}' for v in volumes_ml)} mL ({volumes_in_words(model)})"
    return FrameSchedule(delta, None, source)


def trace_frames(trace, fps: float) -> FrameSchedule:
    """Frames at ``fps`` per second over a volume trace (:class:`lungdeform.playback.schedule.VolumeTrace`,
    mL above end-exhale), first to last sample inclusive, its volume interpolated linearly."""
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be > 0, got {fps}")
    n = max(int(round((trace.t_s[-1] - trace.t_s[0]) * fps)), 1) + 1
    t_s = np.linspace(trace.t_s[0], trace.t_s[-1], n)
    return FrameSchedule(trace.sample(t_s), t_s, trace.source)


def extrapolation_note(model, delta_ml) -> str | None:
    """A note when ``delta_ml : (f,)`` mL leaves the model's range (below end-exhale by more than
    1 mL, or above 1.5 × the volume change it was fitted for): the motion there is extrapolated."""
    # the both-lung volume change the model was made for (each lung at its calibration_ml)
    shares = lung_shares(model)
    fitted = max(lung.calibration_ml / shares[k] for k, lung in model.lungs.items())
    dv = np.asarray(delta_ml, float)
    if dv.min() < -1.0 or dv.max() > 1.5 * fitted:
        return (f"volumes from {dv.min():+.0f} to {dv.max():+.0f} mL about end-exhale, outside the model's "
                f"range (0 to {fitted:.0f} mL): the motion there is extrapolated along the same field")
    return None


def interior_meta(model) -> dict:
    """Per lung, whether its interior field carries the fit's landmark correction and the field in
    words (:data:`lungdeform.interior.field.KIND_TEXT`): ``landmark_correction``, ``interior_field``."""
    corrected = {name: bool(lung.interior.corrected) for name, lung in model.lungs.items()}
    return {"landmark_correction": corrected,
            "interior_field": {name: KIND_TEXT[lung.interior_kind][0]
                               + (f" plus {KIND_TEXT[lung.interior_kind][1]}" if corrected[name] else "")
                               for name, lung in model.lungs.items()}}


#: LPS axes as a clinician names them (x: right→left, y: anterior→posterior, z: inferior→superior).
AXES = ("LR", "AP", "SI")


def motion_summary(positions: np.ndarray, points) -> dict:
    """Per point of ``positions : (f, q, 3)`` mm: peak-to-peak range along LR, AP, SI and the
    largest 3-D excursion from its end-exhale position ``points : (q, 3)`` mm."""
    p = np.asarray(positions, float)
    ptp = np.ptp(p, axis=0)  # (q, 3)
    excursion = np.linalg.norm(p - np.asarray(points, float)[None], axis=2).max(axis=0)
    return {"peak_to_peak_mm": {a: ptp[:, k].tolist() for k, a in enumerate(AXES)},
            "max_excursion_mm": excursion.tolist()}


def write_trajectories(out: Path, points, labels, placement: PointPlacement, positions, frames: FrameSchedule,
                       *, meta: dict | None = None, end_exhale=None) -> dict[str, Path]:
    """Write ``trajectories.csv`` (one row per frame and point: ``t_s`` (blank without times),
    ``delta_ml``, point, label, lung, ``x_mm, y_mm, z_mm`` and the displacement ``dx_mm, dy_mm,
    dz_mm``, LPS), ``points.json`` (placement and :func:`motion_summary` per point, plus ``meta``)
    and ``motion.png`` (displacement along LR, AP, SI against time or volume) into ``out``, each
    atomically. ``positions : (f, q, 3)`` mm at the ``frames`` (:class:`FrameSchedule`: ``delta_ml``
    mL of both lungs above end-exhale, ``t_s`` s or None);
    ``points`` are the positions at the model's scan (``scan_mm``), ``end_exhale : (q, 3)`` mm at
    end-exhale (``end_exhale_mm``; default ``points``: an end-exhale scan)."""
    q = as_vertices(points, "points")
    ee = q if end_exhale is None else np.asarray(end_exhale, float)
    t_s = frames.t_s
    pos = np.asarray(positions, float)
    dv = np.asarray(frames.delta_ml, float)
    disp = pos - q[None]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["t_s", "delta_ml", "point", "label", "lung", "x_mm", "y_mm", "z_mm", "dx_mm", "dy_mm", "dz_mm"])
    for f in range(len(pos)):
        t = "" if t_s is None else f"{float(t_s[f]):.6g}"
        for j in range(len(q)):
            w.writerow([t, f"{dv[f]:.6g}", j + 1, labels[j], placement.lungs[j],
                        *(f"{x:.4f}" for x in pos[f, j]), *(f"{x:.4f}" for x in disp[f, j])])
    paths = {"csv": write_bytes(Path(out) / "trajectories.csv", buf.getvalue().encode())}
    summary = motion_summary(pos, q)
    info = {"frame": "LPS mm, the scan the model was built from", "frames": int(len(pos)),
            "points": [{"point": j + 1, "label": labels[j], "lung": str(placement.lungs[j]),
                        "inside": bool(placement.inside[j]), "distance_to_surface_mm": float(placement.distance_mm[j]),
                        "scan_mm": q[j].tolist(), "end_exhale_mm": ee[j].tolist(),
                        "peak_to_peak_mm": {a: summary["peak_to_peak_mm"][a][j] for a in AXES},
                        "max_excursion_mm": summary["max_excursion_mm"][j]} for j in range(len(q))],
            **(meta or {})}
    paths["json"] = write_bytes(Path(out) / "points.json", json.dumps(info, indent=2).encode())
    x, xlabel = (dv, "volume above end-exhale (mL)") if t_s is None else (np.asarray(t_s, float), "time (s)")
    paths["png"] = save_png(motion(disp, x, xlabel, labels, sort_x=t_s is None), Path(out) / "motion.png")
    return paths


def read_points(path, *, skip_invalid: bool = False, skipped: list[int] | None = None) -> tuple[np.ndarray, list[str]]:
    """Points to track: a CSV with ``x_mm,y_mm,z_mm[,label]`` (LPS mm) or an elastix point set
    (``point`` header, world mm). Returns ``(points (q, 3) float mm, labels)``. ``skip_invalid`` and
    ``skipped`` apply to a CSV as in :func:`read_markers_csv`."""

    path = require_file(path, "points", "give a CSV x_mm,y_mm,z_mm[,label] or an elastix 'point' file")
    try:
        first = next((line.strip().lower() for line in path.read_text(encoding="utf-8-sig").splitlines() if line.strip()), "")
    except (OSError, UnicodeDecodeError) as exc:
        raise ReadError(f"{path}: cannot read points ({exc})") from exc
    if not first:
        raise ReadError(f"{path}: the points file is empty (expected a CSV with header x_mm,y_mm,z_mm[,label] "
                        "or an elastix 'point' file)")
    if first == "index":
        raise ReadError(f"{path}: an elastix 'index' point file holds voxel indices of an image; give the points "
                        f"in world mm ('point' file or a CSV x_mm,y_mm,z_mm)")
    if first == "point":
        pts = read_elastix_points(path)
        return pts, [f"point {i + 1}" for i in range(len(pts))]
    return read_markers_csv(path, skip_invalid=skip_invalid, skipped=skipped, noun="point")


def read_markers_csv(path, *, skip_invalid: bool = False, skipped: list[int] | None = None,
                     noun: str = "marker") -> tuple[np.ndarray, list[str]]:
    """Markers CSV: header ``x_mm,y_mm,z_mm[,label]`` (LPS mm, end-exhale).

    A row whose coordinates are not finite numbers (NaN, inf, text, missing) is refused with
    :class:`ReadError` naming its 1-based line in the file (the first few, and how many), unless
    ``skip_invalid``: then the valid rows are kept and the lines left out are appended to
    ``skipped`` (when given) for the caller to report. ``noun`` (``"marker"`` or ``"point"``) names the
    rows in messages and in the default labels (``marker 1``, …). Returns ``(points (q, 3) float mm, labels)``.
    """
    path = Path(path)
    if path.is_dir():
        raise ReadError(f"{path}: is a folder, not a {noun}s file (give a CSV x_mm,y_mm,z_mm[,label])")
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: a spreadsheet's byte-order mark
            reader = csv.reader(fh)
            rows = [(reader.line_num, r) for r in reader if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ReadError(f"{path}: cannot read {noun}s ({exc})") from exc
    if not rows:
        raise ReadError(f"{path}: the {noun}s file is empty (expected a CSV with header x_mm,y_mm,z_mm[,label])")
    header = [h.strip() for h in rows[0][1]]
    if not {"x_mm", "y_mm", "z_mm"} <= set(header):
        raise ReadError(f"{path}: {noun}s need a header with x_mm,y_mm,z_mm[,label]")
    cols = [header.index(c) for c in ("x_mm", "y_mm", "z_mm")]
    il = header.index("label") if "label" in header else None
    pts, labels, bad = [], [], []
    for k, (lineno, r) in enumerate(rows[1:], start=1):
        xyz = _finite_row(r, cols)
        if xyz is None:
            bad.append(lineno)
            continue
        pts.append(xyz)
        labels.append(r[il].strip() if il is not None and il < len(r) else f"{noun} {k}")
    if bad and not skip_invalid:
        shown = ", ".join(map(str, bad[:5])) + (", …" if len(bad) > 5 else "")
        raise ReadError(f"{path}: {len(bad)} row(s) without finite numbers in x_mm,y_mm,z_mm, at line(s) "
                        f"{shown} (skip_invalid, track --skip-invalid, keeps the other rows)")
    if not pts:
        raise ReadError(f"{path}: no {noun} rows with finite x_mm,y_mm,z_mm")
    if skipped is not None:
        skipped.extend(bad)
    return np.array(pts), labels


def _finite_row(row: list[str], cols: list[int]) -> list[float] | None:
    """The three coordinates of a CSV row, or None when one is missing, not a number or not finite."""
    try:
        xyz = [float(row[i]) for i in cols]
    except (IndexError, ValueError):
        return None
    return xyz if all(np.isfinite(xyz)) else None
