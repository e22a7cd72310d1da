"""Write the bad-input corpus (``tests/corpus/<kind>/<defect>.<suffix>``): small files, one per class
of defect the fuzzers (tests/fuzz/) found plus classic ones (empty, truncated, binary garbage, wrong
header, NaN, huge counts). The files are committed; this script says how each was made.
Run: ``PYTHONPATH=src python tests/corpus/make_corpus.py``."""

from __future__ import annotations

import base64
import gzip
import io
import random
import struct
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))  # run as a script: the repository root, for tests.io.dicom_support
from tests.io.dicom_support import circle, rtstruct_bytes  # noqa: E402

#: The GTV of the RTSTRUCT files: axial circles (mm) on the 2 mm slices of the reference CT that
#: tests/cli/test_bad_input_corpus.py writes (z = -169 … -131), inside its model's lung
GTV_CENTRE, GTV_Z = (90.0, 20.0), (-155.0, -153.0, -151.0, -149.0, -147.0)
#: found by fuzz_image_nii (libFuzzer out-of-memory): a gzipped NIfTI header claiming 2566 x 1280 x 1024 voxels
HUGE_NII = base64.b64decode("H4sIAAAAAAAAA4thZCACFDEwM7BxMbAysDAwQiEqYGLgANMN9mfP+IAxA4OCA6Y5G5xBaqAcXi6GAQaMKP4AueuEEwPDBycGBo/DZ8/47EfIgcQZGBBiIDAwvCwOAA==")
GARBAGE = bytes(random.Random(7).randrange(256) for _ in range(300))  # seeded: the same bytes every time


def _zip(entries: dict[str, bytes], method=zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for name, data in entries.items():  # a fixed date: the same bytes on every run
            z.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data, compress_type=method)
    return buf.getvalue()


def _npy(value) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(value), allow_pickle=False)
    return buf.getvalue()


def _model_files() -> dict[str, bytes]:
    header = {"schema.npy": _npy("lungdeform.model"), "schema_version.npy": _npy(3)}
    blob = _zip({"schema.npy": _npy("x" * 400)})
    # deflate data damaged, CRC kept: zlib.error from the decompressor (fuzzer class 1)
    at = blob.index(b"schema.npy") + len(b"schema.npy") + 40
    damaged = blob[:at] + bytes(b ^ 0xA5 for b in blob[at:at + 8]) + blob[at + 8:]
    # the central directory's "encrypted" flag set: RuntimeError "password required" (fuzzer class 2)
    cd = blob.index(b"PK\x01\x02")
    encrypted = blob[:cd + 8] + struct.pack("<H", 1) + blob[cd + 10:]
    # "version needed to extract" 17.3: NotImplementedError (fuzzer class 3)
    version = blob[:cd + 6] + struct.pack("<H", 173) + blob[cd + 8:]
    return {
        "empty.npz": b"", "garbage.npz": GARBAGE, "truncated.npz": blob[: len(blob) // 2],
        "damaged_deflate.npz": damaged, "encrypted_flag.npz": encrypted, "zip_version.npz": version,
        # a readable archive whose header holds text where a number belongs: ValueError in int()
        "text_version.npz": _zip({**header, "schema_version.npy": _npy("three")}),
        # a lone .npy array: np.load returns an ndarray, not an archive (no context manager)
        "lone_array.npz": _npy(np.zeros(3)),
        # found by fuzz_model: a member that is not an .npy comes back from numpy as raw bytes
        "raw_member.npz": _zip({**header, "provenance": b"{}"}),
    }


def _jump_traces() -> dict[str, bytes]:
    """Found by fuzz_trace_vxp and fuzz_trace_csv: one timestamp about 2.5 years late in a 25 Hz
    breath, which made every uniform-grid step build billions of samples."""
    t_ms = np.arange(0, 8000, 40.0)
    t_ms[150:] += 7.8e10
    amp = np.sin(2 * np.pi * np.arange(200) / 100.0)
    vxp = ["[Header]", "CRC=1", "Version=1.6", "Data_layout=amplitude,phase,timestamp,validflag,ttlin,mark,ttlout",
           "Samples_per_second=25", "Scale_factor=10.0", "[Data]"]
    vxp += [f"{a:.4f},0,{t:.0f},0,1,,0" for t, a in zip(t_ms, amp)]
    csv = ['"Frame";"Timestamp";"x";"y";"z"'] + [f"{i};{t:.0f};0;{a:.4f};0" for i, (t, a) in enumerate(zip(t_ms, amp))]
    return {"timestamp_jump.vxp": ("\r\n".join(vxp) + "\r\n").encode(),
            "timestamp_jump.csv": ("\n".join(csv) + "\n").encode()}


def _lung_mask() -> tuple[bytes, bytes]:
    """A left-lung-sized ellipsoid mask (semi-axes 45, 60, 90 mm on a 4 × 4 × 6 mm grid) as a
    zlib-compressed MetaImage: ``(header, data)``; ``build`` makes a model of it."""
    k, j, i = np.meshgrid(np.arange(36), np.arange(40), np.arange(32), indexing="ij")
    p = np.stack([(i - 15.5) * 4.0, (j - 19.5) * 4.0, (k - 17.5) * 6.0], -1)
    data = zlib.compress(((p / [45.0, 60.0, 90.0]) ** 2).sum(-1).__le__(1).astype(np.uint8).tobytes(), 9)
    header = ("ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
              f"CompressedData = True\nCompressedDataSize = {len(data)}\nTransformMatrix = 1 0 0 0 1 0 0 0 1\n"
              "Offset = 100 -20 -150\nElementSpacing = 4 4 6\nDimSize = 32 40 36\nElementType = MET_UCHAR\n"
              "ElementDataFile = LOCAL\n").encode()
    return header, data


def _nifti_nan_sform(header: bytes, data: bytes) -> bytes:
    """The mask of :func:`_lung_mask` as gzipped NIfTI-1 with NaN as the sform's first coefficient."""
    dims = struct.pack("<8h", 3, 32, 40, 36, 1, 1, 1, 1)
    hdr = bytearray(348)
    hdr[0:4] = struct.pack("<i", 348)
    hdr[40:56] = dims
    hdr[70:72], hdr[72:74] = struct.pack("<h", 2), struct.pack("<h", 8)  # uint8
    hdr[76:108] = struct.pack("<8f", 1, 4, 4, 6, 1, 1, 1, 1)
    hdr[108:112] = struct.pack("<f", 352.0)  # vox_offset
    hdr[112:116] = struct.pack("<f", 1.0)  # scl_slope
    hdr[254:256] = struct.pack("<h", 1)  # sform_code: scanner
    hdr[280:328] = struct.pack("<12f", float("nan"), 0, 0, -100, 0, -4, 0, 20, 0, 0, 6, -150)  # RAS
    hdr[344:348] = b"n+1\0"
    return gzip.compress(bytes(hdr) + bytes(4) + zlib.decompress(data), mtime=0)


def _geometry_images() -> dict[str, bytes]:
    """A valid lung mask (``build`` makes a model of it) whose header places it with numbers ITK
    reads as 0 (NaN, infinity, a value missing), as 1 mm (a NaN NRRD spacing) or turns into a NaN
    direction: it was placed wrongly without a word. The MetaImage keys of the issue: Offset,
    ElementSpacing, TransformMatrix."""
    header, data = _lung_mask()
    bad = {"nan_offset.mha": (b"Offset = 100 -20 -150", b"Offset = nan -20 -150"),
           "inf_offset.mha": (b"Offset = 100 -20 -150", b"Offset = 100 inf -150"),
           "short_offset.mha": (b"Offset = 100 -20 -150", b"Offset = 100 -20"),
           "nan_spacing.mha": (b"ElementSpacing = 4 4 6", b"ElementSpacing = 4 4 nan"),
           "nan_matrix.mha": (b"TransformMatrix = 1 0 0 0 1 0 0 0 1", b"TransformMatrix = 1 0 0 0 NaN 0 0 0 1")}
    out = {name: header.replace(old, new) + data for name, (old, new) in bad.items()}
    out["nan_sform.nii.gz"] = _nifti_nan_sform(header, data)
    out["nan_spacings.nrrd"] = (b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 32 40 36\nspacings: nan 4 6\n"
                                b"encoding: gzip\n\n" + gzip.compress(zlib.decompress(data), mtime=0))
    return out


def _mesh_files() -> dict[str, bytes]:
    tet = "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 {z}\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n"
    return {
        "empty.stl": b"",
        "truncated.stl": b"solid-less binary".ljust(80, b" ") + struct.pack("<I", 1000) + bytes(50),
        "garbage.obj": GARBAGE,
        "wrong_header.ply": b"plx\nformat ascii 1.0\nelement vertex 3\nend_header\n0 0 0\n",
        "nan.obj": tet.format(z="nan").encode(),
        "huge_counts.off": b"OFF\n2000000000 2000000000 0\n0 0 0\n",
        "huge_counts.vtk": b"# vtk DataFile Version 3.0\nx\nBINARY\nDATASET POLYDATA\nPOINTS 2000000000 float\n\x00\x00",
        # offsets far outside the connectivity array (segfault_offsets.vtp, committed as found by
        # fuzz_mesh_vtp, is the input that crashed the process: differences wrapping around int64)
        "huge_offsets.vtp": (
            b'<VTKFile type="PolyData" version="1.0"><PolyData><Piece NumberOfPoints="3" NumberOfPolys="2">'
            b'<Points><DataArray type="Float64" NumberOfComponents="3" format="ascii">0 0 0 1 0 0 0 1 0</DataArray>'
            b'</Points><Polys><DataArray type="Int64" Name="connectivity" format="ascii">0 1 2</DataArray>'
            b'<DataArray type="Int64" Name="offsets" format="ascii">5000000000000000000 -8000000000000000000'
            b'</DataArray></Polys></Piece></PolyData></VTKFile>\n'),
        "truncated.glb": b"glTF" + struct.pack("<II", 2, 100000) + b"\x00" * 20,
    }


def _gtv(z=GTV_Z, radius: float = 8.0) -> list[np.ndarray]:
    return [circle(level, radius, GTV_CENTRE) for level in z]


def _rtstruct_files() -> dict[str, bytes]:
    """RTSTRUCTs whose structure GTV cannot be tracked onto the reference CT: each named by its defect."""
    nan = _gtv()
    nan[2] = nan[2].astype(object)
    nan[2][5, 0] = "nan"
    tilted = _gtv()
    tilted[1] = tilted[1] + np.column_stack([np.zeros((24, 2)), 0.5 * (tilted[1][:, 0] - GTV_CENTRE[0])])
    line = np.column_stack([np.linspace(80.0, 100.0, 6), np.full(6, 20.0), np.full(6, -151.0)])
    whole = rtstruct_bytes([(1, "GTV", _gtv())])
    return {
        # the structure set of another CT: another Frame of Reference and study than the reference CT's
        "frame_mismatch.dcm": rtstruct_bytes([(1, "GTV", _gtv())], frame_uid="1.2.826.0.1.3680043.8.498.55.3",
                                             study_uid="1.2.826.0.1.3680043.8.498.55.1"),
        "no_frame.dcm": rtstruct_bytes([(1, "GTV", _gtv())], frame_uid=""),
        # contours 6 mm then 18 mm apart: slices without a contour in the stack
        "contour_gaps.dcm": rtstruct_bytes([(1, "GTV", _gtv((-165.0, -159.0, -141.0)))]),
        "nan_contour.dcm": rtstruct_bytes([(1, "GTV", nan)]),
        "duplicate_roi.dcm": rtstruct_bytes([(1, "GTV", _gtv()), (2, "GTV", _gtv(radius=6.0))]),
        # 150 contours 0.01 mm apart (a damaged export: 4000 of them took minutes and gigabytes)
        "dense_contours.dcm": rtstruct_bytes([(1, "GTV", [circle(-151.0 + 0.01 * k, 8.0, GTV_CENTRE, 3)
                                                          for k in range(150)])]),
        "degenerate_contour.dcm": rtstruct_bytes([(1, "GTV", _gtv()[:2] + [line] + _gtv()[3:])]),
        "tilted_contour.dcm": rtstruct_bytes([(1, "GTV", tilted)]),
        # every contour a tip of 1 or 2 points (each skipped: it encloses no area), so no region is left
        "only_tips.dcm": rtstruct_bytes([(1, "GTV", [c[:1 + k % 2] for k, c in enumerate(_gtv())])]),
        "open_contour.dcm": rtstruct_bytes([(1, "GTV", _gtv(), "OPEN_PLANAR")]),
        "huge_coordinate.dcm": rtstruct_bytes([(1, "GTV", _gtv()[:4] + [_gtv()[4] * 1e30])]),
        # cut where the ROIs begin: read as a structure set without structures
        "truncated.dcm": whole[:whole.index(b"\x06\x30\x20\x00")],
    }


def _text_files() -> dict[str, dict[str, bytes]]:
    return {
        "image": {"garbage.nii.gz": GARBAGE, "huge_header.nii.gz": HUGE_NII,
                  # found by fuzz_image_mha (libFuzzer timeout): ITK spins on a huge NDims
                  "huge_ndims.mha": b"ObjectType = Image\nNDims = 300000000000004 2.5\nDimSize = 6 5 4\n"
                                    b"ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + bytes(120),
                  "huge_ndims.nrrd": b"NRRD0004\ntype: uchar\ndimension: 300000000000004\nsizes: 6 5 4\n"
                                     b"encoding: raw\n\n" + bytes(120), "empty.mha": b"",
                  "truncated.mha": b"ObjectType = Image\nNDims = 3\nDimSize = 64 64 64\nElementType = MET_UCHAR\n"
                                   b"ElementDataFile = LOCAL\n\x00\x01",
                  # found by fuzz_image_mha: a malformed file pattern as the data file kills the process
                  # inside ITK (SIGFPE, a division by zero)
                  "file_pattern.mha": b"ObjectType = Image\nNDims = 3\nDimSize = 6 5 4\nElementType = MET_UCHAR\n"
                                      b"ElementDataFile = LOCA%LType = MET_UCHAR\n",
                  # found by fuzz_image_mha (libFuzzer timeout): a second NDims line, absurd, after a sane one
                  "repeated_ndims.mha": b"ObjectType = Image\nNDims = 3\nNDims = 800000000004 2.5\nDimSize = 6 5 4\n"
                                        b"ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + bytes(120),
                  # found by fuzz_image_dicom (libFuzzer out-of-memory): no preamble, no explicit VR first, the
                  # first element's length read as 3.3 GB; GDCM took 4 s and 3.3 GB on these 65 bytes
                  "implicit_huge_length.dcm": b"\x02\x00\x00UI\x12" + b"\xc6" * 57 + b"<\x00",
                  "huge_dims.nrrd": b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 100000 100000 100000\n"
                                    b"encoding: raw\n\n\x00"},
        "curve": {"empty.csv": b"", "garbage.csv": GARBAGE, "nan.csv": b"t_s,volume_ml\n0,0\n1,nan\n2,100\n",
                  "wrong_header.csv": b"time,volume\n0,0\n1,100\n"},
        "trace": {"empty.vxp": b"", "garbage.vxp": GARBAGE, "header_only.vxp": b"[Header]\r\nVersion=1.6\r\n",
                  **_jump_traces()},
        "points": {"garbage.csv": GARBAGE, "wrong_header.csv": b"x,y,z\n1,2,3\n",
                   "huge_count.txt": b"point\n99999999999999999999\n1 2 3\n"},
        "manifest": {"nul_byte.csv": b"subject,side,volume_ml,path\nP01,left,2300,ee\x00.ply\nP01,left,2900,ei.ply\n",
                     "no_such_user.csv": b"subject,side,volume_ml,path\nP01,left,2300,~nosuchuser9f3/ee.ply\n"
                                         b"P01,left,2900,ei.ply\n",
                     "garbage.csv": GARBAGE, "wrong_header.csv": b"name,lung,path\nP01,left,a.ply\n"},
    }


def main() -> None:
    kinds = {"model": _model_files(), "mesh": _mesh_files(), "rtstruct": _rtstruct_files(), **_text_files()}
    kinds["image"].update(_geometry_images())
    for kind, files in kinds.items():
        (HERE / kind).mkdir(exist_ok=True)
        for name, data in files.items():
            (HERE / kind / name).write_bytes(data)


if __name__ == "__main__":
    main()
