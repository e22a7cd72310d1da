"""Hostile-input probe of the ``lungdeform`` commands on the radiotherapy path.

Builds small synthetic inputs in a temporary folder (seeded: a two-lung model, a CT series with a
GTV RTSTRUCT, a 4-D CT phantom, images, traces, a fake DIR-Lab COPDgene folder), damages them one
way each (or several at once), runs ``python -m lungdeform …`` on every case as a subprocess (a
compiled copy of this checkout's ``src/lungdeform`` first on ``PYTHONPATH``) with a per-case time-out
and a memory cap, sends SIGTERM or SIGINT mid-run in the signal cases (``warp --phases``,
``validate copd``), and classifies what happened:

``clean``      refused with a documented exit code (2, 3, 130) and one stderr line naming a file or
               an option (or a click usage error naming the option), nothing left behind; or exit 0
               on an input that is odd but valid (with a ``warning``/``note`` line on stderr where
               the case says something had to be fixed); after SIGTERM/SIGINT: nothing half-written
``silent``     exit 0 on a case known to be wrong (``expect="refuse"``, or ``expect="warn"`` without a
               warning line on stderr, or a per-case check of the output failed, or an input was
               overwritten)
``partial``    an output (file, folder, hidden temporary) left after a failure or a signal, or an
               input changed by a failed run
``traceback``  "Traceback" on stderr, or an undocumented exit code (1, killed by a signal, …)
``hang``       the case ran past ``--timeout`` (killed)
``unclear``    refused cleanly but the stderr is not one line naming a file or an option
``refused``    a valid input (``expect="ok"``) refused
``probe-error``  the probe could not build the case (a bug of the probe, never of lungdeform)

Each case declares ``expect``: ``refuse`` (must exit non-zero), ``warn`` (refuse, or exit 0 with a
warning on stderr), ``ok`` (must exit 0) or ``any`` (a clean refusal or exit 0).

Run, from the repository root::

    .venv/bin/python scripts/hostile_probe.py --workers 2 --json probe.json
    .venv/bin/python scripts/hostile_probe.py --only track_ct --only warp_phases_sig --keep

The default set (about 150 cases; :data:`EXTRA` holds about 80 further values of the same classes,
run with ``--all``) took 18 minutes with ``--workers 2`` on two cores shared at a load average of
about 10, most of it the start-up (imports) of each run; ``--only`` picks a few cases. It prints one
line per case as it ends, then the counts per command and outcome and every case that is not
``clean`` (for a traceback its last line). The outcomes ``hang`` and, for the fit cases, ``silent``
against ``hang`` depend on the cores' load: on busy cores raise ``--timeout``.

Options: ``--json FILE`` (per case: name, command, argv, expect, outcome, rc, stderr_first_line,
seconds, reason, why), ``--all``, ``--only SUBSTR`` (cases whose name holds it; repeatable), ``--workers N``,
``--timeout S`` (per case), ``--memory-gib G`` (address-space cap of each run), ``--seed N``,
``--keep`` (keep the temporary folder and print it: each case's inputs and outputs under
``cases/NAME``, its stdout and stderr under ``logs/``), ``--list`` (print the case names and exit).
Nothing outside the temporary folder is written (the runs get ``TMPDIR``, ``MPLCONFIGDIR`` and
``XDG_CACHE_HOME`` inside it, and no bytecode). The exit code is 0 when every case is ``clean``,
else 1.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import resource
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

sys.dont_write_bytecode = True  # the probe writes nothing into the checkout (no __pycache__)
if str(Path(__file__).resolve().parents[1] / "src") not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
OUTCOMES = ("clean", "silent", "partial", "traceback", "hang", "unclear", "refused")
#: exit codes the CLI documents for a refusal (lungdeform.cli.main): bad input, target not met, interrupted
REFUSAL_CODES = (2, 3, 130)
GTV_CENTRE = np.array([90.0, 0.0, -40.0])  # inside the left lung of the probe's model
CT_SOP = "1.2.840.10008.5.1.4.1.1.2"


# --- inputs ----------------------------------------------------------------------------------------

def _uid(fx, *parts) -> str:
    return ".".join(["1.2.826.0.1.3680043.8.498", str(900 + fx.seed), *map(str, parts)])


def _raw(ds, tag: int, vr: str, text: str) -> None:
    """Set element ``tag`` to ``text`` as raw bytes (values pydicom would refuse: 5-value IOP, text in DS)."""
    from pydicom.dataelem import RawDataElement
    from pydicom.tag import Tag

    b = text.encode("latin-1")
    if len(b) % 2:
        b += b" "
    ds._dict[Tag(tag)] = RawDataElement(Tag(tag), vr, len(b), b, 0, False, True)


def ct_dataset(pixels, spacing, position, uids: dict, k: int, iop=(1, 0, 0, 0, 1, 0)):
    """One axial CT slice (pydicom FileDataset, explicit VR little endian), int16 HU."""
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    meta = FileMetaDataset()
    sop = f"{uids['series']}.{k + 1}"
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = CT_SOP, sop
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset("", {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = CT_SOP, sop, "CT"
    ds.PatientName, ds.PatientID = uids.get("patient_name", "Probe^Phantom"), uids.get("patient", "PROBE01")
    ds.StudyInstanceUID, ds.SeriesInstanceUID = uids["study"], uids["series"]
    ds.FrameOfReferenceUID = uids["frame"]
    ds.SeriesDescription = uids.get("description", "probe CT")
    ds.InstanceNumber = k + 1
    ds.ImagePositionPatient = [f"{x:.4f}" for x in position]
    ds.ImageOrientationPatient = [f"{x:.6f}" for x in iop]
    ds.PixelSpacing = [f"{spacing[1]:g}", f"{spacing[0]:g}"]
    ds.SliceThickness = f"{spacing[2]:g}"
    ds.Rows, ds.Columns = pixels.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.RescaleIntercept, ds.RescaleSlope = "0", "1"
    ds.PixelData = np.ascontiguousarray(pixels, "<i2").tobytes()
    return ds


def write_ct(folder: Path, volume, spacing, origin, uids: dict, name: str = "ct", **hooks) -> Path:
    """``volume`` (z, y, x) as one DICOM file per slice. ``hooks``: ``z`` the slice positions (default
    regular), ``iop`` the orientation, ``shift(k)`` an extra (3,) offset of slice k's position,
    ``edit(ds, k)`` a last change per slice."""
    folder.mkdir(parents=True, exist_ok=True)
    nz = len(volume)
    z, shift, edit = hooks.get("z"), hooks.get("shift"), hooks.get("edit")
    zs = [origin[2] + k * spacing[2] for k in range(nz)] if z is None else list(z)
    for k in range(nz):
        pos = np.array([origin[0], origin[1], zs[k]]) + (0 if shift is None else shift(k))
        ds = ct_dataset(volume[k], spacing, pos, uids, k, hooks.get("iop") or (1, 0, 0, 0, 1, 0))
        if edit is not None:
            edit(ds, k)
        ds.save_as(folder / f"{name}{k:04d}.dcm", enforce_file_format=False)
    return folder


def phase_ct(shape, spacing, scale: float, rng):
    """(z, y, x) int16 HU: a body (40 HU) in air holding two lungs (-850 HU), ellipsoids of semi-axes
    (28, 34, 44) mm * ``scale`` at x = ±40 mm (after tests/fourdct_phantom.py)."""
    nz, ny, nx = shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    p = np.stack([(i - (nx - 1) / 2) * spacing[0], (j - (ny - 1) / 2) * spacing[1],
                  (k - (nz - 1) / 2) * spacing[2]], -1)
    ct = np.full(shape, -1000.0)
    ct[(p[..., 0] / 90) ** 2 + (p[..., 1] / 80) ** 2 <= 1] = 40.0
    for sgn in (1.0, -1.0):
        ct[((((p - [sgn * 40.0, 0.0, 0.0]) / (np.array([28.0, 34.0, 44.0]) * scale)) ** 2).sum(-1)) <= 1] = -850.0
    return (ct + rng.normal(0, 5, ct.shape)).astype(np.int16)


FOURD_SHAPE, FOURD_SPACING = (24, 48, 48), (4.0, 4.0, 6.0)


def write_4dct(fx, folder: Path, phases: int = 4, **hooks) -> Path:
    """A 4-D CT: phase p a series in ``folder/phaseP`` (SeriesDescription ``Gated 10p%``), lungs
    inflated by 1 + 0.06 p per axis. Each hook ``NAME_of(p)`` may change phase p: ``uids_of`` its UIDs
    (a dict merged in), ``z_of`` its slice positions, ``iop_of`` its orientation, ``shift_of`` and
    ``edit_of`` the per-slice hooks of :func:`write_ct`, ``drop_of`` slices left out (indices),
    ``description_of`` its SeriesDescription."""
    nz, ny, nx = FOURD_SHAPE
    sx, sy, sz = FOURD_SPACING
    origin = (-(nx - 1) / 2 * sx, -(ny - 1) / 2 * sy, -(nz - 1) / 2 * sz)
    rng = np.random.default_rng(fx.seed)
    hook = {k: hooks.get(f"{k}_of") or (lambda _p: None) for k in ("uids", "z", "iop", "shift", "edit", "drop",
                                                                   "description")}
    for p in range(phases):
        uids = {"study": _uid(fx, 7, 1), "series": _uid(fx, 7, 2, p), "frame": _uid(fx, 7, 3),
                "description": hook["description"](p) or f"Gated {10 * p}%", **(hook["uids"](p) or {})}
        vol = phase_ct(FOURD_SHAPE, FOURD_SPACING, 1.0 + 0.06 * p, rng)
        z = hook["z"](p)
        keep = [k for k in range(nz) if k not in set(hook["drop"](p) or ())]
        zs = [origin[2] + k * sz for k in range(nz)] if z is None else list(z)
        write_ct(folder / f"phase{p}", vol[keep], FOURD_SPACING, origin, uids, z=[zs[k] for k in keep],
                 iop=hook["iop"](p), shift=hook["shift"](p), edit=hook["edit"](p))
    return folder


def circle(z: float, r: float = 10.0, c=GTV_CENTRE[:2], n: int = 24):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([c[0] + r * np.cos(a), c[1] + r * np.sin(a), np.full(n, float(z))], 1)


def sphere_contours(zs, r: float = 10.0, zc: float = GTV_CENTRE[2]):
    """Circular sections of a sphere of radius ``r`` at heights ``zs`` (inside it)."""
    return [circle(z, np.sqrt(max(r * r - (z - zc) ** 2, 1.0))) for z in zs]


def rtstruct_with(fx, path: Path, rois, edit: Callable | None = None) -> Path:
    """The probe's GTV RTSTRUCT with its ROIs replaced by ``rois`` = [(name, [contour (k, 3)], kind)]
    (contours written as given: NaN, 1e308 …), then ``edit(ds)``."""
    import pydicom
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    ds = pydicom.dcmread(fx.gtv)
    frame = ds.FrameOfReferenceUID
    ds.StructureSetROISequence, ds.ROIContourSequence, ds.RTROIObservationsSequence = Sequence(), Sequence(), Sequence()
    for number, (name, contours, kind) in enumerate(rois, start=1):
        roi = Dataset()
        roi.ROINumber, roi.ReferencedFrameOfReferenceUID, roi.ROIName = number, frame, name
        roi.ROIGenerationAlgorithm = "MANUAL"
        ds.StructureSetROISequence.append(roi)
        rc = Dataset()
        rc.ROIDisplayColor, rc.ReferencedROINumber, rc.ContourSequence = [255, 0, 0], number, Sequence()
        for i, pts in enumerate(contours, start=1):
            c = Dataset()
            c.ContourNumber, c.ContourGeometricType = i, "CLOSED_PLANAR"
            c.NumberOfContourPoints = len(pts)
            c.ContourData = [f"{x:.6g}"[:16] for x in np.asarray(pts, float).ravel()]
            rc.ContourSequence.append(c)
        ds.ROIContourSequence.append(rc)
        obs = Dataset()
        obs.ObservationNumber, obs.ReferencedROINumber, obs.RTROIInterpretedType = number, number, kind
        obs.ROIInterpreter = ""
        ds.RTROIObservationsSequence.append(obs)
    if edit is not None:
        edit(ds)
    ds.save_as(path, enforce_file_format=False)
    return path


def edited_gtv(fx, path: Path, edit: Callable) -> Path:
    """The probe's GTV RTSTRUCT with ``edit(ds)`` applied."""
    import pydicom

    ds = pydicom.dcmread(fx.gtv)
    edit(ds)
    ds.save_as(path, enforce_file_format=False)
    return path


def write_mha(path: Path, header: dict, data: bytes = b"") -> Path:
    """A MetaImage with the ``header`` lines as given (ElementDataFile last) and ``data``."""
    lines = "".join(f"{k} = {v}\n" for k, v in header.items())
    path.write_bytes(lines.encode() + data)
    return path


def mha_header(**over) -> dict:
    h = {"ObjectType": "Image", "NDims": "3", "BinaryData": "True", "BinaryDataByteOrderMSB": "False",
         "CompressedData": "False", "TransformMatrix": "1 0 0 0 1 0 0 0 1", "Offset": "-180 -108 -166",
         "ElementSpacing": "8 8 10", "DimSize": "24 27 34", "ElementType": "MET_UCHAR", "ElementDataFile": "LOCAL"}
    h.update({k.replace("_", ""): v for k, v in over.items()})
    return h


def huge_mha(path: Path, side: int = 1000) -> Path:
    """``side``³ zero bytes deflated (about 1 MB for 1000³): passes the inflate-ratio check."""
    comp, chunks, left = zlib.compressobj(9), [], side ** 3
    block = bytes(1 << 24)
    while left:
        n = min(left, len(block))
        chunks.append(comp.compress(block[:n]))
        left -= n
    chunks.append(comp.flush())
    data = b"".join(chunks)
    h = mha_header(DimSize=f"{side} {side} {side}", CompressedData="True", CompressedDataSize=str(len(data)),
                   ElementSpacing="1 1 1", Offset="-500 -500 -500")
    return write_mha(path, h, data)


def model_variant(fx, path: Path, edit: Callable) -> Path:
    """The probe's model file with ``edit(arrays: dict)`` applied, saved as an .npz."""
    with np.load(fx.model, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    edit(arrays)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def provenance_with(arrays: dict, **extra) -> None:
    prov = json.loads(str(arrays["provenance"]))
    prov.update(extra)
    arrays["provenance"] = np.array(json.dumps(prov))


def curve_text(t=None, v=None) -> str:
    t = np.linspace(0, 8, 161) if t is None else t
    v = 250 * (1 - np.cos(np.pi * t / 2)) if v is None else v
    return "t_s,volume_ml\n" + "".join(f"{a:.6g},{b:.6g}\n" for a, b in zip(t, v))


def samples_text(n: int = 300, rate: float = 25.0, amp=None) -> str:
    t = np.arange(n) / rate
    a = 10 * np.sin(2 * np.pi * t / 4.0) if amp is None else amp(t)
    return "".join(f"{x:.4f},{y:.6g}\n" for x, y in zip(t, a))


def marker_csv(amp=None) -> str:
    """A marker trace (``Frame;Timestamp(ms);x;y;z``, what ``view --trace`` reads): 12 s at 25 Hz."""
    t = np.arange(300) / 25.0
    a = 10 * np.sin(2 * np.pi * t / 4.0) if amp is None else amp(t)
    return "Frame;Timestamp(ms);x;y;z\n" + "".join(f"{i};{1000 * x:.0f};0;{y:.6g};0\n" for i, (x, y) in enumerate(zip(t, a)))


def ellipsoid_mask(shape, spacing, origin, centres, axes):
    nz, ny, nx = shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    p = np.stack([origin[0] + i * spacing[0], origin[1] + j * spacing[1], origin[2] + k * spacing[2]], -1)
    m = np.zeros(shape, np.uint8)
    for c, a in zip(centres, axes):
        m[(((p - c) / a) ** 2).sum(-1) <= 1] = 1
    return m


def copd_case(folder: Path, n: int, shift=(3.0, -2.0, 4.0), seed: int = 3) -> None:
    """DIR-Lab-named files of case ``n``: two ellipsoid lungs at expiration, scaled (1.06, 1.06, 1.12)
    and shifted at inspiration, 8 landmarks per lung moved alike (after tests/validate/test_copd.py)."""
    from lungdeform.io.image import write_image
    from lungdeform.io.landmarks import write_elastix_points

    shape, spacing, origin = (44, 40, 64), np.array([3.5, 3.5, 4.0]), np.array([-112.0, -70.0, -88.0])
    centres = [np.array([45.0, 0.0, 0.0]), np.array([-47.0, 0.0, 0.0])]
    axes = [np.array([32.0, 42.0, 62.0]), np.array([34.0, 44.0, 64.0])]
    scale = np.array([1.06, 1.06, 1.12])
    exp = ellipsoid_mask(shape, spacing, origin, centres, axes)
    insp = ellipsoid_mask(shape, spacing, origin, centres, [a * scale for a in axes])
    write_image(folder / f"copd{n}_exp_mask.nii.gz", exp, spacing, origin, np.eye(3))
    write_image(folder / f"copd{n}_insp_mask.nii.gz", insp, spacing, origin + shift, np.eye(3))
    rng = np.random.default_rng(seed)
    a = np.concatenate([c + rng.uniform(-0.5, 0.5, (8, 3)) * ax for c, ax in zip(centres, axes)])
    b = np.array([c + (q - c) * scale + shift for c, q in zip(np.repeat(centres, 8, 0), a)])
    write_elastix_points(folder / f"copd{n}_exp_landmarks.txt", a)
    write_elastix_points(folder / f"copd{n}_insp_landmarks.txt", b)


@dataclass
class Fixtures:
    """The shared, read-only inputs (built once): paths, and the model's end-exhale volume."""

    root: Path
    seed: int
    model: Path = None
    ct: Path = None
    gtv: Path = None
    ref: Path = None
    image: Path = None
    curve: Path = None
    trace: Path = None
    copd: Path = None
    v_ee: float = 0.0
    ct_uids: dict = None

    @property
    def v1(self) -> str:
        return f"{self.v_ee + 300:.1f}"


def build_fixtures(root: Path, seed: int) -> Fixtures:
    import pydicom

    from lungdeform.geometry.mesh import Surface, icosphere
    from lungdeform.io.dicom.rtstruct import read_ct_series, write_rtstruct
    from lungdeform.io.image import write_image
    from lungdeform.io.modelfile import save_model
    from lungdeform.model.lung import Model, build_lung

    fx = Fixtures(root, seed)
    root.mkdir(parents=True, exist_ok=True)
    # the probe writes invalid values on purpose (NaN in a DS): pydicom need not warn about them
    pydicom.config.settings.reading_validation_mode = pydicom.config.IGNORE
    pydicom.config.settings.writing_validation_mode = pydicom.config.IGNORE
    warnings.filterwarnings("ignore", category=UserWarning, module="pydicom")
    lungs = {}
    for side, x in (("left", 90.0), ("right", -90.0)):
        s = icosphere(2)
        lungs[side] = build_lung(Surface(s.vertices * [60.0, 80.0, 110.0] + [x, 0, 0], s.faces, side), side)
    model = Model(lungs, {"source": "hostile probe ellipsoids"})
    fx.model = save_model(root / "model.npz", model)
    fx.v_ee = float(sum(lung.volume_ee_ml for lung in lungs.values()))
    # the reference CT of the GTV: 32 x 32 x 20 slices of 2 mm around the GTV centre
    fx.ct_uids = {"study": _uid(fx, 1), "series": _uid(fx, 2), "frame": _uid(fx, 3)}
    origin = GTV_CENTRE + [-31.0, -31.0, -19.0]
    fx.ct = write_ct(root / "ct", np.zeros((20, 32, 32), np.int16), (2.0, 2.0, 2.0), origin, fx.ct_uids)
    sphere = icosphere(3, 10.0, center=tuple(GTV_CENTRE))
    fx.gtv = root / "gtv.dcm"
    write_rtstruct(fx.gtv, read_ct_series(fx.ct), [("GTV", sphere.vertices, sphere.faces, "GTV")])
    a = np.zeros((34, 27, 24), np.uint8)  # a coarse label image of the lungs' boxes
    a[8:26, 5:22, 2:9] = 1
    a[8:26, 5:22, 15:22] = 2
    fx.ref = write_image(root / "ref.nii.gz", a, [8.0, 8.0, 10.0], [-100.0, -108.0, -166.0], np.eye(3))
    hu = np.where(a > 0, -850, 40).astype(np.int16)
    fx.image = write_image(root / "ct.nii.gz", hu, [8.0, 8.0, 10.0], [-100.0, -108.0, -166.0], np.eye(3))
    fx.curve = root / "curve.csv"
    fx.curve.write_text(curve_text())
    fx.trace = root / "trace.csv"
    fx.trace.write_text(marker_csv())
    fx.copd = root / "copd"
    fx.copd.mkdir()
    copd_case(fx.copd, 1)
    return fx


# --- cases -----------------------------------------------------------------------------------------

@dataclass
class Case:
    """One hostile input: ``build(fx, d)`` writes its inputs into the case folder ``d`` and returns the
    arguments after ``lungdeform`` (or ``(args, stdin bytes)``)."""

    name: str
    command: str
    expect: str
    build: Callable
    why: str = ""
    #: (signal number, glob under the case folder whose first match triggers it, allowed(relative path,
    #: case folder): what may stay after the signal)
    signal: tuple | None = None
    #: for an exit 0: a reason the output is wrong, or None
    verify: Callable | None = None
    #: ``runner(d, argv, limit, env) -> Run`` instead of a plain run
    runner: Callable | None = None
    timeout: float | None = None


@dataclass
class Settings:
    """How the cases run: per-case time-out (s), address-space cap per run (GiB), seed, parallel runs."""

    timeout: float = 60.0
    memory_gib: float = 6.0
    seed: int = 0
    workers: int = 1


@dataclass
class Run:
    """What one run gave: exit code (None after a time-out), its output, whether it was killed for
    running past the time-out, whether the case's signal was sent."""

    rc: int | None
    stdout: str
    stderr: str
    timed_out: bool = False
    signalled: bool = False


@dataclass
class Result:
    name: str
    command: str
    expect: str
    outcome: str
    rc: int | None
    stderr_first_line: str
    seconds: float
    argv: str = ""
    reason: str = ""
    why: str = ""
    stderr: str = field(default="", repr=False)


def _p(path) -> str:
    return str(path)


def track_rt(fx, d, rtstruct=None, ct=None, extra=(), out_rt=None, volume=True):
    """``track`` of a structure onto ``--reference-ct`` (defaults: the probe's GTV and CT)."""
    args = ["track", _p(fx.model), "--rtstruct", _p(rtstruct or fx.gtv), "--structure", "GTV",
            "--out", _p(d / "out"), "--out-rtstruct", _p(out_rt or d / "moved.dcm"), "--reference-ct", _p(ct or fx.ct)]
    return args + (["--volume-ml", fx.v1] if volume else []) + list(extra)


def ct_variant(fx, d, name="ref", **kw) -> Path:
    """The probe's reference CT written again under ``d/name`` with ``write_ct`` hooks ``kw``."""
    uids = {**fx.ct_uids, **kw.pop("uids", {})}
    nz = kw.pop("nz", 20)
    return write_ct(d / name, np.zeros((nz, 32, 32), np.int16), (2.0, 2.0, 2.0), GTV_CENTRE + [-31.0, -31.0, -19.0],
                    uids, **kw)


def _set(**attrs):
    def edit(ds, *_k):
        for key, value in attrs.items():
            setattr(ds, key, value)
    return edit


def _set_frame(uid):
    def edit(ds):
        ds.FrameOfReferenceUID = uid
        ds.ReferencedFrameOfReferenceSequence[0].FrameOfReferenceUID = uid
        for roi in ds.StructureSetROISequence:
            roi.ReferencedFrameOfReferenceUID = uid
    return edit


def _w(path: Path, data) -> None:
    """Write ``data`` (text or bytes) to ``path``; None, so that ``_w(…) or args`` gives the args."""
    (path.write_bytes if isinstance(data, bytes) else path.write_text)(data)


def _copy(src: Path, dst: Path) -> Path:
    (shutil.copytree if src.is_dir() else shutil.copy2)(src, dst)
    return dst


def _rtstruct_names(path: Path) -> list:
    import pydicom

    return [str(r.ROIName) for r in pydicom.dcmread(path).StructureSetROISequence]


def verify_non_ascii(d: Path, _stdout: str):
    import pydicom

    ds = pydicom.dcmread(d / "moved.dcm")
    charset = ds.get("SpecificCharacterSet", "")
    charset = list(charset) if not isinstance(charset, str) else [charset]
    names = [str(r.ROIName) for r in ds.StructureSetROISequence]
    if not any("192" in c for c in charset):
        return f"no SpecificCharacterSet ISO_IR 192 for ROI names {names!r}"
    if not all(n.startswith(("GTV-é肿瘤", "ITV_GTV-é肿瘤")) for n in names):  # NAME@TAG and the ITV
        return f"ROI names changed: {names!r}"
    return None


def verify_finite_stdout(_d: Path, stdout: str):
    bad = [ln for ln in stdout.splitlines() if any(w in ln.lower() for w in ("nan", "inf"))]
    return f"stdout holds {bad[0]!r}" if bad else None


def verify_contours_kept(n: int):
    def check(d: Path, _stdout: str):
        from lungdeform.io.dicom.rtstruct import read_rtstruct

        got = {k: len(s.contours) for k, s in read_rtstruct(d / "moved.dcm").items()}
        rest = [k for k in got if k.endswith(("@phase00",))] or list(got)[:1]
        return None if all(got[k] >= n for k in rest) else f"moved structure has {got} contours, drawn with {n}"
    return check


def verify_image_finite(name: str):
    def check(d: Path, _stdout: str):
        from lungdeform.io.image import read_image

        a = read_image(d / name).array
        return None if np.all(np.isfinite(a)) else f"{name} holds non-finite voxels"
    return check


def verify_field_nonzero(d: Path, _stdout: str):
    import SimpleITK as sitk

    a = sitk.GetArrayFromImage(sitk.ReadImage(str(d / "u.mha")))
    return None if np.abs(a).max() > 0.01 else "the displacement field is zero everywhere"


Z_GTV = GTV_CENTRE[2] - 9 + 2 * np.arange(10)  # the reference CT's slices through the GTV


def rt_case(name, expect, rois=None, edit=None, why="", ct=None, extra=(), **kw) -> Case:
    """A ``track`` case: the probe's GTV RTSTRUCT changed by ``edit(ds)`` (or with the ROIs ``rois``
    instead, :func:`rtstruct_with`) onto the reference CT ``ct(fx, d)`` (default: the probe's)."""
    def build(fx, d):
        path = rtstruct_with(fx, d / "rs.dcm", rois, edit) if rois is not None else edited_gtv(fx, d / "rs.dcm", edit)
        return track_rt(fx, d, path, ct(fx, d) if ct else None, extra)
    return Case(name, "track", expect, build, why, **kw)


def track_structure_cases() -> list[Case]:
    """Structures that disagree with the CT, or whose contours are damaged, odd or named badly."""
    C = []

    def rt(*args, **kw):
        C.append(rt_case(*args, **kw))

    rt("track_frame_and_study_mismatch", "refuse",
       edit=lambda ds: (_set_frame("1.2.3.4.5")(ds), _set(StudyInstanceUID="1.2.3.4.6")(ds)),
       why="RTSTRUCT drawn in another frame of reference and study than --reference-ct")
    rt("track_frame_mismatch", "refuse", edit=_set_frame("1.2.3.4.5"), why="RTSTRUCT frame of reference differs")
    rt("track_study_mismatch_only", "warn", edit=_set(StudyInstanceUID="1.2.3.4.6"), why="same frame, other study")
    rt("track_patient_mismatch", "warn", edit=_set(PatientID="SOMEONE-ELSE", PatientName="Other^Patient"),
       why="RTSTRUCT of another patient ID than the CT")
    rt("track_frame_uid_missing", "warn", edit=lambda ds: (delattr(ds, "FrameOfReferenceUID"),
                                                           delattr(ds, "ReferencedFrameOfReferenceSequence")),
       why="RTSTRUCT without any frame of reference")
    rt("track_contour_gap_6mm", "warn", rois=[("GTV", sphere_contours(np.delete(Z_GTV, [4, 5])), "GTV")],
       why="two contours missing: a 6 mm gap in 2 mm contours")
    rt("track_contour_every_6mm", "warn", rois=[("GTV", sphere_contours(Z_GTV[::3]), "GTV")],
       why="contours every 6 mm (every third 2 mm slice of the CT)")
    rt("track_contour_gap_18mm", "warn", rois=[("GTV", sphere_contours(np.r_[Z_GTV[:1], Z_GTV[-1:]]), "GTV")],
       why="only the first and last contour: 18 mm apart")
    rt("track_contour_nan", "warn", rois=[("GTV", sphere_contours(Z_GTV)[:5] + [circle(Z_GTV[5]) * np.nan]
                                            + sphere_contours(Z_GTV)[6:], "GTV")],
       why="one contour of NaN among ten")
    rt("track_contour_one_nan_point", "warn", rois=[("GTV", [c if i != 4 else np.where(np.arange(24)[:, None] == 3, np.nan, c)
                                                             for i, c in enumerate(sphere_contours(Z_GTV))], "GTV")],
       why="one NaN coordinate in one contour")
    rt("track_contour_all_nan", "refuse", rois=[("GTV", [circle(z) * np.nan for z in Z_GTV], "GTV")],
       why="every contour NaN")
    rt("track_contour_inf", "warn", rois=[("GTV", sphere_contours(Z_GTV)[:9] + [np.c_[np.full((24, 2), np.inf), circle(Z_GTV[9])[:, 2]]], "GTV")],
       why="one contour of infinities")
    rt("track_contour_1e308", "refuse", rois=[("GTV", sphere_contours(Z_GTV)[:9] + [circle(Z_GTV[9]) * 0 + 1e308], "GTV")],
       why="one contour at 1e308 mm")
    rt("track_contour_degenerate", "warn", rois=[("GTV", sphere_contours(Z_GTV)[:9] + [circle(Z_GTV[9])[:2]], "GTV")],
       why="a two-point contour")
    rt("track_contour_single_point_all", "refuse", rois=[("GTV", [circle(z)[:1] for z in Z_GTV], "GTV")],
       why="every contour a single point")
    rt("track_contour_nonplanar", "warn", rois=[("GTV", [c + [0, 0, 0] if i != 3 else c + np.c_[0 * c[:, :2], np.linspace(0, 5, 24)]
                                                        for i, c in enumerate(sphere_contours(Z_GTV))], "GTV")],
       why="one contour not in one plane (z 0-5 mm)")
    rt("track_contour_off_slice", "warn", rois=[("GTV", sphere_contours(Z_GTV + 0.7), "GTV")],
       why="contours 0.7 mm off the CT's slice planes")
    rt("track_contour_self_intersecting", "warn",
       rois=[("GTV", [c[[0, 12, 6, 18, 3, 15, 9, 21]] for c in sphere_contours(Z_GTV)], "GTV")],
       why="bow-tie (self-intersecting) polygons")
    rt("track_contour_outside_ct", "warn", rois=[("GTV", sphere_contours(Z_GTV + 60, zc=GTV_CENTRE[2] + 60), "GTV")],
       why="structure above the reference CT's last slice")
    rt("track_contours_dense_4000", "refuse",
       rois=[("GTV", [circle(GTV_CENTRE[2] - 20 + 0.01 * k) for k in range(4000)], "GTV")],
       why="4000 contours 0.01 mm apart: bounded time and memory")
    rt("track_contours_dense_400", "any",
       rois=[("GTV", [circle(GTV_CENTRE[2] - 10 + 0.05 * k) for k in range(400)], "GTV")],
       why="400 contours 0.05 mm apart")
    rt("track_contour_huge_polygon", "any", rois=[("GTV", [circle(z, n=2000) for z in Z_GTV], "GTV")],
       why="10 contours of 2000 points each (fine but valid)")
    rt("track_roi_non_ascii", "ok", rois=[("GTV-é肿瘤", sphere_contours(Z_GTV), "GTV")],
       edit=lambda ds: setattr(ds, "SpecificCharacterSet", "ISO_IR 192"), verify=verify_non_ascii,
       extra=["--structure", "GTV-é肿瘤"], why="UTF-8 ROI name: written back with SpecificCharacterSet")
    rt("track_roi_name_near_limit", "warn", rois=[("G" * 60, sphere_contours(Z_GTV), "GTV")], extra=["--structure", "G" * 60],
       why="60-character ROI name: NAME@volume exceeds DICOM's 64 (cut with its tag whole, said: issue 36)")
    rt("track_roi_name_over_limit", "warn", rois=[("X" * 80, sphere_contours(Z_GTV), "GTV")], extra=["--structure", "X" * 80],
       why="80-character ROI name in the input (over the DICOM limit)")
    rt("track_roi_duplicate", "refuse", rois=[("GTV", sphere_contours(Z_GTV), "GTV"),
                                              ("GTV", sphere_contours(Z_GTV[:4]), "GTV")],
       why="two ROIs named GTV")
    rt("track_roi_duplicate_case", "any", rois=[("GTV", sphere_contours(Z_GTV), "GTV"), ("gtv", sphere_contours(Z_GTV[:4]), "GTV")],
       why="ROIs GTV and gtv")
    rt("track_roi_no_contour_sequence", "refuse", rois=[("GTV", [], "GTV")], why="the ROI has no contours")
    rt("track_roi_nan_and_frame_mismatch", "refuse", rois=[("GTV", sphere_contours(Z_GTV)[:9] + [circle(Z_GTV[9]) * np.nan], "GTV")],
       edit=_set_frame("1.2.3.4.9"), why="a NaN contour and another frame of reference")
    rt("track_structure_empty_name", "refuse", extra=["--structure", ""], edit=lambda ds: None, why="--structure ''")

    return C


def track_ct_cases() -> list[Case]:
    """Reference CT series whose geometry or identity is wrong."""
    C = []

    def rt(*args, **kw):
        C.append(rt_case(*args, **kw))

    def ct_case(name, expect, why, **kw):
        rt(name, expect, edit=lambda ds: None, ct=lambda fx, d: ct_variant(fx, d, **kw), why=why,
           verify=verify_contours_kept(10) if expect in ("warn", "ok") else None)

    ct_case("track_ct_missing_slices", "warn", "reference CT missing 3 slices through the GTV",
            z=[GTV_CENTRE[2] - 19 + 2 * k for k in range(20) if k not in (8, 9, 10)], nz=17)
    ct_case("track_ct_uneven_spacing", "warn", "reference CT slices 2 and 4 mm apart in turn",
            z=np.cumsum([0] + [2 + 2 * (k % 2) for k in range(19)]) + GTV_CENTRE[2] - 29)
    tilt = np.radians(20)
    ct_case("track_ct_gantry_tilt", "warn", "reference CT with a 20° gantry tilt",
            iop=(1, 0, 0, 0, np.cos(tilt), -np.sin(tilt)), edit=_set(GantryDetectorTilt="20"))
    ct_case("track_ct_iop_zero", "refuse", "reference CT ImageOrientationPatient all zero", iop=(0, 0, 0, 0, 0, 0))
    ct_case("track_ct_iop_5_values", "refuse", "reference CT ImageOrientationPatient with 5 values",
            edit=lambda ds, k: _raw(ds, 0x00200037, "DS", "1\\0\\0\\0\\1"))
    ct_case("track_ct_iop_parallel", "refuse", "reference CT row and column directions parallel",
            iop=(1, 0, 0, 1, 0, 0))
    ct_case("track_ct_iop_nan", "refuse", "reference CT ImageOrientationPatient NaN",
            edit=lambda ds, k: _raw(ds, 0x00200037, "DS", "nan\\0\\0\\0\\1\\0"))
    ct_case("track_ct_ipp_text", "refuse", "reference CT ImagePositionPatient not numbers",
            edit=lambda ds, k: _raw(ds, 0x00200032, "DS", "left\\up\\" + str(k)))
    ct_case("track_ct_ipp_nan", "refuse", "reference CT ImagePositionPatient NaN on one slice",
            edit=lambda ds, k: _raw(ds, 0x00200032, "DS", "nan\\0\\0") if k == 7 else None)
    ct_case("track_ct_ipp_missing", "refuse", "reference CT without ImagePositionPatient",
            edit=lambda ds, k: delattr(ds, "ImagePositionPatient"))
    ct_case("track_ct_duplicate_positions", "refuse", "two reference CT slices at the same position",
            z=[GTV_CENTRE[2] - 19 + 2 * min(k, 18) for k in range(20)])
    ct_case("track_ct_mixed_orientation", "refuse", "one reference CT slice with another orientation",
            edit=lambda ds, k: setattr(ds, "ImageOrientationPatient", ["0", "1", "0", "1", "0", "0"]) if k == 5 else None)
    ct_case("track_ct_mixed_frames", "refuse", "reference CT slices in two frames of reference",
            edit=lambda ds, k: setattr(ds, "FrameOfReferenceUID", "1.2.3.99") if k % 2 else None)
    ct_case("track_ct_sheared_positions", "warn", "reference CT slices shifted 1 mm sideways each (sheared)",
            shift=lambda k: np.array([float(k), 0.0, 0.0]))

    def two_series(fx, d):
        ref = ct_variant(fx, d)
        other = {**fx.ct_uids, "series": _uid(fx, 2, 9), "frame": _uid(fx, 3, 9)}
        write_ct(ref, np.zeros((20, 32, 32), np.int16), (2.0, 2.0, 2.0), GTV_CENTRE + [-31.0, -31.0, -19.0], other,
                 name="other")
        return ref

    rt("track_ct_two_series", "warn", edit=lambda ds: None, ct=two_series,
       why="reference CT folder holding two series (two frames of reference)")

    return C


def track_output_cases() -> list[Case]:
    """Missing inputs, outputs onto inputs or under files, and out-of-range options."""
    C = []

    def simple(name, expect, build, why):
        C.append(Case(name, "track", expect, build, why))

    simple("track_ct_folder_missing", "refuse", lambda fx, d: track_rt(fx, d, ct=d / "nope"), "--reference-ct missing")
    simple("track_ct_empty_folder", "refuse", lambda fx, d: (d / "empty").mkdir() or track_rt(fx, d, ct=d / "empty"),
           "--reference-ct an empty folder")
    simple("track_ct_is_the_rtstruct", "refuse", lambda fx, d: track_rt(fx, d, ct=fx.gtv), "--reference-ct the RTSTRUCT file")
    simple("track_rtstruct_truncated", "refuse",
           lambda fx, d: _w(d / "rs.dcm", fx.gtv.read_bytes()[:1500]) or track_rt(fx, d, d / "rs.dcm"),
           "RTSTRUCT cut at 1500 bytes")
    simple("track_out_rtstruct_is_input", "refuse",
           lambda fx, d: track_rt(fx, d, _copy(fx.gtv, d / "rs.dcm"), out_rt=d / "rs.dcm"),
           "--out-rtstruct is the --rtstruct file")
    simple("track_out_rtstruct_is_ct_slice", "refuse",
           lambda fx, d: track_rt(fx, d, ct=_copy(fx.ct, d / "ct"), out_rt=d / "ct" / "ct0000.dcm"),
           "--out-rtstruct is a slice of --reference-ct")
    simple("track_out_rtstruct_is_folder", "refuse",
           lambda fx, d: (d / "moved.dcm").mkdir() or track_rt(fx, d), "--out-rtstruct an existing folder")
    simple("track_out_rtstruct_under_file", "refuse",
           lambda fx, d: _w(d / "plan.txt", "x") or track_rt(fx, d, out_rt=d / "plan.txt" / "moved.dcm"),
           "--out-rtstruct under a regular file")
    simple("track_out_under_file", "refuse",
           lambda fx, d: _w(d / "plan.txt", "x") or
           [*track_rt(fx, d)[:6], "--out", _p(d / "plan.txt" / "o"), *track_rt(fx, d)[8:]],
           "--out under a regular file")
    simple("track_out_is_file", "refuse",
           lambda fx, d: _w(d / "out", "x") or track_rt(fx, d), "--out an existing file")
    simple("track_out_rtstruct_is_model", "refuse",
           lambda fx, d: ["track", _p(_copy(fx.model, d / "m.npz")), *track_rt(fx, d, out_rt=d / "m.npz")[2:]],
           "--out-rtstruct is the model file")
    for value in ("nan", "inf", "1e308", "-3000", "0"):
        simple(f"track_volume_{value}", "refuse",
               lambda fx, d, v=value: track_rt(fx, d, volume=False, extra=["--volume-ml", v]), f"--volume-ml {value}")
    for value in ("100000", "0", "-2", "1000000000000"):
        simple(f"track_phases_{value}", "refuse",
               lambda fx, d, v=value: track_rt(fx, d, volume=False, extra=["--phases", v]), f"--phases {value}")
    simple("track_phases_curve_nan", "refuse",
           lambda fx, d: _w(d / "c.csv", curve_text(v=np.r_[250 * (1 - np.cos(np.pi * np.linspace(0, 8, 161)[:100] / 2)),
                                                                       [np.nan] * 61]))
           or track_rt(fx, d, volume=False, extra=["--phases", "4", "--curve", _p(d / "c.csv")]),
           "--curve whose last 61 volumes are NaN")
    simple("track_points_1e308", "refuse",
           lambda fx, d: _w(d / "p.csv", "x_mm,y_mm,z_mm\n90,0,-40\n1e308,-1e308,0\n")
           or ["track", _p(fx.model), "--points", _p(d / "p.csv"), "--out", _p(d / "out"), "--volume-ml", fx.v1],
           "--points row at ±1e308")
    simple("track_valid_control", "ok", lambda fx, d: track_rt(fx, d), "the probe's GTV onto its own CT (control)")
    return C


def track_cases() -> list[Case]:
    return track_structure_cases() + track_ct_cases() + track_output_cases()


#: Time-out (s) of a case that may run a whole (small) fit: about 20 s of work on an idle core, so that a
#: fit accepted on loaded cores is told from a hang
FIT_TIMEOUT = 180.0


def fit_args(folder, d, *extra):
    return ["fit", _p(folder), "--side", "right", "--out", _p(d / "out"), "--no-baselines", "--evaluations", "10",
            "--direction-degree", "0", "--no-stiffness", "--align", "none", "--interior", "sliding", "--refine-mm", "0", *extra]


def fit_cases() -> list[Case]:
    C = []

    def f4(name, expect, why, extra=(), **hooks):
        C.append(Case(name, "fit", expect, lambda fx, d: fit_args(write_4dct(fx, d / "ct4d", **hooks), d, *extra), why,
                      timeout=FIT_TIMEOUT))

    other = {"patient": "PROBE02", "patient_name": "Other^Patient", "study": "1.2.3.4.77", "frame": "1.2.3.4.78"}
    f4("fit4d_two_patients", "refuse", "phases 2 and 3 of another patient (study, frame of reference)",
       uids_of=lambda p: other if p >= 2 else {})
    f4("fit4d_two_frames", "refuse", "phase 1 in another frame of reference", uids_of=lambda p: {"frame": "1.2.3.4.79"} if p == 1 else {})
    f4("fit4d_two_studies", "warn", "phase 3 in another study, same frame", uids_of=lambda p: {"study": "1.2.3.4.80"} if p == 3 else {})
    zs = np.cumsum([0] + [6 if k % 2 == 0 else 3 for k in range(23)]) - 50.0
    f4("fit4d_uneven_spacing", "warn", "slices 6 mm then 3 mm apart in every phase", z_of=lambda p: zs)
    tilt = np.radians(20)
    f4("fit4d_gantry_tilt", "warn", "20° gantry tilt in every phase", iop_of=lambda p: (1, 0, 0, 0, np.cos(tilt), -np.sin(tilt)),
       edit_of=lambda p: _set(GantryDetectorTilt="20"))
    f4("fit4d_missing_slices", "warn", "phase 2 missing 3 slices in the lungs", drop_of=lambda p: (10, 11, 12) if p == 2 else ())
    f4("fit4d_iop_5_values", "refuse", "phase 1 ImageOrientationPatient with 5 values",
       edit_of=lambda p: (lambda ds, k: _raw(ds, 0x00200037, "DS", "1\\0\\0\\0\\1")) if p == 1 else None)
    f4("fit4d_iop_zero", "refuse", "phase 0 ImageOrientationPatient all zero", iop_of=lambda p: (0,) * 6 if p == 0 else (1, 0, 0, 0, 1, 0))
    f4("fit4d_ipp_text", "refuse", "phase 3 ImagePositionPatient not numbers",
       edit_of=lambda p: (lambda ds, k: _raw(ds, 0x00200032, "DS", "a\\b\\c")) if p == 3 else None)
    f4("fit4d_duplicate_phase", "refuse", "two series both 'Gated 20%'", description_of=lambda p: "Gated 20%" if p in (2, 3) else f"Gated {10 * p}%")
    f4("fit4d_rescale_nan", "refuse", "phase 1 RescaleSlope NaN",
       edit_of=lambda p: (lambda ds, k: _raw(ds, 0x00281053, "DS", "nan")) if p == 1 else None)
    f4("fit4d_mixed_pixel_spacing", "any", "phase 2 with 3 mm pixels declared (same grid)",
       edit_of=lambda p: _set(PixelSpacing=["3", "3"]) if p == 2 else None)
    f4("fit4d_two_patients_uneven", "refuse", "two patients and uneven slices together",
       uids_of=lambda p: other if p == 3 else {}, z_of=lambda p: zs)
    f4("fit4d_one_phase", "refuse", "a 4-D CT folder of one phase", phases=1)
    C.append(Case("fit4d_empty_folder", "fit", "refuse", lambda fx, d: (d / "ct4d").mkdir() or fit_args(d / "ct4d", d),
                  "an empty folder"))
    C.append(Case("fit4d_out_is_input", "fit", "refuse",
                  lambda fx, d: [*fit_args(write_4dct(fx, d / "ct4d"), d)[:5], _p(d / "ct4d"), *fit_args(d / "ct4d", d)[6:]],
                  "--out is the 4-D CT folder"))
    C.append(Case("fit4d_out_under_file", "fit", "refuse",
                  lambda fx, d: _w(d / "f", "x") or
                  [*fit_args(write_4dct(fx, d / "ct4d"), d)[:5], _p(d / "f" / "o"), *fit_args(d / "ct4d", d)[6:]],
                  "--out under a regular file"))
    for opt, value in (("--evaluations", "0"), ("--refine-mm", "nan"), ("--volumes", "nan,inf,1,2"), ("--folds", "-1")):
        C.append(Case(f"fit4d_option_{opt[2:]}_{value.split(',')[0]}", "fit", "refuse",
                      lambda fx, d, o=opt, v=value: fit_args(write_4dct(fx, d / "ct4d"), d, o, v), f"{opt} {value}"))
    C.append(Case("fit_missing_input", "fit", "refuse", lambda fx, d: fit_args(d / "nope", d), "input folder missing"))
    C.append(Case("fit4d_valid_control", "fit", "ok", lambda fx, d: fit_args(write_4dct(fx, d / "ct4d"), d),
                  "a clean 4-phase 4-D CT (control)", timeout=FIT_TIMEOUT))
    return C


def dvf_args(fx, d, *extra, model=None, ref=None, out=None, volume=True):
    return (["dvf", _p(model or fx.model), "--reference", _p(ref or fx.ref), "--out", _p(out or d / "u.mha")]
            + (["--volume-ml", fx.v1] if volume else []) + list(extra))


def model_edit(key: str, fn: Callable, lung: str = "left"):
    def edit(arrays):
        k = f"lung/{lung}/{key}"
        arrays[k] = fn(arrays[k])
    return edit


def dvf_cases() -> list[Case]:
    C = []
    for value in ("1e9", "nan", "inf", "-1", "0", "1e308"):
        C.append(Case(f"dvf_volume_{value}", "dvf", "refuse", lambda fx, d, v=value: dvf_args(fx, d, "--volume-ml", v, volume=False),
                      f"--volume-ml {value}"))
    for value in ("1e9", "inf", "nan", "0", "-4", "1e-3"):
        C.append(Case(f"dvf_node_mm_{value}", "dvf", "refuse", lambda fx, d, v=value: dvf_args(fx, d, "--node-mm", v),
                      f"--node-mm {value}"))
    C.append(Case("dvf_scan_huge", "dvf", "refuse", lambda fx, d: dvf_args(fx, d, "--scan", "99999999999", volume=False),
                  "--scan 99999999999"))

    def mha(name, why, expect="refuse", data=None, **over):
        def build(fx, d):
            h = mha_header(**over)
            n = int(np.prod([int(float(x)) for x in h["DimSize"].split()])) if data is None else 0
            return dvf_args(fx, d, ref=write_mha(d / "ref.mha", h, bytes(n) if data is None else data))
        C.append(Case(name, "dvf", expect, build, why))

    mha("dvf_ref_offset_nan", "reference .mha with Offset = nan", Offset="nan 0 0")
    mha("dvf_ref_offset_inf", "reference .mha with Offset = inf", Offset="0 inf 0")
    mha("dvf_ref_spacing_zero", "reference .mha with ElementSpacing 0", ElementSpacing="0 8 10")
    mha("dvf_ref_spacing_negative", "reference .mha with a negative spacing", ElementSpacing="8 -8 10")
    mha("dvf_ref_spacing_nan", "reference .mha with ElementSpacing nan", ElementSpacing="nan 8 10")
    mha("dvf_ref_spacing_1e308", "reference .mha with ElementSpacing 1e308", ElementSpacing="1e308 8 10")
    mha("dvf_ref_direction_zero", "reference .mha with an all-zero TransformMatrix", TransformMatrix="0 0 0 0 0 0 0 0 0")
    mha("dvf_ref_direction_singular", "reference .mha with two equal axes", TransformMatrix="1 0 0 1 0 0 0 0 1")
    mha("dvf_ref_direction_nan", "reference .mha with a NaN in TransformMatrix", TransformMatrix="nan 0 0 0 1 0 0 0 1")
    mha("dvf_ref_offset_1e308", "reference .mha 1e308 mm away", Offset="1e308 0 0")
    mha("dvf_ref_2d", "a 2-D reference", NDims="2", DimSize="24 27", ElementSpacing="8 8", Offset="0 0",
        TransformMatrix="1 0 0 1")
    C.append(Case("dvf_ref_huge_1000cubed", "dvf", "refuse", lambda fx, d: dvf_args(fx, d, ref=huge_mha(d / "huge.mha")),
                  "a 1 MB .mha declaring 1000³ voxels: a grid-size cap", timeout=120))
    mha("dvf_ref_huge_header_no_data", "header declaring 1000³ voxels in a missing .raw", expect="refuse",
        data=b"", DimSize="1000 1000 1000", ElementDataFile="missing.raw")
    mha("dvf_ref_huge_grid_tiny_spacing", "a 1000 x 1000 x 1000 grid of 0.1 mm (the field would be 12 GB)",
        expect="refuse", data=None, DimSize="1000 1000 1", ElementSpacing="0.1 0.1 0.1")

    C.append(Case("dvf_out_is_folder", "dvf", "refuse", lambda fx, d: (d / "u.mha").mkdir() or dvf_args(fx, d),
                  "--out u.mha an existing folder"))
    C.append(Case("dvf_out_is_reference", "dvf", "refuse",
                  lambda fx, d: dvf_args(fx, d, ref=_copy(fx.ref, d / "ref.nii.gz"), out=d / "ref.nii.gz"),
                  "--out is --reference"))
    C.append(Case("dvf_out_under_file", "dvf", "refuse",
                  lambda fx, d: _w(d / "f", "x") or dvf_args(fx, d, out=d / "f" / "u.mha"), "--out under a regular file"))
    C.append(Case("dvf_valid_control", "dvf", "ok", lambda fx, d: dvf_args(fx, d), "the probe's model on its label image (control)",
                  verify=verify_field_nonzero))
    return C


def model_cases() -> list[Case]:
    """Damaged model files (complex, NaN, out-of-range arrays; a bad provenance), read by ``dvf``."""
    C = []

    def bad_model(name, why, edit, expect="refuse", extra=()):
        C.append(Case(name, "model", expect, lambda fx, d: dvf_args(fx, d, *extra, model=model_variant(fx, d / "m.npz", edit)), why))

    bad_model("model_complex_displacement", "displacement stored complex128", model_edit("displacement", lambda a: a.astype(complex)))
    bad_model("model_complex_vertices", "vertices complex128 (imaginary parts 1 mm)", model_edit("vertices", lambda a: a + 1j))
    bad_model("model_float32_vertices", "vertices float32", model_edit("vertices", lambda a: a.astype(np.float32)), expect="any")
    bad_model("model_int_faces_as_float", "faces stored float64", model_edit("faces", lambda a: a.astype(float)), expect="any")
    bad_model("model_nan_vertex", "one vertex NaN", model_edit("vertices", lambda a: np.where(np.arange(len(a))[:, None] == 5, np.nan, a)))
    bad_model("model_inf_displacement", "one displacement infinite", model_edit("displacement", lambda a: np.where(np.arange(len(a))[:, None] == 5, np.inf, a)))
    bad_model("model_huge_displacement", "displacements of 1e300 mm", model_edit("displacement", lambda a: a * 1e300))
    bad_model("model_unit_ml_zero", "unit_ml 0", model_edit("unit_ml", lambda a: np.array(0.0)))
    bad_model("model_unit_ml_nan", "unit_ml NaN", model_edit("unit_ml", lambda a: np.array(np.nan)))
    bad_model("model_volume_ee_negative", "volume_ee_ml -1", model_edit("volume_ee_ml", lambda a: np.array(-1.0)))
    bad_model("model_volume_ee_nan", "volume_ee_ml NaN", model_edit("volume_ee_ml", lambda a: np.array(np.nan)))
    bad_model("model_faces_negative", "a face index -7", model_edit("faces", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 4, -7, a)))
    bad_model("model_side_middle", "side 'middle'", model_edit("side", lambda a: np.array("middle")))
    bad_model("model_constants_nan", "c5 NaN", model_edit("constants", lambda a: np.where(np.arange(9) == 4, np.nan, a)))
    bad_model("model_gravity_zero", "gravity (0, 0, 0)", model_edit("gravity", lambda a: np.zeros(3)))
    bad_model("model_provenance_matrix_4", "provenance alignment matrix of 4 values, --scan 1",
              lambda a: provenance_with(a, volumes_ml=[2000.0, 2300.0], alignment=[{"applied": {"matrix": [1, 0, 0, 1]}}]),
              extra=())
    bad_model("model_provenance_matrix_nan", "provenance alignment matrix of NaN, --scan 1",
              lambda a: provenance_with(a, volumes_ml=[2000.0, 2300.0], alignment=[{"applied": {"matrix": [[np.nan] * 4] * 4}}]))
    bad_model("model_provenance_volumes_text", "provenance volumes_ml text, --scan 1",
              lambda a: provenance_with(a, volumes_ml=["a", "b"]))
    bad_model("model_provenance_not_json", "provenance not JSON", lambda a: a.update(provenance=np.array("{not json")))
    bad_model("model_provenance_list", "provenance a JSON list", lambda a: a.update(provenance=np.array("[1, 2]")))
    bad_model("model_schema_version_99", "schema_version 99", lambda a: a.update(schema_version=np.array(99)))
    bad_model("model_lungs_missing_lung", "lungs names a lung with no arrays", lambda a: a.update(lungs=np.array(["left", "right", "middle"])))
    bad_model("model_no_lungs", "lungs empty", lambda a: a.update(lungs=np.array([], dtype="<U5")))
    for c in C:
        if c.name.startswith("model_provenance_m") or c.name.startswith("model_provenance_volumes"):
            build = c.build
            c.build = lambda fx, d, b=build: [*[x for x in b(fx, d) if x not in ("--volume-ml", fx.v1)], "--scan", "1"]
    return C


def warp_args(fx, d, *extra, image=None, out=None, volume=True):
    return (["warp", _p(image or fx.image), _p(fx.model), "--out", _p(out or d / "w.mha")]
            + (["--volume-ml", fx.v1] if volume else []) + list(extra))


def phases_args(fx, d, n: str, out=None, image=None):
    return warp_args(fx, d, "--curve", _p(fx.curve), "--phases", n, out=out, image=image, volume=False)


def _no_leftovers(_rel: str, _d: Path) -> bool:
    return False


def warp_cases() -> list[Case]:
    C = []
    for n in ("100000", "0", "-3", "101"):
        C.append(Case(f"warp_phases_{n}", "warp", "refuse", lambda fx, d, v=n: phases_args(fx, d, v), f"--phases {n} to .mha files"))
    C.append(Case("warp_phases_101_dicom", "warp", "refuse", lambda fx, d: phases_args(fx, d, "101", out=d / "4dct"),
                  "--phases 101 as DICOM folders"))
    for opt, v in (("--node-mm", "inf"), ("--node-mm", "nan"), ("--node-mm", "1e9"), ("--volume-ml", "1e9"), ("--volume-ml", "nan")):
        vol = opt != "--volume-ml"
        C.append(Case(f"warp_{opt[2:].replace('-', '_')}_{v}", "warp", "refuse",
                      lambda fx, d, o=opt, x=v, vol=vol: warp_args(fx, d, o, x, volume=vol), f"{opt} {v}"))
    C.append(Case("warp_out_is_folder_mha", "warp", "refuse", lambda fx, d: (d / "w.mha").mkdir() or warp_args(fx, d),
                  "--out X.mha an existing folder"))
    C.append(Case("warp_out_is_image", "warp", "refuse",
                  lambda fx, d: warp_args(fx, d, image=_copy(fx.image, d / "ct.nii.gz"), out=d / "ct.nii.gz"),
                  "--out is the input image"))
    C.append(Case("warp_out_under_file", "warp", "refuse",
                  lambda fx, d: _w(d / "f", "x") or warp_args(fx, d, out=d / "f" / "w.mha"), "--out under a regular file"))
    C.append(Case("warp_phase_out_is_image", "warp", "refuse",
                  lambda fx, d: phases_args(fx, d, "2", image=_copy(fx.image, d / "ct_phase01.nii.gz"), out=d / "ct.nii.gz"),
                  "--phases output OUT_phase01 is the input image"))
    C.append(Case("warp_curve_nan", "warp", "refuse",
                  lambda fx, d: _w(d / "c.csv", curve_text(v=np.full(161, np.nan)))
                  or warp_args(fx, d, "--curve", _p(d / "c.csv"), "--phases", "2", volume=False), "--curve all NaN"))
    C.append(Case("warp_curve_1e308", "warp", "refuse",
                  lambda fx, d: _w(d / "c.csv", curve_text(v=1e308 * np.sin(np.linspace(0, 8, 161))))
                  or warp_args(fx, d, "--curve", _p(d / "c.csv"), "--phases", "2", volume=False), "--curve of ±1e308 mL"))
    C.append(Case("warp_curve_flat", "warp", "any",
                  lambda fx, d: _w(d / "c.csv", curve_text(v=np.zeros(161)))
                  or warp_args(fx, d, "--curve", _p(d / "c.csv"), "--phases", "2", volume=False), "--curve flat"))

    def img(name, why, expect, arr_fn, verify_name="w.mha"):
        def build(fx, d):
            from lungdeform.io.image import read_image, write_image

            im = read_image(fx.image)
            a = arr_fn(im.array.astype(np.float64))
            return warp_args(fx, d, image=write_image(d / "in.mha", a, im.spacing, im.origin, im.direction))
        C.append(Case(name, "warp", expect, build, why, verify=verify_image_finite(verify_name)))

    img("warp_image_pm1e308", "input voxels of ±1e308", "warn",
        lambda a: np.where(np.indices(a.shape).sum(0) % 2 == 0, 1e308, -1e308))
    img("warp_image_nan_voxels", "input with NaN voxels", "warn", lambda a: np.where(a < 0, np.nan, a))
    img("warp_image_inf_voxels", "input with infinite voxels", "warn", lambda a: np.where(a < 0, -np.inf, a))
    def offset_nan(fx, d):
        (d / "in.raw").write_bytes(bytes(24 * 27 * 34))
        return warp_args(fx, d, image=write_mha(d / "in.mhd", mha_header(Offset="nan nan nan", ElementDataFile="in.raw")))
    C.append(Case("warp_image_offset_nan", "warp", "refuse", offset_nan, "input .mhd with Offset = nan"))
    C.append(Case("warp_valid_control", "warp", "ok", lambda fx, d: warp_args(fx, d), "one state to .mha (control)"))
    C.append(Case("warp_phases_valid_control", "warp", "ok", lambda fx, d: phases_args(fx, d, "2"), "two phases to .mha (control)"))

    for sig, tag in ((signal.SIGTERM, "sigterm"), (signal.SIGINT, "sigint")):
        C.append(Case(f"warp_phases_{tag}_mha", "warp", "refuse", lambda fx, d: phases_args(fx, d, "12", out=d / "ct.mha"),
                      f"{tag.upper()} while the phases are written (OUT_phase00.mha's hidden file is there: the set "
                      "appears whole at the end since issue 36, so OUT_phase00.mha itself only appears when all are done)",
                      signal=(sig, ".ct_phase00.mha.*", _no_leftovers)))
        C.append(Case(f"warp_phases_{tag}_dicom", "warp", "refuse",
                      lambda fx, d: phases_args(fx, d, "12", out=d / "4dct"),
                      f"{tag.upper()} once the hidden DICOM folder holds phase00",
                      signal=(sig, ".4dct.*.partial/phase00/CT0001.dcm", _no_leftovers)))
    return C


def stream_case(name, expect, stdin: str, *opts, why="", verify=verify_finite_stdout) -> Case:
    return Case(name, "stream", expect, lambda fx, d: (["stream", "-", *opts], stdin.encode("utf-8", "surrogateescape")),
                why, verify=verify)


def _head(text: str, n: int) -> str:
    """The first ``n`` lines of ``text``."""
    return "".join(text.splitlines(True)[:n])


def _tail(text: str, n: int) -> str:
    """``text`` from its line ``n`` (0-based) on."""
    return "".join(text.splitlines(True)[n:])


def stream_cases() -> list[Case]:
    good = samples_text()  # 300 samples at 25 Hz, one per line
    C = [
        stream_case("stream_samples_pm1e308", "warn", samples_text(amp=lambda t: 1e308 * np.sign(np.sin(2 * np.pi * t / 4) + 1e-9)),
                    why="amplitudes of ±1e308"),
        stream_case("stream_sample_1e308_spike", "warn", _head(good, 200) + "8.0000,1e308\n" + _tail(good, 201),
                    why="one amplitude spike of 1e308 among normal samples (t = 8 s)"),
        stream_case("stream_sample_nan", "warn", _head(good, 200) + "8.0000,nan\n" + _tail(good, 201),
                    why="a NaN amplitude among normal samples (t = 8 s)"),
        stream_case("stream_time_inf", "refuse", _head(good, 200) + "inf,1.0\n", why="time inf"),
        stream_case("stream_time_backwards", "warn", good + "1.0,2.0\n", why="time going back 11 s"),
        stream_case("stream_time_jump_1e9", "warn", good + "1e9,2.0\n1e9,2.1\n", why="time jumping to 1e9 s"),
        stream_case("stream_time_duplicate", "any", _head(good, 100) + _head(good, 100), why="the same timestamps twice"),
        stream_case("stream_garbage_line", "refuse", _head(good, 50) + "hello world\n", why="a line of text"),
        stream_case("stream_nul_bytes", "refuse", _head(good, 50) + "1\x00,2\x00\n", why="NUL bytes"),
        stream_case("stream_non_utf8", "refuse", _head(good, 50) + "1,\udcff\udcfe\n", why="bytes that are not UTF-8"),
        stream_case("stream_huge_line", "refuse", "1" * 5_000_000 + ",2\n", why="a 5 MB line"),
        stream_case("stream_empty", "any", "", why="no sample at all"),
        stream_case("stream_valid_control", "ok", good, why="a 12 s sine (control)"),
    ]
    for opt, v in (("--v-ee-ml", "nan"), ("--v-ee-ml", "-100"), ("--v-ee-ml", "1e308"), ("--tidal-volume-ml", "inf"),
                   ("--tidal-volume-ml", "1e308"), ("--tidal-volume-ml", "nan"), ("--window-s", "nan"), ("--window-s", "1e308"),
                   ("--predict-ms", "inf"), ("--predict-ms", "-1"), ("--predict-ms", "3000")):
        C.append(stream_case(f"stream_{opt[2:].replace('-', '_')}_{v}", "refuse", good, opt, v,
                             why=f"{opt} {v}" + (" (view refuses above 2000)" if v == "3000" else "")))
    C.append(Case("stream_trace_missing", "stream", "refuse", lambda fx, d: ["stream", _p(d / "nope.csv")], "trace file missing"))
    C.append(Case("stream_trace_folder", "stream", "refuse", lambda fx, d: ["stream", _p(d)], "trace is a folder"))
    return C


def view_reset_runner(d: Path, argv: list, timeout: float, env: dict) -> Run:
    """Start the viewer on 127.0.0.1 (port 0), reset 20 connections (RST), stop it with SIGINT."""
    proc = subprocess.Popen(argv, cwd=d, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    LIVE.add(proc)
    url = None
    try:
        line = proc.stdout.readline().decode("utf-8", "replace")
        if " at http://" in line:
            url = line.split(" at ", 1)[1].split()[0]
        if url:
            host, port = url.split("//", 1)[1].split("/", 1)[0].rsplit(":", 1)
            for i in range(20):
                s = socket.create_connection((host, int(port)), timeout=2)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, np.array([1, 0], np.int32).tobytes())
                s.sendall(b"GET /model.glb HTTP/1.1\r\nHost: x\r\n\r\n" if i % 2 else b"GET / HTTP/1.1\r\n")
                time.sleep(0.05)
                s.close()
            time.sleep(1.0)
        _send(proc, signal.SIGINT)
        out, err = proc.communicate(timeout=timeout)
        return Run(proc.returncode, line + _text(out), _text(err))
    except subprocess.TimeoutExpired:
        _kill(proc)
        out, err = proc.communicate()
        return Run(None, _text(out), _text(err), True)
    finally:
        if proc.poll() is None:
            _kill(proc)
        LIVE.discard(proc)


def view_cases() -> list[Case]:
    def v(name, why, *extra, trace=False, model=None):
        def build(fx, d):
            m = model(fx, d) if model else fx.model
            return ["view", _p(m), "--port", "0", *(["--trace", _p(fx.trace)] if trace else []), *extra]
        return Case(name, "view", "refuse", build, why, timeout=30)

    C = [v(f"view_predict_{x}", f"--predict-ms {x} with --trace", "--predict-ms", x, trace=True)
         for x in ("nan", "inf", "-5", "1e9", "2001")]
    C += [v("view_predict_without_trace", "--predict-ms 100 without --trace", "--predict-ms", "100"),
          v("view_port_negative", "--port -1", "--port", "-1"),
          v("view_port_70000", "--port 70000", "--port", "70000"),
          v("view_host_bad", "--host 999.1.1.1", "--host", "999.1.1.1"),
          v("view_model_missing", "model missing", model=lambda fx, d: d / "nope.npz"),
          v("view_model_complex", "complex displacement model",
            model=lambda fx, d: model_variant(fx, d / "m.npz", model_edit("displacement", lambda a: a.astype(complex)))),
          v("view_trace_missing", "--trace missing", "--trace", "nope.csv"),
          v("view_trace_1e308", "--trace of ±1e308 amplitudes", "--trace", "big.csv"),
          v("view_glb_with_trace", "a .glb with --trace", trace=True, model=lambda fx, d: (d / "m.glb").write_bytes(b"glTF") and d / "m.glb")]
    big = C[-2]
    base = big.build
    big.build = lambda fx, d, b=base: (d / "big.csv").write_text(
        marker_csv(amp=lambda t: 1e308 * np.sign(np.sin(t) + 1e-9))) and b(fx, d)
    C.append(Case("view_connection_resets", "view", "ok", lambda fx, d: ["view", _p(fx.model), "--port", "0"],
                  "20 connections reset by the client, then Ctrl-C", runner=view_reset_runner, timeout=60))
    return C


def copd_args(data, d, *extra):
    return ["validate", "copd", "--data", _p(data), "--out", _p(d / "out"), *extra]


def copd_fake(d: Path, complete=(1,), partial=None) -> Path:
    """A data folder holding the four DIR-Lab file names (empty files: only existence is read)."""
    data = d / "data"
    data.mkdir(exist_ok=True)
    for n in complete:
        for kind in ("exp_mask.nii.gz", "insp_mask.nii.gz", "exp_landmarks.txt", "insp_landmarks.txt"):
            (data / f"copd{n}_{kind}").write_bytes(b"")
    for n, kinds in (partial or {}).items():
        for kind in kinds:
            (data / f"copd{n}_{kind}").write_bytes(b"")
    return data


def _lungs_have_digest(rel: str, d: Path) -> bool:
    """After a signal, ``validate copd`` may leave its output folder, and a lung folder OUT/copdN/<side>
    only with its ``metrics.json`` holding the settings digest (a finished, resumable lung); no hidden
    temporary anywhere."""
    parts = Path(rel).parts
    if parts[0] != "out" or any(p.startswith(".") for p in parts):
        return False
    if len(parts) <= 2:
        return (d / rel).is_dir() or parts[-1] in ("metrics.json", "report.html")
    try:
        return "settings_digest" in json.loads((d / Path(*parts[:3]) / "metrics.json").read_text())
    except (OSError, ValueError):
        return False


def copd_cases() -> list[Case]:
    M = "--manifest-only"
    C = [
        Case("copd_manifest_incomplete_case", "validate copd", "warn",
             lambda fx, d: copd_args(copd_fake(d, (1,), {2: ("exp_mask.nii.gz", "insp_mask.nii.gz", "exp_landmarks.txt")}), d, M),
             "copd2 lacks its inspiration landmarks: dropped without a word?"),
        Case("copd_manifest_only_incomplete", "validate copd", "refuse",
             lambda fx, d: copd_args(copd_fake(d, (), {3: ("exp_mask.nii.gz",)}), d, M), "the only case incomplete"),
        Case("copd_manifest_empty_folder", "validate copd", "refuse", lambda fx, d: copd_args(copd_fake(d, ()), d, M),
             "no case at all"),
        Case("copd_manifest_data_is_file", "validate copd", "refuse",
             lambda fx, d: _w(d / "f", "x") or copd_args(d / "f", d, M), "--data a regular file"),
        Case("copd_manifest_out_under_file", "validate copd", "refuse",
             lambda fx, d: _w(d / "f", "x") or [*copd_args(copd_fake(d), d, M)[:5], _p(d / "f" / "o"), M],
             "--out under a regular file"),
        Case("copd_manifest_out_is_file", "validate copd", "refuse",
             lambda fx, d: _w(d / "out", "x") or copd_args(copd_fake(d), d, M), "--out an existing file"),
        Case("copd_manifest_out_is_data", "validate copd", "any",
             lambda fx, d: [*copd_args(copd_fake(d), d, M)[:5], _p(d / "data"), M], "--out is the data folder"),
        Case("copd_manifest_case_name_padded", "validate copd", "any",
             lambda fx, d: copd_args(copd_fake(d, (1, 10)), d, M, "--cases", "01"), "--cases 01 (copd1 and copd10 there)"),
        Case("copd_manifest_valid_control", "validate copd", "ok", lambda fx, d: copd_args(copd_fake(d, (1, 2)), d, M),
             "two complete cases (control)"),
    ]
    for v in ("nan", "-1", "1e9", "1,1", "", "1;2"):
        C.append(Case(f"copd_manifest_cases_{v or 'empty'}".replace(",", "_").replace(";", "_"), "validate copd", "refuse",
                      lambda fx, d, x=v: copd_args(copd_fake(d, (1,)), d, M, "--cases", x), f"--cases {v!r}"))
    C.append(Case("copd_missing_data_no_out", "validate copd", "refuse", lambda fx, d: copd_args(d / "nope", d),
                  "full run on a missing data folder"))
    C.append(Case("copd_evaluations_zero", "validate copd", "refuse",
                  lambda fx, d: copd_args(fx.copd, d, "--evaluations", "0"), "--evaluations 0"))
    for sig, tag in ((signal.SIGTERM, "sigterm"), (signal.SIGINT, "sigint")):
        C.append(Case(f"copd_{tag}_during_fit", "validate copd", "refuse",
                      lambda fx, d: copd_args(fx.copd, d, "--evaluations", "3"),
                      f"{tag.upper()} once the first lung folder holds a file",
                      signal=(sig, "out/copd1/left/*", _lungs_have_digest), timeout=180))
    return C


def all_cases() -> list[Case]:
    return track_cases() + fit_cases() + dvf_cases() + model_cases() + warp_cases() + stream_cases() + view_cases() + copd_cases()


#: Variants of a class another case already covers (other values of the same option, near-duplicate
#: files): run with ``--all`` or when named by ``--only``; the default set stays within ~10 minutes.
EXTRA = frozenset("""
track_volume_inf track_volume_-3000 track_volume_0 track_phases_-2 track_phases_1000000000000
track_roi_duplicate_case track_out_is_file track_contour_one_nan_point track_contour_single_point_all
track_contours_dense_400 track_ct_iop_nan track_ct_ipp_missing track_out_rtstruct_is_ct_slice
dvf_volume_inf dvf_volume_-1 dvf_volume_0 dvf_node_mm_0 dvf_node_mm_-4 dvf_ref_spacing_negative dvf_ref_offset_inf
dvf_ref_direction_nan dvf_scan_huge
model_int_faces_as_float model_volume_ee_negative model_gravity_zero model_provenance_list model_no_lungs
model_unit_ml_nan model_lungs_missing_lung
stream_v_ee_ml_-100 stream_v_ee_ml_1e308 stream_tidal_volume_ml_nan stream_window_s_1e308 stream_predict_ms_-1
stream_time_duplicate stream_trace_folder stream_non_utf8
warp_phases_-3 warp_phases_101 warp_node_mm_nan warp_volume_ml_nan warp_image_inf_voxels
view_predict_-5 view_predict_1e9 view_port_negative view_model_missing
copd_manifest_cases_-1 copd_manifest_cases_empty copd_manifest_cases_1_2 copd_manifest_case_name_padded
fit4d_option_folds_-1 fit4d_two_studies fit4d_mixed_pixel_spacing fit4d_iop_zero
track_contour_self_intersecting track_contour_huge_polygon track_ct_iop_parallel track_out_rtstruct_is_model
track_phases_curve_nan track_ct_is_the_rtstruct track_rtstruct_truncated track_contour_inf
dvf_ref_spacing_1e308 dvf_ref_2d dvf_node_mm_nan dvf_volume_1e308
model_complex_vertices model_constants_nan model_schema_version_99
stream_nul_bytes stream_window_s_nan warp_curve_flat warp_image_nan_voxels view_host_bad view_trace_missing
copd_manifest_out_is_data copd_manifest_cases_1_1 fit4d_rescale_nan fit4d_option_volumes_nan fit_missing_input
""".split())


# --- running ---------------------------------------------------------------------------------------

#: Runs under way (killed with their process groups when the probe itself is stopped)
LIVE: set = set()


def _kill(proc) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def snapshot(folder: Path) -> dict:
    """{relative path: (size, mtime_ns) or 'dir'} of everything under ``folder`` (hidden names too)."""
    out = {}
    for base, dirs, files in os.walk(folder):
        for name in dirs:
            out[os.path.relpath(os.path.join(base, name), folder)] = "dir"
        for name in files:
            p = os.path.join(base, name)
            try:
                st = os.lstat(p)
                out[os.path.relpath(p, folder)] = (st.st_size, st.st_mtime_ns)
            except OSError:
                pass
    return out


def _matches(folder: Path, pattern: str) -> bool:
    for base, dirs, files in os.walk(folder):
        for name in dirs + files:
            if fnmatch.fnmatch(os.path.relpath(os.path.join(base, name), folder), pattern):
                return True
    return False


def child_env(root: Path) -> dict:
    env = dict(os.environ)
    src = str(root / "src")
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    for key, sub in (("TMPDIR", "tmp"), ("MPLCONFIGDIR", "mpl"), ("XDG_CACHE_HOME", "cache")):
        (root / sub).mkdir(exist_ok=True)
        env[key] = str(root / sub)
    env.update(PYTHONDONTWRITEBYTECODE="1", PYTHONNOUSERSITE="1", MPLBACKEND="Agg", LC_ALL=env.get("LC_ALL", "C.UTF-8"))
    env.pop("LUNGDEFORM_DATA", None)
    return env


def cap_memory(pid: int, memory_gib: float) -> None:
    """Cap the address space of a run just started (no ``preexec_fn``: the probe runs cases in threads);
    a run allocating past it gets a MemoryError instead of exhausting a shared machine."""
    cap = int(memory_gib * 2 ** 30)
    try:
        resource.prlimit(pid, resource.RLIMIT_AS, (cap, cap))
    except (ProcessLookupError, PermissionError, ValueError):
        pass


def _text(b: bytes) -> str:
    return b.decode("utf-8", "replace")


def _send(proc, sig) -> None:
    """SIGINT as Ctrl-C sends it (to the whole process group); SIGTERM as ``kill PID`` does."""
    if sig == signal.SIGINT:
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)


def run_process(case: Case, d: Path, argv: list, stdin: bytes | None, limit: float, env: dict,
                settings: Settings) -> Run:
    """Run ``argv`` in ``d``; for a signal case, send the signal once its trigger file appears."""
    proc = subprocess.Popen(argv, cwd=d, env=env, stdin=subprocess.PIPE if stdin is not None else subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    cap_memory(proc.pid, settings.memory_gib)
    LIVE.add(proc)
    signalled, t0 = False, time.monotonic()
    try:
        if case.signal is None:
            out, err = proc.communicate(stdin, timeout=limit)
            return Run(proc.returncode, _text(out), _text(err))
        sig, pattern, _allowed = case.signal
        while proc.poll() is None and time.monotonic() - t0 < limit:
            if _matches(d, pattern):
                time.sleep(0.1)
                _send(proc, sig)
                signalled = True
                break
            time.sleep(0.05)
        out, err = proc.communicate(timeout=max(5.0, limit - (time.monotonic() - t0)))
        return Run(proc.returncode, _text(out), _text(err), False, signalled)
    except subprocess.TimeoutExpired:
        _kill(proc)
        out, err = proc.communicate()
        return Run(None, _text(out), _text(err), True, signalled)
    finally:
        if proc.poll() is None:
            _kill(proc)
        LIVE.discard(proc)


def _names_something(text: str, argv: list) -> bool:
    """Whether an error names a file or an option of the command line (or stdin): an option as given,
    a path as given, or a file's name as a whole word (``ct`` is not named by "structure")."""
    tokens = [a for a in argv[1:] if a.startswith("--")]
    paths = [a for a in argv[1:] if not a.startswith("-") and (os.sep in a or "." in a)]
    names = {Path(a).name for a in paths if Path(a).name}
    return (any(t in text for t in tokens) or any(p in text for p in paths) or "stdin" in text.lower()
            or any(re.search(rf"(?<![\w.-]){re.escape(n)}(?![\w-])", text) for n in names))


#: Warnings that say nothing about the input (the probe's fits run on a small evaluation budget)
UNRELATED_WARNINGS = ("did not converge",)


def _warned(stderr: str) -> bool:
    """Whether stderr holds a ``warning``/``note`` line about the input."""
    return any(ln.strip().lower().startswith(("warning", "note")) and not any(u in ln for u in UNRELATED_WARNINGS)
               for ln in stderr.splitlines())


def _after_signal(case: Case, run: Run, diff: dict, d: Path) -> tuple[str, str]:
    allowed = case.signal[2]
    left = [k for k in diff["new"] if not allowed(k, d)] + diff["changed"] + diff["gone"]
    if left:
        return "partial", f"after the signal: {left[:4]}"
    if run.rc in REFUSAL_CODES or run.rc in (-signal.SIGTERM, 128 + signal.SIGTERM):
        return "clean", f"exit {run.rc}, nothing half-written"
    if run.rc == 0:  # it finished as the signal came, its outputs whole
        return "clean", "exit 0: finished as the signal came, nothing half-written"
    return "traceback", f"exit {run.rc} after the signal"


def _success(case: Case, run: Run, diff: dict, d: Path) -> tuple[str, str]:
    note = " (finished before the signal)" if case.signal is not None else ""
    warned = _warned(run.stderr)
    if diff["changed"] or diff["gone"]:
        return "silent", f"exit 0 but an input changed: {(diff['changed'] + diff['gone'])[:3]}{note}"
    if case.expect == "refuse":
        return "silent", f"exit 0 on an input that should be refused{' (with a warning)' if warned else ''}{note}"
    if case.expect == "warn" and not warned:
        return "silent", f"exit 0 without a warning on stderr{note}"
    if case.verify is not None:
        try:
            why = case.verify(d, run.stdout)
        except Exception as exc:  # noqa: BLE001 - an output that cannot even be read back is the finding
            why = f"output not readable: {type(exc).__name__}: {str(exc)[:200]}"
        if why:
            return "silent", why
    return "clean", f"exit 0{' with a warning' if warned else ''}{note}"


def _refusal(case: Case, run: Run, diff: dict, argv: list) -> tuple[str, str]:
    left = diff["new"] + diff["changed"] + diff["gone"]
    if left:
        return "partial", f"exit {run.rc} but left {left[:4]}"
    if case.expect == "ok":
        return "refused", f"a valid input refused (exit {run.rc})"
    if "Usage:" in run.stderr:  # click's own usage error: several lines, naming the option
        ok = _names_something(run.stderr, argv) or "Invalid value" in run.stderr
        return ("clean", "usage error") if ok else ("unclear", "usage error naming no option")
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    if len(lines) != 1:
        return "unclear", f"{len(lines)} stderr lines"
    if not _names_something(lines[0], argv):
        return "unclear", "the error names no file or option"
    return "clean", f"exit {run.rc}"


def classify(case: Case, run: Run, before: dict, after: dict, d: Path, argv: list) -> tuple[str, str]:
    """(outcome, reason) of one run, from the case folder's snapshots before and after (see the
    module docstring for the outcomes)."""
    diff = {"new": sorted(set(after) - set(before)), "gone": sorted(set(before) - set(after)),
            "changed": sorted(k for k in before if k in after and before[k] != after[k] and before[k] != "dir")}
    if run.timed_out:
        also = " (stderr holds a Traceback)" if "Traceback" in run.stderr else ""
        return "hang", f"killed after {case.timeout or 'the time-out'} s{also}"
    if "Traceback" in run.stderr:  # its last line that says something (socketserver ends with dashes)
        last = [ln for ln in run.stderr.splitlines() if any(ch.isalnum() for ch in ln)][-1:] or [""]
        return "traceback", last[0].strip()[:300]
    if case.signal is not None and run.signalled:
        return _after_signal(case, run, diff, d)
    if run.rc == 0:
        return _success(case, run, diff, d)
    if run.rc in REFUSAL_CODES:
        return _refusal(case, run, diff, argv)
    return "traceback", f"undocumented exit code {run.rc}"


def _probe_error(case: Case, text: str) -> Result:
    return Result(case.name, case.command, case.expect, "probe-error", None, text[:400], 0.0, why=case.why)


def run_case(case: Case, fx: Fixtures, root: Path, settings: Settings) -> Result:
    """Build the case's inputs in its own folder, run it, classify it."""
    d = root / "cases" / case.name
    d.mkdir(parents=True)
    try:
        built = case.build(fx, d)
    except Exception as exc:  # noqa: BLE001 - a probe bug: reported, never hidden
        return _probe_error(case, f"{type(exc).__name__}: {exc}")
    args, stdin = built if isinstance(built, tuple) else (built, None)
    if not (isinstance(args, list) and all(isinstance(a, str) for a in args)):
        return _probe_error(case, f"bad arguments {args!r}")
    argv = [sys.executable, "-m", "lungdeform", *args]
    env, limit = child_env(root), case.timeout or settings.timeout
    before, t0 = snapshot(d), time.monotonic()
    if case.runner is not None:
        run = case.runner(d, argv, limit, env)
    else:
        run = run_process(case, d, argv, stdin, limit, env, settings)
    seconds = time.monotonic() - t0
    outcome, reason = classify(case, run, before, snapshot(d), d, argv)
    logs = root / "logs"  # beside the case folders, so that the snapshots do not see them (kept with --keep)
    logs.mkdir(exist_ok=True)
    (logs / f"{case.name}.out").write_text(run.stdout, encoding="utf-8")
    (logs / f"{case.name}.err").write_text(run.stderr, encoding="utf-8")
    first = next((ln.strip() for ln in run.stderr.splitlines() if ln.strip()), "")
    shown = shlex.join(["lungdeform", *args]).replace(str(root), "$PROBE")
    return Result(case.name, case.command, case.expect, outcome, run.rc, first.replace(str(root), "$PROBE")[:400],
                  round(seconds, 2), shown[:600], reason.replace(str(root), "$PROBE"), case.why, run.stderr)


def select(cases: list[Case], only: list[str] | None, everything: bool = False) -> list[Case]:
    """The cases named by ``only`` (substrings), else every case but :data:`EXTRA` (all with ``everything``)."""
    if only:
        return [c for c in cases if any(s in c.name for s in only)]
    return [c for c in cases if everything or c.name not in EXTRA]


def stage_package(root: Path) -> Path:
    """A compiled copy of this checkout's package under ``root/src`` (the runs import it from there:
    no bytecode is written into the checkout, and no run recompiles it)."""
    import compileall

    dst = root / "src"
    shutil.copytree(REPO / "src" / "lungdeform", dst / "lungdeform", ignore=shutil.ignore_patterns("__pycache__"))
    compileall.compile_dir(dst, quiet=1)
    return dst


def run_probe(root: Path, settings: Settings | None = None, only=None, everything: bool = False,
              progress: Callable[[Result], None] | None = None) -> list[Result]:
    """Build the fixtures under ``root`` and run the selected cases; the results in case order."""
    settings = settings or Settings()
    # a probe started in the background of a shell ignores SIGINT, and so would every run it starts
    # (an ignored signal stays ignored across exec): the runs must get Python's Ctrl-C handling
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    cases = select(all_cases(), only, everything)
    names = [c.name for c in cases]
    assert len(names) == len(set(names)), "case names must be unique"
    stage_package(root)
    fx = build_fixtures(root / "shared", settings.seed)
    shared_before = snapshot(fx.root)

    def one(case):
        r = run_case(case, fx, root, settings)
        if progress is not None:
            progress(r)
        return r

    pool = ThreadPoolExecutor(max(1, settings.workers))
    try:
        results = list(pool.map(one, cases))
    except BaseException:  # Ctrl-C or SIGTERM of the probe: no run outlives it
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in list(LIVE):
            _kill(proc)
        pool.shutdown(wait=True)  # the cases under way end at once, their runs killed
        raise
    pool.shutdown()
    if snapshot(fx.root) != shared_before:
        raise RuntimeError(f"a case changed the shared inputs under {fx.root}: a probe bug")
    return results


def summary_table(results: list[Result]) -> str:
    """Counts per outcome, per command and in all."""
    outcomes = list(OUTCOMES) + (["probe-error"] if any(r.outcome == "probe-error" for r in results) else [])
    commands = sorted({r.command for r in results})
    width = max(len(c) for c in commands + ["command", "all"])
    lines = [f"{'command':<{width}} " + " ".join(f"{o:>9}" for o in outcomes) + f" {'total':>6}"]
    for c in commands + ["all"]:
        rs = [r for r in results if c in ("all", r.command)]
        counts = " ".join(f"{sum(r.outcome == o for r in rs):>9}" for o in outcomes)
        lines.append(f"{c:<{width}} {counts} {len(rs):>6}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write the per-case results here")
    ap.add_argument("--only", action="append", help="run the cases whose name holds this (repeatable)")
    ap.add_argument("--all", action="store_true", help="also the variants in EXTRA (about twice as long)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds per case before it counts as a hang")
    ap.add_argument("--memory-gib", type=float, default=6.0, help="address-space cap of each run (GiB)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    ap.add_argument("--list", action="store_true", help="print the case names and exit")
    a = ap.parse_args(argv)
    if a.list:
        for c in select(all_cases(), a.only, a.all):
            print(f"{c.name:42s} {c.command:14s} {c.expect:7s} {c.why}")
        return 0
    settings = Settings(a.timeout, a.memory_gib, a.seed, a.workers)
    root = Path(tempfile.mkdtemp(prefix="lungdeform-probe-"))
    t0 = time.monotonic()

    def progress(r: Result) -> None:
        mark = "" if r.outcome == "clean" else "  <--"
        print(f"{r.outcome:10s} {r.seconds:6.1f}s {r.name}{mark}", flush=True)

    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM stops the probe as Ctrl-C does
    try:
        results = run_probe(root, settings, a.only, a.all, progress)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    finally:
        if a.keep:
            print(f"kept {root}")
        else:
            shutil.rmtree(root, ignore_errors=True)
    print()
    print(summary_table(results))
    bad = [r for r in results if r.outcome != "clean"]
    if bad:
        print("\nnot clean:")
        for r in bad:
            print(f"  {r.name} [{r.outcome}] {r.reason[:160]} | {r.stderr_first_line[:160]}")
    print(f"\n{len(results)} case(s) in {time.monotonic() - t0:.0f} s")
    if a.json:
        outcomes = sorted({r.outcome for r in results} | set(OUTCOMES), key=lambda o: (o not in OUTCOMES, o))
        per = {c: {o: sum(r.outcome == o for r in results if r.command == c) for o in outcomes}
               for c in sorted({r.command for r in results})}
        doc = {"seed": a.seed, "timeout_s": a.timeout, "seconds": round(time.monotonic() - t0),
               "counts": {o: sum(r.outcome == o for r in results) for o in outcomes}, "per_command": per,
               "cases": [{k: v for k, v in r.__dict__.items() if k != "stderr"} for r in results]}
        a.json.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
