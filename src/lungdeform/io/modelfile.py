"""The model file: a versioned ``.npz`` (numpy zip) holding everything playback needs.

Schema ``lungdeform.model``, version 6 (documented in docs/MODEL_FORMAT.md). Top-level keys:

=================  ==================  =====================================================
key                type                meaning
=================  ==================  =====================================================
schema             str                 ``"lungdeform.model"``
schema_version     int                 6 (1 to 5 are read too)
lungs              (k,) str            lung names (``"left"``, ``"right"``)
provenance         str (JSON)          sources, settings, software version, creation time
scan_state         str                 the scan's breathing state (:mod:`lungdeform.model.scan_state`)
scan_above_ee_ml   float               mL of both lungs the scan lies above end-exhale
=================  ==================  =====================================================

Per lung, under ``lung/<name>/``: ``side`` str; ``vertices (n, 3) float64`` mm LPS (the scan's surface p:
end-exhale unless ``scan_above_ee_ml`` > 0);
``faces (m, 3) int32`` (outward); ``constants (9,)`` c1…c9; ``stiffness (n,)``;
``frame_axes (3, 3)`` (rows: lung X, Y, Z in LPS); ``frame_lower (3,)``, ``frame_upper (3,)``
(end-exhale box, lung-frame mm); ``directions (n, 3)`` unit, LPS; ``force_basis (4, n)``
(elastostatic force for fields 1, x̂, ŷ, ẑ); ``gravity (3,)`` unit LPS; ``force_weights (4,)``;
``displacement (n, 3) float64`` mm per ``unit_ml``; ``unit_ml``; ``calibration_ml``; ``d_min`` mm;
``volume_ee_ml``; ``volume_poly (4,)`` mm³ (volume of p + s·u as a cubic in s). Optional (a fit
with interior landmarks): ``landmarks (m, 3)`` mm LPS, ``landmark_correction (m, 3)`` mm per unit,
``landmark_smoothing`` (mm, or mm² for the thin-plate kinds; :mod:`lungdeform.interior.field`). Optional
(a fit of cropped scans): ``interior_vertices (n,) bool`` (at least 13 set), the vertices whose
motion drives the interior field (the crop faces left out). Optional (an older lung saved again):
``interior_kind`` str, ``"sliding_thin_plate"`` or ``"thin_plate"`` (it keeps the interior field it
was made with; absent: ``"sliding"``). Optional (a fit whose interior follows a surface-to-surface
map, :mod:`lungdeform.interior.surface_map`): ``interior_map_linear (3, 4)`` mm per unit,
``interior_map_warp (3, 4)``, ``interior_map_centers (k, 3)`` mm LPS, ``interior_map_weights (k, 3)``
mm per unit and ``interior_map_width_mm``; all five or none. Optional with them (a lung built with
a population default's interior prior, or fitted with a motion prior): ``interior_map_prior (3, 4)`` mm per unit and
``interior_map_prior_taper_mm``, the prior tapered to zero at the lung's surface
(:class:`lungdeform.interior.prior.TaperedPrior`, over the lung's own ``vertices``); both or none.

Loading checks that the file is a zip archive (not text, an image or a pickle), the schema name and
version, that every key is present, and every shape;
that every array holds values of its kind (real numbers, finite, where numbers belong: no complex,
text or objects; integer faces; one value where one belongs), and that the provenance is a JSON
object whose ``volumes_ml`` are finite numbers and whose alignment matrices are 4 × 4.
Version 6 keeps a built lung's interior prior apart from its surface map, tapered to zero at the
surface; before it the prior was folded into ``interior_map_linear`` and moved the lung's own surface
(a warped lung breathed about 56 % of the model's volume). A version-5 or older lung whose map is the
surface extension of its own displacement (a lung built with a population default) is read with
the folded prior split off and tapered (:func:`lungdeform.model.lung.unfolded_prior`); any other map
(a fit's) is read as made. Version 5 adds the scan's breathing state (``scan_state``, ``scan_above_ee_ml``): the surfaces may be
an end-inhale or mid-ventilation scan, which an older reader would play as end-exhale (breathing
further in from an inhaled scan), so it refuses the file instead; files of versions 1 to 4 are
end-exhale scans. Versions 2 to 4 changed only how interior points move (:attr:`LungModel.interior_kind`). Version 4 adds
the optional surface-to-surface map (an older reader would play such a lung's interior differently,
so it refuses the file instead). Version 3:
the landmark correction is the sliding correction (:func:`lungdeform.interior.sliding.sliding_correction`,
which keeps the surface's normal motion), where version 2 used a thin-plate spline through the same
per-unit residuals (``interior_kind = "sliding_thin_plate"``). Version 2 made the surface part the
sliding interpolation of the surface's normal motion, where version 1 used the thin-plate spline of
the whole displacement (``"thin_plate"``). Older files are read and keep their fields, so their
interior points play back as made.
"""

from __future__ import annotations

import datetime as _dt
import json
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np

from lungdeform import __version__
from lungdeform.atomic import finite_json, write_npz
from lungdeform.errors import InputError, ModelFileError, require_file
from lungdeform.geometry.frame import LungFrame
from lungdeform.geometry.mesh import Surface
from lungdeform.interior.prior import TaperedPrior
from lungdeform.interior.surface_map import SurfaceMapField
from lungdeform.model.lung import LungModel, Model, unfolded_prior
from lungdeform.model.scan_state import ScanState

SCHEMA = "lungdeform.model"
#: Largest displacement (mm) a lung may have at its calibration volume: far beyond any breath.
MAX_TIDAL_DISPLACEMENT_MM = 1000.0
SCHEMA_VERSION = 6
#: Schema versions this lungdeform reads: 1 to 4 differ only in their interior field, 5 adds the scan's
#: breathing state, 6 the tapered interior prior (module docstring).
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6)

_OPTIONAL = ("landmarks", "landmark_correction", "landmark_smoothing")
#: The surface-to-surface map's arrays (:class:`~lungdeform.interior.surface_map.SurfaceMapField`).
_MAP = ("linear", "warp", "centers", "weights", "width_mm")
#: The tapered interior prior on top of the map (:class:`~lungdeform.interior.prior.TaperedPrior`).
_MAP_PRIOR = ("prior", "prior_taper_mm")
_PER_LUNG = ("side", "vertices", "faces", "constants", "stiffness", "frame_axes", "frame_lower",
             "frame_upper", "directions", "force_basis", "gravity", "force_weights",
             "displacement", "unit_ml", "calibration_ml", "d_min", "volume_ee_ml", "volume_poly")
#: The kind of each member's values (numpy dtype kinds): real floating point (finite) unless named here.
_KINDS = {"schema": "U", "schema_version": "iu", "lungs": "U", "provenance": "U", "side": "U", "faces": "iu",
          "interior_vertices": "b", "interior_kind": "U", "scan_state": "U", "scan_above_ee_ml": "f"}
_KIND_NAMES = {"U": "text", "iu": "integer", "b": "bool", "f": "real floating point"}
#: Members that hold one value (shape ``()``).
_SCALARS = ("schema", "schema_version", "provenance", "side", "unit_ml", "calibration_ml", "d_min", "volume_ee_ml",
            "landmark_smoothing", "interior_kind", "interior_map_width_mm", "interior_map_prior_taper_mm",
            "scan_state", "scan_above_ee_ml")


def lung_arrays(lung: LungModel) -> dict[str, np.ndarray]:
    """The per-lung arrays of the schema (also used by exporters)."""
    out = {
        "side": np.array(lung.side),
        "vertices": lung.surface.vertices,
        "faces": lung.surface.faces.astype(np.int32),
        "constants": lung.constants,
        "stiffness": lung.stiffness,
        "frame_axes": lung.frame.axes,
        "frame_lower": lung.frame.lower,
        "frame_upper": lung.frame.upper,
        "directions": lung.directions,
        "force_basis": lung.force_basis,
        "gravity": lung.gravity,
        "force_weights": lung.force_weights,
        "displacement": lung.displacement,
        "unit_ml": np.array(lung.unit_ml),
        "calibration_ml": np.array(lung.calibration_ml),
        "d_min": np.array(lung.d_min),
        "volume_ee_ml": np.array(lung.volume_ee_ml),
        "volume_poly": lung.volume_poly,
    }
    if lung.landmarks is not None and lung.landmark_correction is not None:
        out.update(landmarks=lung.landmarks, landmark_correction=lung.landmark_correction,
                   landmark_smoothing=np.array(lung.landmark_smoothing))
    if lung.interior_vertices is not None:
        out["interior_vertices"] = np.asarray(lung.interior_vertices, bool)
    if lung.interior_kind != "sliding":  # an older lung saved again keeps its interior field
        out["interior_kind"] = np.array(lung.interior_kind)
    if lung.interior_map is not None:
        out.update({f"interior_map_{k}": np.asarray(getattr(lung.interior_map, k)) for k in _MAP})
        prior = lung.interior_map.prior
        if prior is not None:  # its depth is the lung's own: it is read back over these vertices
            if not np.array_equal(prior.vertices, lung.surface.vertices):
                raise InputError(f"lung '{lung.side}': its interior prior tapers over another surface than the lung's")
            out.update(interior_map_prior=prior.affine, interior_map_prior_taper_mm=np.array(prior.width_mm))
    return out


def save_model(path, model: Model) -> Path:
    """Write ``model`` to ``path`` (``.npz`` appended if missing) atomically; return the path."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    arrays: dict[str, np.ndarray] = {
        "schema": np.array(SCHEMA),
        "schema_version": np.array(SCHEMA_VERSION),
        "lungs": np.array(model.names),
        "provenance": np.array(json.dumps(finite_json(model.provenance), default=str, allow_nan=False)),
        "scan_state": np.array(model.scan.name),
        "scan_above_ee_ml": np.array(float(model.scan.above_ee_ml)),
    }
    for name, lung in model.lungs.items():
        for key, value in lung_arrays(lung).items():
            arrays[f"lung/{name}/{key}"] = value
    return write_npz(path, arrays, compress=True)


def load_model(path) -> Model:
    """Read a model file; raise :class:`ModelFileError` naming the file and the problem."""
    path = require_file(path, "model", "give the .npz that build, fit or demo wrote", ModelFileError)
    if path.stat().st_size == 0:
        raise ModelFileError(f"{path}: file is empty")
    _check_container(path)
    try:
        with open(path, "rb") as fh:  # our handle: numpy leaks its own when the zip is unreadable
            z = np.load(fh, allow_pickle=False)
            if not hasattr(z, "files"):  # a lone .npy array: np.load returns it, not an archive
                raise ModelFileError(f"{path}: not a lungdeform model file (one NumPy array, not an .npz archive)")
            data = {k: z[k] for k in z.files}
        raw = [k for k, v in data.items() if not isinstance(v, np.ndarray)]  # a zip member without .npy
        if raw:
            raise ModelFileError(f"{path}: not a lungdeform model file (member {raw[0]!r} is not a NumPy array)")
    except ValueError as exc:  # numpy's advice on pickled objects is not for our users
        why = "it holds Python objects, not arrays" if "pickle" in str(exc) else str(exc)
        raise ModelFileError(f"{path}: not a lungdeform model file ({why})") from exc
    except (OSError, zipfile.BadZipFile, EOFError, zlib.error, RuntimeError, NotImplementedError,
            MemoryError) as exc:  # a damaged archive: bad deflate data, "encrypted", odd zip versions, huge shapes
        raise ModelFileError(f"{path}: not a lungdeform model file (damaged archive: {exc})") from exc
    if "schema" not in data:
        raise ModelFileError(f"{path}: not a lungdeform model file (a NumPy .npz archive without the 'schema' "
                             f"member; it holds {_listed(data)})")
    if str(data["schema"]) != SCHEMA:
        raise ModelFileError(f"{path}: not a lungdeform model file (its 'schema' member is {str(data['schema'])!r}, "
                             f"expected {SCHEMA!r})")
    try:
        version = int(data.get("schema_version", -1))
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"{path}: damaged header (schema_version {data['schema_version'].tolist()!r})") from exc
    if version not in READABLE_VERSIONS:
        raise ModelFileError(
            f"{path}: model schema version {version} is not supported (this lungdeform reads "
            f"{', '.join(map(str, READABLE_VERSIONS))})"
        )
    _check_members(path, data)
    try:
        provenance = json.loads(str(data["provenance"]))
        names = [str(x) for x in data["lungs"]]
    except (KeyError, ValueError) as exc:
        raise ModelFileError(f"{path}: damaged header ({exc})") from exc
    _check_provenance(path, provenance)
    try:
        lungs = {name: _lung(path, name, data, version) for name in names}
    except (TypeError, ValueError, IndexError) as exc:  # arrays of the wrong dtype (text, objects) or size
        raise ModelFileError(f"{path}: damaged lung arrays ({exc})") from exc
    return Model(lungs, provenance, _scan_state(path, data, version))


def _scan_state(path: Path, data: dict, version: int) -> ScanState:
    """The scan's breathing state: both keys in a version-5 file, end-exhale in older ones."""
    present = [k for k in ("scan_state", "scan_above_ee_ml") if k in data]
    if version < 5 and not present:
        return ScanState()
    if len(present) != 2:
        raise ModelFileError(f"{path}: schema {version} needs both scan_state and scan_above_ee_ml, "
                             f"found {', '.join(present) or 'neither'}")
    try:
        return ScanState(str(data["scan_state"]), float(data["scan_above_ee_ml"]))
    except InputError as exc:
        raise ModelFileError(f"{path}: {exc}") from exc


#: The first bytes of a zip archive (an ``.npz``; an empty zip starts with the end record) and of an ``.npy``.
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
_NPY_MAGIC = b"\x93NUMPY"


def _check_container(path: Path) -> None:
    """ModelFileError when ``path`` does not start as a zip archive (an ``.npz``) or a lone ``.npy``
    array: a text file, an image or a pickle is named as not an archive, before numpy reads it."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(6)
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the model file ({exc})") from exc
    if head.startswith(_ZIP_MAGIC) or head.startswith(_NPY_MAGIC):
        return
    if head[:1] == b"\x80":  # a pickle's protocol byte: np.load would unpickle it, and refuses
        raise ModelFileError(f"{path}: not a lungdeform model file (a Python pickle, not a NumPy .npz archive)")
    raise ModelFileError(f"{path}: not a lungdeform model file (not a NumPy .npz archive: not a zip file)")


def _listed(data: dict) -> str:
    """The members of an archive, for a message: the first few names and how many."""
    if not data:
        return "no members"
    names = sorted(data)
    return ", ".join(repr(n) for n in names[:4]) + (f", … ({len(names)} members)" if len(names) > 4 else "")


def _check_members(path: Path, data: dict) -> None:
    """ModelFileError naming the member when a known member's values are of the wrong kind (complex,
    text or objects where real numbers belong: :data:`_KINDS`), are not one value where one belongs
    (:data:`_SCALARS`), or are real numbers that are not finite."""
    for member, value in data.items():
        key = member.rsplit("/", 1)[-1] if member.startswith("lung/") else member
        if key not in _KINDS and key not in _PER_LUNG + _OPTIONAL and not key.startswith("interior_map_"):
            continue  # not of the schema: ignored
        kind = _KINDS.get(key, "f")
        if value.dtype.kind not in kind:
            raise ModelFileError(f"{path}: member {member!r} holds {value.dtype} values, expected "
                                 f"{_KIND_NAMES[kind]}")
        if key in _SCALARS and value.shape != ():
            raise ModelFileError(f"{path}: member {member!r} has shape {value.shape}, expected one value (shape ())")
        if kind == "f" and not np.isfinite(value).all():
            raise ModelFileError(f"{path}: member {member!r} holds NaN or infinity")


def _check_provenance(path: Path, prov) -> None:
    """ModelFileError naming the entry when the provenance is not a JSON object, or the entries that
    playback reads (``volumes_ml``; ``alignment[i].applied/apex.matrix``, 4 × 4) are malformed."""
    if not isinstance(prov, dict):
        raise ModelFileError(f"{path}: member 'provenance' is not a JSON object")

    def number(x) -> bool:
        return isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x)

    vols = prov.get("volumes_ml")
    if vols is not None and not (isinstance(vols, list) and all(number(v) for v in vols)):
        raise ModelFileError(f"{path}: member 'provenance' entry volumes_ml is not a list of finite numbers")
    alignment = prov.get("alignment")
    if alignment is None:
        return
    if not (isinstance(alignment, list) and all(isinstance(a, dict) for a in alignment)):
        raise ModelFileError(f"{path}: member 'provenance' entry alignment is not a list of objects")
    for i, entry in enumerate(alignment):
        for part in ("applied", "apex"):
            matrix = (entry.get(part) or {}).get("matrix") if isinstance(entry.get(part) or {}, dict) else "?"
            if matrix is None:
                continue
            ok = (isinstance(matrix, list) and len(matrix) == 4
                  and all(isinstance(r, list) and len(r) == 4 and all(number(x) for x in r) for r in matrix))
            if not ok:
                raise ModelFileError(f"{path}: member 'provenance' entry alignment[{i}].{part}.matrix is not a "
                                     "4 x 4 matrix of finite numbers")


def _lung(path: Path, name: str, data: dict, version: int = SCHEMA_VERSION) -> LungModel:
    prefix = f"lung/{name}/"
    missing = [k for k in _PER_LUNG if prefix + k not in data]
    if missing:
        raise ModelFileError(f"{path}: lung '{name}' lacks {', '.join(missing)}")
    a = {k: data[prefix + k] for k in _PER_LUNG}
    v = a["vertices"]
    if v.ndim != 2 or v.shape[1] != 3:
        raise ModelFileError(f"{path}: lung '{name}' vertices have shape {v.shape}, expected (n, 3)")
    n = len(v)
    expected = {"faces": (None, 3), "constants": (9,), "stiffness": (n,), "frame_axes": (3, 3),
                "frame_lower": (3,), "frame_upper": (3,), "directions": (n, 3),
                "force_basis": (4, n), "gravity": (3,), "force_weights": (4,),
                "displacement": (n, 3), "volume_poly": (4,)}
    for key, shape in expected.items():
        got = a[key].shape
        if len(got) != len(shape) or any(s is not None and s != g for s, g in zip(shape, got)):
            raise ModelFileError(
                f"{path}: lung '{name}' {key} has shape {got}, expected {tuple(s or 'm' for s in shape)}"
            )
    if int(a["faces"].max(initial=-1)) >= n:
        raise ModelFileError(f"{path}: lung '{name}' faces index beyond its {n} vertices")
    opt = {k: data[prefix + k] for k in _OPTIONAL if prefix + k in data}
    if opt and len(opt) != len(_OPTIONAL):
        raise ModelFileError(f"{path}: lung '{name}' has only part of the landmark correction "
                             f"({', '.join(sorted(opt))}; expected {', '.join(_OPTIONAL)})")
    if opt:
        lm, cor = opt["landmarks"], opt["landmark_correction"]
        if lm.ndim != 2 or lm.shape[1:] != (3,) or cor.shape != lm.shape or len(lm) < 5:
            raise ModelFileError(f"{path}: lung '{name}' landmarks {lm.shape} and landmark_correction "
                                 f"{cor.shape} must both be (m, 3) with m >= 5")
        sm = float(opt["landmark_smoothing"])
        if not (np.all(np.isfinite(lm)) and np.all(np.isfinite(cor)) and np.isfinite(sm) and sm >= 0):
            raise ModelFileError(f"{path}: lung '{name}' landmark correction holds NaN, infinity or a negative smoothing")
    if str(a["side"]) not in ("left", "right"):
        raise ModelFileError(f"{path}: lung '{name}' side is {str(a['side'])!r}, expected 'left' or 'right'")
    for key in ("unit_ml", "calibration_ml", "d_min"):  # volumes and distances the playback divides by
        if not float(a[key]) > 0:
            raise ModelFileError(f"{path}: lung '{name}' {key} is {float(a[key])!r}, expected a positive number")
    peak = float(np.abs(a["displacement"]).max(initial=0.0)) * (float(a["calibration_ml"]) / float(a["unit_ml"]))
    if not peak <= MAX_TIDAL_DISPLACEMENT_MM:
        raise ModelFileError(f"{path}: lung '{name}' displacement reaches {peak:.3g} mm at its calibration volume "
                             f"(+{float(a['calibration_ml']):g} mL), more than {MAX_TIDAL_DISPLACEMENT_MM:g} mm: "
                             "not a breathing lung")
    surface = Surface(v, a["faces"].astype(np.int64), name)
    frame = LungFrame(str(a["side"]), a["frame_axes"], a["frame_lower"], a["frame_upper"])
    kind = "thin_plate" if version == 1 else str(data.get(prefix + "interior_kind", "sliding"))
    if version == 2 and kind == "sliding" and opt:  # a schema-2 correction is a thin-plate spline
        kind = "sliding_thin_plate"
    try:  # LungModel checks interior_vertices and interior_kind; the error names the file
        return LungModel(
            side=str(a["side"]), surface=surface, constants=a["constants"], stiffness=a["stiffness"],
            frame=frame, directions=a["directions"], force_basis=a["force_basis"],
            gravity=a["gravity"], displacement=a["displacement"], unit_ml=float(a["unit_ml"]),
            calibration_ml=float(a["calibration_ml"]), d_min=float(a["d_min"]),
            landmarks=opt.get("landmarks"), landmark_correction=opt.get("landmark_correction"),
            landmark_smoothing=float(opt.get("landmark_smoothing", 0.0)),
            interior_vertices=data.get(prefix + "interior_vertices"), interior_kind=kind,
            interior_map=_interior_map(data, prefix, surface, a["displacement"], version),
        )
    except InputError as exc:
        raise ModelFileError(f"{path}: lung '{name}' {exc}") from exc


def _interior_map(data: dict, prefix: str, surface: Surface, displacement, version: int) -> SurfaceMapField | None:
    """The lung's surface-to-surface map with its tapered prior, or None; InputError (named by the
    caller) when partial or malformed. A map of a version-5 or older file had a built lung's prior
    folded in: split off and tapered (:func:`lungdeform.model.lung.unfolded_prior`)."""
    keys = [prefix + "interior_map_" + k for k in _MAP]
    present = [k for k in keys if k in data]
    extra = [k for k in (prefix + "interior_map_" + k for k in _MAP_PRIOR) if k in data]
    if not present and not extra:
        return None
    if len(present) != len(keys) or len(extra) not in (0, len(_MAP_PRIOR)):
        raise InputError(f"has only part of the interior map ({', '.join(k[len(prefix):] for k in present + extra)})")
    linear, warp, centers, weights, width = (np.asarray(data[k]) for k in keys)
    field = SurfaceMapField(linear, warp, centers, weights, float(width))
    if extra:
        affine, taper_mm = (np.asarray(data[k]) for k in extra)
        return field.with_prior(TaperedPrior(affine, surface.vertices, surface.faces, float(taper_mm)))
    return unfolded_prior(field, surface, displacement) if version < 6 else field


def provenance(command: str, **extra) -> dict:
    """What a model file records about its making: software version, command, argv, time (UTC)."""

    return {
        "software": f"lungdeform {__version__}",
        "command": command,
        "argv": sys.argv[1:],
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        **extra,
    }
