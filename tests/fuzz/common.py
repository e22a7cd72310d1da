"""What every fuzz harness shares: the readers, the rule, the seeds, the crash record.

The rule checked: the only exceptions a reader may raise are the package's own documented errors
(:class:`lungdeform.errors.LungdeformError` and subclasses); a workflow harness (``track_rtstruct``)
also asserts what it writes is right (an AssertionError is a crash too). Anything else escaping a reader
(ValueError, IndexError, struct.error, UnicodeDecodeError, OverflowError, MemoryError, ...) is a
crash, recorded once per (exception type, innermost ``lungdeform`` frame) with the input that
caused it as a reproducer file.

Each ``fuzz_<reader>.py`` is a small script with ``TestOneInput(data)`` calling
:func:`test_one_input`; run as a script it fuzzes with atheris (coverage guided) when installed,
else with :func:`mutate_loop` (seeded random mutation). ``tests/fuzz/run.py`` runs them all.
"""

from __future__ import annotations

import argparse
import atexit
import hashlib
import importlib
import json
import os
import random
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np

import lungdeform
from lungdeform.errors import LungdeformError

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = str(Path(lungdeform.__file__).resolve().parent)


# =========================================================================== readers
def _mesh(path):
    from lungdeform.io.meshfile import read_mesh

    return read_mesh(path)


def _image(path):
    from lungdeform.io.image import read_image

    return read_image(path)


def _dicom(path):
    """One slice of a small 4-D CT (:func:`_dicom_series`, the fuzzed bytes), read by one of the two
    DICOM readers, chosen by the input's first byte (a byte of the preamble, which no reader uses;
    one reader per input halves the cost of an execution, GDCM reading a whole series): odd, as its
    series by :func:`read_image`; even, the whole folder by the 4-D CT phase sorter."""
    from lungdeform.io.dicom.fourdct import read_phases
    from lungdeform.io.image import read_image

    with open(path, "rb") as fh:
        first = fh.read(1)
    if first and first[0] & 1:
        return read_image(path)
    return read_phases(Path(path).parent)


def _fourdct_folder(path):
    """The table of :mod:`tests.fuzz.fourdct_folder` (the fuzzed bytes) written as a 4-D CT folder
    beside it, read by the 4-D CT phase sorter."""
    from lungdeform.io.dicom.fourdct import read_phases
    from tests.fuzz.fourdct_folder import write_folder

    folder = Path(path).parent / "fourdct"
    write_folder(Path(path).read_bytes(), folder)
    return read_phases(folder)


def _model(path):
    from lungdeform.io.modelfile import load_model

    return load_model(path)


def _curve(path):
    from lungdeform.playback.schedule import read_volume_csv

    return read_volume_csv(path)


def _trace(path):
    from lungdeform.breathing.trace import read_trace

    return read_trace(path)


def _elastix(path):
    from lungdeform.io.landmarks import read_elastix_points

    return read_elastix_points(path, spacing=(1.0, 1.0, 2.5), origin=(0.0, 0.0, 0.0))


def _track_points(path):
    from lungdeform.playback.trajectory import read_points

    return read_points(path)


def _manifest(path):
    from lungdeform.cohort.manifest import read_manifest

    return read_manifest(path)


def _spacing(path):
    from lungdeform.validate.dirlab_files import read_voxel_spacing

    return read_voxel_spacing(path)


def _dirlab_points(path):
    from lungdeform.io.landmarks import read_dirlab_points

    return read_dirlab_points(path, (0.97, 0.97, 2.5), shape=(256, 256, 94))


def _rtstruct(path):
    from lungdeform.io.dicom.rtstruct import read_rtstruct

    return read_rtstruct(path)


#: The fixed parts of the track_rtstruct workflow (:func:`_track_fixture`), made once per process
_TRACK: dict = {}
#: The slice of the reference CT an input with an odd first byte replaces (see :func:`_track_rtstruct`)
TRACK_CT_SLICE = "slice003.dcm"


def _track_fixture() -> dict:
    """A one-lung model (:func:`_model_seed`'s lung), a 10-slice reference CT of 2 mm slices around
    its centre (tests/io/dicom_support.py, fixed UIDs) and a GTV drawn on it (a 2.5 mm sphere): made
    once, in a folder removed at exit."""
    if not _TRACK:
        import trimesh

        from lungdeform.io.dicom.rtstruct import read_ct_series, write_rtstruct
        from lungdeform.io.modelfile import load_model
        from lungdeform.playback.structures import read_structure
        from tests.io.dicom_support import write_ct_series

        folder = Path(tempfile.mkdtemp(prefix="ldfuzz-track-"))
        atexit.register(shutil.rmtree, folder, True)
        ct = write_ct_series(folder / "ct", shape=(10, 8, 8), origin=(83.0, 13.0, -160.0))
        s = trimesh.creation.icosphere(1, radius=2.5)
        write_rtstruct(folder / "gtv.dcm", read_ct_series(ct), [("GTV", s.vertices + [90.0, 20.0, -150.0], s.faces, "GTV")])
        model = _model_seed(folder)[0]
        _TRACK.update(ct=ct, gtv=folder / "gtv.dcm", model=load_model(model),
                      slice=(ct / TRACK_CT_SLICE).read_bytes())
        read_structure(_TRACK["gtv"], "GTV")  # warm: the first call imports what the workflow needs
    return _TRACK


def _track_rtstruct(path):
    """The library path of ``track --rtstruct … --out-rtstruct … --reference-ct`` on the fixed
    model and CT of :func:`_track_fixture`, the input chosen by its first byte (a preamble byte no
    reader uses): even, the input is the RTSTRUCT (structure GTV); odd, it replaces one slice of the
    reference CT, and the fixture's GTV is tracked. What it writes is checked: the structure's frame
    of reference is the CT's, every ROI has contours, every contour lies on a slice of the CT."""
    import io

    from lungdeform.io.dicom.rtstruct import build_rtstruct, check_structure_on_ct, read_ct_series
    from lungdeform.playback.structures import moved_surfaces, read_structure
    from lungdeform.playback.trajectory import place_points

    fx = _track_fixture()
    with open(path, "rb") as fh:
        first = fh.read(1)
    as_ct = bool(first and first[0] & 1)
    if as_ct:
        shutil.copyfile(path, fx["ct"] / TRACK_CT_SLICE)
    try:
        rs = fx["gtv"] if as_ct else path
        tracked = read_structure(rs, "GTV")
        ct = read_ct_series(fx["ct"])
        check_structure_on_ct(tracked.roi, ct, str(rs))
        place_points(fx["model"], tracked.points, source=str(rs))
        surfaces = moved_surfaces(fx["model"], tracked, np.array([0.0, 40.0]), ["a", "b"], source=str(rs))
        ds, counts = build_rtstruct(ct, surfaces, label="GTV moved")
        ds.save_as(io.BytesIO(), enforce_file_format=True)
    finally:
        if as_ct:
            (fx["ct"] / TRACK_CT_SLICE).write_bytes(fx["slice"])
    _check_written(ds, counts, ct, tracked)


def _check_written(ds, counts: dict, ct, tracked) -> None:
    """The invariants of a written structure set (an AssertionError is a crash: a wrong answer)."""
    assert tracked.roi.frame_uid == str(ct.header.FrameOfReferenceUID), "structure written on another frame"
    assert all(counts.values()), f"an ROI without contours: {counts}"
    levels = ct.levels
    for rc in ds.ROIContourSequence:
        for c in rc.ContourSequence:
            h = np.asarray(c.ContourData, float).reshape(-1, 3) @ ct.normal
            assert np.abs(levels - h.mean()).min() < 0.01 and np.ptp(h) < 0.01, "a contour off the CT's slices"


#: reader name -> (file suffix, function of the path)
READERS: dict[str, tuple[str, Callable]] = {
    "mesh_stl": (".stl", _mesh), "mesh_obj": (".obj", _mesh), "mesh_ply": (".ply", _mesh),
    "mesh_vtk": (".vtk", _mesh), "mesh_vtp": (".vtp", _mesh), "mesh_off": (".off", _mesh),
    "mesh_glb": (".glb", _mesh),
    "image_nii": (".nii.gz", _image), "image_mha": (".mha", _image), "image_nrrd": (".nrrd", _image),
    "image_dicom": (".dcm", _dicom),
    "fourdct_folder": (".txt", _fourdct_folder),
    "model": (".npz", _model), "curve": (".csv", _curve),
    "trace_vxp": (".vxp", _trace), "trace_csv": (".csv", _trace),
    "points_elastix": (".txt", _elastix), "points_track": (".csv", _track_points),
    "manifest": (".csv", _manifest),
    "dirlab_spacing": (".csv", _spacing), "dirlab_points": (".txt", _dirlab_points),
    "rtstruct": (".dcm", _rtstruct), "track_rtstruct": (".dcm", _track_rtstruct),
}


READER_MODULES = ("lungdeform.io.meshfile", "lungdeform.io.vtk", "lungdeform.io.image", "lungdeform.io.dicom.guard",
                  "lungdeform.io.dicom.series", "lungdeform.io.dicom.fourdct",
                  "lungdeform.io.modelfile",
                  "lungdeform.playback.schedule", "lungdeform.breathing.trace", "lungdeform.io.landmarks",
                  "lungdeform.playback.trajectory", "lungdeform.cohort.manifest", "lungdeform.validate.dirlab_files",
                  "lungdeform.io.dicom.rtstruct", "lungdeform.geometry.contours", "lungdeform.playback.structures")


# =========================================================================== seeds
def _tiny_surface():
    from lungdeform.geometry.mesh import icosphere

    s = icosphere(1, 1.0)
    return s.vertices * np.array([45.0, 70.0, 110.0]) + np.array([90.0, 20.0, -150.0]), s.faces


def _mesh_seed(folder: Path, suffix: str) -> list[Path]:
    from lungdeform.io.meshfile import write_mesh

    v, f = _tiny_surface()
    if suffix == ".glb":
        import trimesh

        path = folder / "tiny.glb"
        path.write_bytes(trimesh.Trimesh(v, f, process=False).export(file_type="glb"))
        return [path]
    out = [write_mesh(folder / f"tiny{suffix}", v, f)]
    if suffix == ".ply":
        out += sorted((ROOT / "src" / "lungdeform" / "data").glob("*.ply"))[:1]
    if suffix == ".stl":  # the ASCII variant too
        tri = v[f]
        rows = ["solid t"] + ["facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {a} {b} {c}\n" for a, b, c in t)
                              + "endloop\nendfacet" for t in tri[:8]] + ["endsolid t"]
        (folder / "ascii.stl").write_text("\n".join(rows) + "\n")
        out.append(folder / "ascii.stl")
    return out


def _image_seed(folder: Path, suffix: str) -> list[Path]:
    import SimpleITK as sitk

    arr = np.zeros((4, 5, 6), np.uint8)
    arr[1:3, 1:4, 1:5] = 1
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((0.8, 0.8, 2.5))
    img.SetOrigin((-100.0, -120.0, -200.0))
    path = folder / f"mask{suffix}"
    sitk.WriteImage(img, str(path), False)  # uncompressed: the header is what is fuzzed
    return [path]


#: The fuzzed slice of :func:`_dicom_series`: the last slice of its second phase.
DICOM_INPUT = "p1_1.dcm"


def _dicom_series(folder: Path) -> list[Path]:
    """A tiny 4-D CT of two phases (series "CT 0%" and "CT 10%", 2 slices of 6 × 5 int16 voxels each,
    with TemporalPositionIndex too) written by SimpleITK into ``folder``; its files."""
    import SimpleITK as sitk

    folder.mkdir(parents=True, exist_ok=True)
    w = sitk.ImageFileWriter()
    w.KeepOriginalImageUIDOn()
    files = []
    for phase in range(2):
        uid = f"1.2.826.0.1.3680043.2.1125.9.{phase + 1}"
        for n in range(2):
            arr = (np.arange(30, dtype=np.int16).reshape(1, 5, 6) * 10 - 1000 + 100 * phase)
            im = sitk.GetImageFromArray(arr)
            for tag, value in {"0008|0060": "CT", "0020|000e": uid, "0020|000d": "1.2.826.0.1.3680043.2.1125.9",
                               "0008|0018": f"{uid}.{n + 1}", "0020|0013": str(n + 1), "0008|103e": f"CT {10 * phase}%",
                               "0020|9128": str(phase + 1), "0020|0032": f"-10\\-8\\{2.5 * n}",
                               "0020|0037": "1\\0\\0\\0\\1\\0", "0028|0030": "0.8\\0.8",
                               "0018|0050": "2.5"}.items():
                im.SetMetaData(tag, value)
            files.append(folder / f"p{phase}_{n}.dcm")
            w.SetFileName(str(files[-1]))
            w.Execute(im)
    return files


def _dicom_companions(folder: Path) -> None:
    """The slices of :func:`_dicom_series` beside the fuzzed one (which the input file replaces)."""
    _dicom_series(folder)
    (folder / DICOM_INPUT).unlink()


def _model_seed(folder: Path) -> list[Path]:
    from lungdeform.geometry.mesh import Surface
    from lungdeform.io.modelfile import save_model
    from lungdeform.model.lung import Model, build_lung

    v, f = _tiny_surface()
    lung = build_lung(Surface(v, f, "left"), "left")
    return [save_model(folder / "model.npz", Model({"left": lung}, {"source": "fuzz seed"}))]


def _text_seeds(name: str) -> dict[str, str]:
    t = np.arange(0.0, 8.0, 0.2)
    vol = 250 * (1 - np.cos(2 * np.pi * t / 4)) + 2500
    vxp = ["[Header]", "CRC=1", "Version=1.6", "Data_layout=amplitude,phase,timestamp,validflag,ttlin,mark,ttlout",
           "Samples_per_second=25", "Scale_factor=10.0", "[Data]"]
    vxp += [f"{np.sin(x):.4f},0,{1000 * x:.0f},0,1,{'P' if i % 20 == 0 else ''},0" for i, x in enumerate(t)]
    marker = ['"Frame";"Timestamp";"x";"y";"z"'] + [
        f"{6 * i};{1000 * x:g};{-396.9 + 3 * np.sin(x):.3f};5,1;{85.6 - 10 * np.sin(x):.3f}".replace(".", ",")
        for i, x in enumerate(t)] + ["0;0;0;0;0"]
    return {
        "curve": "t_s,volume_ml\n" + "".join(f"{a:g},{b:.2f}\n" for a, b in zip(t, vol)),
        "trace_vxp": "\r\n".join(vxp) + "\r\n",
        "trace_csv": "\r\n".join(marker) + "\r\n",
        "points_elastix": "point\n3\n1.5 2.5 -3.0\n10 20 30\n-4.25 0 7\n",
        "points_track": "x_mm,y_mm,z_mm,label\n90,20,-150,a\n95.5,25,-140,b\n",
        "manifest": ("subject,side,volume_ml,path,landmarks\nP01,right,2310,P01/ee_right.ply,P01/ee.pts\n"
                     "P01,right,2905,P01/ei_right.ply,P01/ei.pts\nP02,both,,P02/ct_exhale.nii.gz\n"
                     "P02,both,,P02/ct_inhale.nii.gz\n"),
        "dirlab_spacing": ("case,dim_x,dim_y,dim_z,spacing_x_mm,spacing_y_mm,spacing_z_mm\n"
                           "1,256,256,94,0.97,0.97,2.5\n2,256,256,112,1.16,1.16,2.5\n"),
        "dirlab_points": "10 20 30\n100.5 200 40\n1 1 1\n",
    }.get(name, "")


def _manifest_files(folder: Path) -> None:
    """The files the seed manifest names (only their existence is read)."""
    for rel in ("P01/ee_right.ply", "P01/ee.pts", "P01/ei_right.ply", "P01/ei.pts",
                "P02/ct_exhale.nii.gz", "P02/ct_inhale.nii.gz"):
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(b"x")


def _rtstruct_seed(folder: Path) -> list[Path]:
    """A two-ROI structure set on a 6-slice synthetic CT series (tests/io/dicom_support.py)."""
    import trimesh

    from lungdeform.io.dicom.rtstruct import read_ct_series, write_rtstruct
    from tests.io.dicom_support import write_ct_series

    ct = read_ct_series(write_ct_series(folder / "ct", shape=(6, 8, 8), origin=(-7.0, -7.0, -5.0)))
    s = trimesh.creation.icosphere(1, radius=4.0)
    write_rtstruct(folder / "seed.dcm", ct, [("GTV", s.vertices, s.faces, "GTV"), ("ITV", s.vertices * 1.5, s.faces)])
    return [folder / "seed.dcm"]


def _track_rtstruct_seed(folder: Path) -> list[Path]:
    """The fixture's GTV RTSTRUCT (first byte even: tracked) and one of its CT slices with the first
    byte odd (replacing that slice: see :func:`_track_rtstruct`)."""
    fx = _track_fixture()
    (folder / "gtv.dcm").write_bytes(fx["gtv"].read_bytes())
    (folder / "odd_slice.dcm").write_bytes(b"\x01" + fx["slice"][1:])
    return [folder / "gtv.dcm", folder / "odd_slice.dcm"]


def make_seeds(name: str, folder: Path) -> list[Path]:
    """Small real files for ``name`` written by the package's own writers (plus shipped data)."""
    folder.mkdir(parents=True, exist_ok=True)
    suffix = READERS[name][0]
    if name.startswith("mesh_"):
        return _mesh_seed(folder, suffix)
    if name == "image_dicom":  # the valid slice the harness mutates (the rest of its series is fixed),
        # as it is (preamble byte 0 even: the phase sorter) and with that byte odd (read_image; see _dicom)
        seed = next(p for p in _dicom_series(folder / "series") if p.name == DICOM_INPUT)
        odd = folder / f"odd_{DICOM_INPUT}"
        odd.write_bytes(b"\x01" + seed.read_bytes()[1:])
        return [seed, odd]
    if name.startswith("image_"):
        return _image_seed(folder, suffix)
    if name == "fourdct_folder":  # tables of tags (tests/fuzz/fourdct_folder.py), not DICOM bytes
        from tests.fuzz.fourdct_folder import seed_tables

        paths = [folder / f"seed{k}.txt" for k in range(2)]
        for path, table in zip(paths, seed_tables()):
            path.write_bytes(table)
        return paths
    if name == "model":
        return _model_seed(folder)
    if name == "rtstruct":
        return _rtstruct_seed(folder)
    if name == "track_rtstruct":
        return _track_rtstruct_seed(folder)
    path = folder / f"seed{suffix}"
    path.write_text(_text_seeds(name))
    return [path]


def local_data_seeds(name: str, limit_bytes: int = 200_000) -> list[Path]:
    """Small files of the right suffix under ``$LUNGDEFORM_DATA`` (local runs; never copied into the repo)."""
    root = os.environ.get("LUNGDEFORM_DATA")
    if not root or not Path(root).is_dir():
        return []
    suffix = READERS[name][0]
    found = []
    for p in Path(root).rglob(f"*{suffix}"):
        if p.is_file() and p.stat().st_size <= limit_bytes:
            found.append(p)
        if len(found) >= 5:
            break
    return found


# =========================================================================== the rule and the record
def crash_key(exc: BaseException) -> str:
    """``Type @ module.py:line`` of the innermost frame in the package (or the outermost one)."""
    frames = traceback.extract_tb(exc.__traceback__)
    ours = [fr for fr in frames if fr.filename.startswith(PACKAGE)]
    fr = (ours or frames or [None])[-1]
    where = "?" if fr is None else f"{os.path.relpath(fr.filename, Path(PACKAGE).parent)}:{fr.lineno}"
    return f"{type(exc).__name__} @ {where}"


class Recorder:
    """Runs one reader on bytes; counts executions; keeps one reproducer per unique crash."""

    def __init__(self, name: str, out: Path | None):
        self.name, self.suffix, self.reader = name, READERS[name][0], READERS[name][1]
        self.out = out
        self.work = Path(tempfile.mkdtemp(prefix=f"ldfuzz-{name}-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
        atexit.register(shutil.rmtree, self.work, True)  # libFuzzer's exit skips this: then the OS's tmp cleaning
        if name == "manifest":
            _manifest_files(self.work)
        if name == "image_dicom":
            _dicom_companions(self.work)
        self.path = self.work / f"input{self.suffix}"
        # one descriptor kept open: an input is written by truncate + pwrite (no open/close per execution)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.executions, self.start, self.last_flush = 0, time.monotonic(), 0.0
        self.crashes: dict[str, dict] = {}

    def run(self, data: bytes) -> str | None:
        """Feed ``data``; return the crash key when the reader broke the rule, else None."""
        self.executions += 1
        os.ftruncate(self._fd, len(data))
        os.pwrite(self._fd, data, 0)
        key = None
        try:
            self.reader(self.path)
        except LungdeformError:
            pass
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:  # noqa: BLE001 - that is the point: anything else is a crash
            key = crash_key(exc)
            if key not in self.crashes:
                self._keep(key, exc, data)
        if self.executions % 256 == 0 and time.monotonic() - self.last_flush > 1.0:
            self.flush()
        return key

    def close(self) -> None:
        """Close the input file and remove the working folder."""
        os.close(self._fd)
        shutil.rmtree(self.work, ignore_errors=True)

    def _keep(self, key: str, exc: BaseException, data: bytes) -> None:
        entry = {"key": key, "type": type(exc).__name__, "message": str(exc)[:300], "reproducer": None}
        if self.out is not None:
            digest = hashlib.sha1(data).hexdigest()[:12]
            path = self.out / self.name / f"crash-{digest}{self.suffix}"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
            entry["reproducer"] = str(path)
        self.crashes[key] = entry
        self.flush()

    def stats(self) -> dict:
        return {"reader": self.name, "executions": self.executions,
                "seconds": round(time.monotonic() - self.start, 1),
                "unique_crashes": len(self.crashes), "crashes": list(self.crashes.values())}

    def flush(self) -> None:
        self.last_flush = time.monotonic()
        if self.out is not None:
            (self.out / self.name).mkdir(parents=True, exist_ok=True)
            tmp = self.out / self.name / "stats.json.tmp"
            tmp.write_text(json.dumps(self.stats(), indent=1))
            tmp.replace(self.out / self.name / "stats.json")


_RECORDERS: dict[str, Recorder] = {}


def test_one_input(name: str, data: bytes) -> None:
    """What each harness's ``TestOneInput`` does (a crash is recorded, not raised: the fuzzer goes on)."""
    rec = _RECORDERS.get(name)
    if rec is None:
        out = os.environ.get("LUNGDEFORM_FUZZ_OUT")
        rec = _RECORDERS[name] = Recorder(name, Path(out) if out else None)
        atexit.register(rec.flush)
    rec.run(data)


# =========================================================================== mutation (no atheris)
_INTERESTING = [b"0", b"-1", b"nan", b"inf", b"-inf", b"1e308", b"99999999999999999999", b"4294967295",
                b"", b"\x00", b"\xff\xff\xff\xff", b"\x00\x00\x00\x80", b",", b";", b"\n", b"\xc3\x28", b"\xfe\xff"]


def mutate(data: bytes, rnd: random.Random, corpus: list[bytes]) -> bytes:
    """One to four random edits: bit flips, byte sets, inserts, deletes, truncation, number swaps, splices."""
    b = bytearray(data)
    for _ in range(rnd.randint(1, 4)):
        op, n = rnd.randrange(8), len(b)
        pos = rnd.randrange(n + 1)
        if op == 0 and n:
            b[min(pos, n - 1)] ^= 1 << rnd.randrange(8)
        elif op == 1 and n:
            b[min(pos, n - 1)] = rnd.randrange(256)
        elif op == 2:
            b[pos:pos] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 8)))
        elif op == 3 and n:
            del b[pos:pos + rnd.randint(1, max(1, n // 8))]
        elif op == 4:
            del b[pos:]
        elif op == 5:
            digits = [i for i in range(n) if 48 <= b[i] <= 57]
            if digits:
                i = rnd.choice(digits)
                j = i
                while j < n and (48 <= b[j] <= 57 or b[j] in b".eE-+"):
                    j += 1
                b[i:j] = rnd.choice(_INTERESTING)
        elif op == 6 and corpus:
            other = rnd.choice(corpus)
            k = rnd.randrange(len(other) + 1)
            b[pos:] = other[k:k + rnd.randint(1, 64)] + b[pos:]
        elif op == 7 and n:
            k = rnd.randint(1, min(16, n))
            src = rnd.randrange(n - k + 1)
            b[pos:pos] = b[src:src + k]
    return bytes(b)


def mutate_loop(name: str, seeds: list[bytes], runs: int, seconds: float, seed: int = 0,
                out: Path | None = None, at_least: int = 0) -> Recorder:
    """Seeded random-mutation fuzzing of one reader in this process, ``runs`` inputs or ``seconds``,
    whichever ends first, but at least ``at_least`` inputs however long they take (a loaded machine
    must not cut a smoke run short); returns its recorder (reproducers under ``out``, default
    ``$LUNGDEFORM_FUZZ_OUT``)."""
    rnd = random.Random(seed)
    if out is None and os.environ.get("LUNGDEFORM_FUZZ_OUT"):
        out = Path(os.environ["LUNGDEFORM_FUZZ_OUT"])
    rec = Recorder(name, out)
    corpus = [s for s in seeds if s] or [b""]
    for s in [b"", b"\x00" * 7, bytes(range(256))] + corpus:
        rec.run(s)
    end = time.monotonic() + seconds
    while rec.executions < runs and (time.monotonic() < end or rec.executions < at_least):
        rec.run(mutate(rnd.choice(corpus), rnd, corpus))
    rec.flush()
    rec.close()
    return rec


# =========================================================================== the script side
def seed_dir(name: str, out: Path) -> Path:
    """The fuzzer's working corpus: the generated seeds plus ``$LUNGDEFORM_DATA`` files (local only)."""
    corpus = out / name / "corpus"
    seeds = make_seeds(name, out / name / "seeds")
    corpus.mkdir(parents=True, exist_ok=True)
    for p in seeds + local_data_seeds(name):
        (corpus / f"seed-{p.name}").write_bytes(p.read_bytes())
    return corpus


def main(name: str, test_one: Callable[[bytes], None]) -> None:
    """``python fuzz_<reader>.py --runs N --seconds S --out DIR [--engine atheris|mutate]``."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=100_000)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=ROOT / "fuzz-out")
    ap.add_argument("--engine", choices=("atheris", "mutate"), default=None)
    args = ap.parse_args()
    os.environ["LUNGDEFORM_FUZZ_OUT"] = str(args.out.resolve())
    engine = args.engine
    if engine is None:
        try:
            import atheris  # noqa: F401
            engine = "atheris"
        except ImportError:
            engine = "mutate"
    if engine == "atheris":
        import atheris

        with atheris.instrument_imports(include=["lungdeform"]):  # coverage of the package's code
            for module in READER_MODULES:
                importlib.import_module(module)
    corpus = seed_dir(name, args.out)
    if engine == "mutate":
        seeds = [p.read_bytes() for p in sorted(corpus.iterdir())]
        mutate_loop(name, seeds, args.runs, args.seconds)
        return
    atheris.Setup([sys.argv[0], f"-runs={args.runs}", f"-max_total_time={max(1, int(args.seconds))}",
                   "-max_len=65536", "-rss_limit_mb=4096", "-timeout=20",
                   f"-artifact_prefix={args.out.resolve() / name}/", "-print_final_stats=1", str(corpus)], test_one)
    atheris.Fuzz()
