"""VTK legacy (.vtk) and XML PolyData (.vtp) files through lungdeform.io.meshfile: hand-made files, meshio's
unstructured grid and files written by VTK itself (the readers are in lungdeform.io.vtk), and the one .vtp
writer (lungdeform.io.vtk.vtp_bytes) in both its layouts."""

from __future__ import annotations

import base64
import json
import struct
import subprocess
import sys
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np
import pytest

from lungdeform.geometry.mesh import icosphere
from lungdeform.io.meshfile import load_surface, read_mesh, write_mesh
from lungdeform.io.vtk import read_vtp, vtp_bytes
from tests.io.test_meshfile import CUBE_VOLUME, SPHERE, cube_quads


# --------------------------------------------------------------------------- hand-made files
def test_hand_made_ascii_vtp(tmp_path):
    v, quads = cube_quads()
    conn = " ".join(str(i) for q in quads for i in q)
    offsets = " ".join(str(4 * (k + 1)) for k in range(len(quads)))
    pts = " ".join(f"{x:g}" for x in v.ravel())
    (tmp_path / "cube.vtp").write_text(f"""<?xml version="1.0"?>
<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">
  <PolyData>
    <Piece NumberOfPoints="8" NumberOfVerts="0" NumberOfLines="0" NumberOfStrips="0" NumberOfPolys="6">
      <Points><DataArray type="Float32" NumberOfComponents="3" format="ascii">{pts}</DataArray></Points>
      <Polys>
        <DataArray type="Int32" Name="connectivity" format="ascii">{conn}</DataArray>
        <DataArray type="Int32" Name="offsets" format="ascii">{offsets}</DataArray>
      </Polys>
    </Piece>
  </PolyData>
</VTKFile>
""")
    surf, report = load_surface(tmp_path / "cube.vtp")
    assert report.n_faces == 12  # six quads fanned into two triangles each
    assert surf.volume == pytest.approx(CUBE_VOLUME)


def test_vtk_unstructured_grid_from_meshio(tmp_path):
    import meshio

    meshio.vtk.write(str(tmp_path / "u.vtk"), meshio.Mesh(SPHERE.vertices, [("triangle", SPHERE.faces)]), binary=True)
    surf, _ = load_surface(tmp_path / "u.vtk")
    assert surf.volume == pytest.approx(SPHERE.volume)


# Files written by VTK 9.7.2 itself (vtkXMLPolyDataWriter, vtkPolyDataWriter, vtkStripper) from
# the 12-vertex icosahedron of lungdeform.geometry.mesh.icosphere(0) before normalisation, (±1, ±t, 0)
# etc. with t the golden ratio, as float32: inline binary with zlib and lzma, appended raw and base64, triangle strips,
# legacy 5.1 binary (OFFSETS/CONNECTIVITY, METADATA) and legacy 4.2 ASCII. They are the check
# that the readers follow VTK's real layout, not our own idea of it. zlib + base64 of a JSON
# {name: base64(file)}.
VTK_FILES = """
eNrtPNmS2siyv3LCr33iWhLgaZ2IeUArEkigfXmZQBIGtDXupll04/77SS0glRAMDts9tm93BGNVZVXlWlmZtcz/fvDW6fz5
+FcWr73/2W03H/7zrw8zhux71n4ZJObRJ+KdF2JrSevvhfDxgQ4Plslu+bl1iIWROvB5gxRiaueNYtax1ZWwpgjXFrO5Rb7O
NGE/Cdm1wIuDgDc/ez0xcm2BFKLDJhipL65hvrp8vPLWwnLOmyuXN4927zSmKXqpkkkAcwhy64/E2O/JOx9oCVL12YIxnEhd
BTzHeAS+9xMz8wnyKIT9sUAPHw2efFkYOZx9oNfDZVkXxw5hLPXU3DrAm064ikfEr8FIIoWQPQLt08DC10D/zI3d2E/VLOcB
qQe8HuC6qI9lzE/ivZ+BrGihheMwKOrD4Xq2fMppqeghN16qFnJr1k9waje3BpjKc5ijF/wUsBkrxx5/uGyPdddX42eNuqXA
lO0UWzw6drQMRvHe1bG1mhx2jl3KW0+4bV536o/yL+88G/SdmJXcoAfv7vwEXwUMtnaS+NWxxQH00RxrkLoGvqnsZyAxwkHS
pb3MOLisSwNJV5rtVgvmRruwlkPxYzlVMThKMWT4cYxRfHOTAMv/ZcmZZfKytXFVYuMGIZfIqctKrDpSOdXV9IBXQpUITLGv
YW4WGGLfSEyQ9/bZ4FaZka4mGuP2VIN7XoAdBTGMpzRkWOgifnUT8uhZHJbbukaYA4EfrDwLbDfaH21sMDMi/LMRcVMVM0BG
IF+ibDvTRCLgt0095PDYSwJsnstgLZxstqk3y7EOuKtRYH9qXMiK7mgHv5YMicux9jsz4V4Cy7gPj/bd8YDNXsoPtdP9rrB/
gzv6CTfomh9+1pgbXDVf77B1DfrKobIW2EpfCdh0MoidnroJkhhbaMLyRBvoag24Vn4KOuLEFego1q04920HV3s5TvVmPdeH
+q1kGc9SGHXZLNWw2erHjlG5FD6N8lNxtdCR/o9NeZx9bwT+i3GwfI46Fh4DvTs3cTPXLuZtAj53C/MaeBRBn9wx581IuFeX
MOW51Yf5y8XjTBhMG/WOvSSFNXbmD5Ep/M60Y1zNh3Kv7i709KjzYAu2hNjIjG3IQaOwhU3lvOVrAiHTtY+CteEVfFEY8DEx
t9XBT8jzV9ghmbipHINfvc+nnuys5UMn+pm/1ryjTrQztf1xFCJ3mmzSWvcH/i70xBz0YCRu/NG77n523Rk99Ti3qawVH7ws
3nTeDdu+8iB18Gk0+FT5oChble+c6Xishma0SDeZQQSfFJOj1WjV1011Hhwfd37mqspxm3pc8Eky5ZlvU4JrYPhUNwduuDJk
XdUt3dktLHdkRqtZkK5eJ9lKdvUg1ngzcmw/mxtkJtubxIsGB+e4TebJYOsx4nSMkSuZdzE5UXpTfjA3GBmXsafjImRxiVAJ
GVMhzh1Qpi2Rd+nlK+TtEW7iEybmH+9am7K2Xclo7FnOC7M5L+S0tCmyjKt0jHQNBwtGq0g1IOIu5I9TRhQPtCTuK0kAMdPW
UK1YkY5kNMFXqgQS0ENVc7I4nmCrwyKRt3JPwnycshaJmQTJ4JNMyDBPBMzQthrgGUv7+9d8yDHO9gsyVeaWGbrlGnmCn2Lg
fJ0xILbbeDzEHss///zw7399mG82izRYBH89z/fnXIc7tzvP7UbusBZG+XolbzyisN9XsNelk8aYa5Iwx9U4z0fAL2IBxG+q
NYjmFvcKsn9yLQ5yHfHzaUzTyNdp6Rvzk8sYrJozV/KWa+2HTRwS2FB8yluutQc/h3sW5GARmZx9yf04kBzoWvvfPjeyqb0L
NuJaykUsOQmjvRSyBykbwrriIDJC1rmQfZ3qw6Oks5nEgI9YN3VGVbGfUvraa7pkWnEpcxC9pKKTh3w/2sbgi16reFKSYnKq
46Js4yKlRwEHPL94hFy2rfJxJDYFOPCZBnxOr3Dhd3L5V3nBcp7Lo+Br2NUOaGvx2zEWzPWVNzLj+/Cw3x0P+KJL+bVi92tx
fe7HqjnejKsssCckv/mK+D/0iMGra8nY3HY3wSi61wav20vbBtc3/ARigyw2vepTHr/nOrjyR1Sc56su3Yo5btOKrJG3fJnA
V/Fdng/rxlVfPMkQ3V7occZW+0ffP099axkQ98jg2/NWbu/z+T6hGbVj6Ju0onHmTds+2VTuh+XrfnOHrisXenzsiLF/Ud3m
evkddbu8T7f4aS+3ub+Exp+/rm7942+oW0LWnTt1+1V5RK5j6qyfYo1il7B+whqrwvz3SQHWq+BY5bDcgzIs/gDpH5iXZY/D
U3nWKhfwP1rwc7n8W04eSP7x8eO5zLTKBfyhBX/4uFN3s9m+qhToVnlYlHct+K4BH/7NX3/IImV6f/7kutpTSv3ZOWANH3X2
r8cfd8Hp5flzUteyXfjFGm500d9g7KVrfLqGP3XRx9dwv4s/oa6U6kGVLvxSl9DoLvhw2YW/0X/5N/iHXfJRuuhr6Ffooq8h
f6eLvnFXZYO+hv6jLvqo1khMF74GvQ0h1XOLrfGZXUTwtT4X9aBsl5DSGl7bw6TGX4/E1KTINapBDa+b5r4E/FLb7zzQ4X5n
xupETeKX3F8hexrep/5Pen5b+MZq/UTycKjbQJ4SI3sLp7w83xu8sf419haqGPv+/YtqH/t2jkxfP9u9a4+k3FvN89/reyQM
Gl907muc8kMW2SvK1yXGtQ4vHe2767nLM7Pra7wL+T2HSbCin2OYuOp/RM62i7N3yDfjSmd3xwDts0NERq094lt7I40Y4NZe
1MX5I8RoFZ2wjhODiQvxm1flmDojftYjUtNNUlOMwUiFeM3jybBsC3FZ6mLzZj5fwIHPnvoEdBwvzv3K88li70DIbY83+wW9
He3g1+b3cizIK4szWv0uPIfvjofZ7zrk93D3WcTl3tujCfYU/JBzpDeNQ48Sc1f++O3nSm+6jyPs79rHKc77W3pkDtX+8q++
lwX54/o33MsKBezOvawLPc64yzz5F9VtJv2WulX2d+r28hyfOVRnNr+8bn/LPegpExF36hbVY7H+FueMD1WeUcAb8eKjctZP
ef4mwPoJa2wE8z/Nz5wdW47zNapcz6jP8/peRarTLwM1W/YnjbsWLqY8Tw2/P4Wc5nx3wQqkcRaPpvTLrnGfIVXL/s/N/tVP
VI4kYaSuYoyCc71msLsgFgn47NVtY2bSc7UgpogAa/TXyv5B6O+ddPNper6PxTGK7fQkXvy0CFdU476IImfUehH6/XpsmSr7
P/WQ/ibVm+n46U4XOTu11zHy1Pfv4RimGGabb0rpBc0yfwGvf7SBlEXqRlu1WdZY7nrbFME/uTEm4yJ6OyBwFaUNxR8h45g3
+OcQmC3fwI/AKA+BiT2ENtTeQgSH2bJDhA8cwY/KH9Wlfks3KH4ZgVkI/6Mb+GmU//gGflQ2LfkjulFw7ob9IThoFIbq30Jt
JUXwY9dhSoLwL6Cy2SLyV27IGObfrlO+6Phj1L4QGBs06TQRGdImghvpRzmIfAUM4R21r2cEP4HgmCD6tVWEtpZdIPYtIfhV
BIeBzH2W/Jr9p+r5QJwl8x+w/QQp6vBbtp+KZbvr+YDObcAE3p8PvD8f6HKxG9RtRej0mOBqBEEYXy4n7l6zFUyK2D6ETTCt
zCfFFN2q7XPABl8gJYbxNz3FWjnFVUbL2Ump2td4CKlGysBJJFxKsJ4ai66Tqr0541Iqf8BVnRrAtH3VbKHfXJ6nejz2+Ny1
iQrQVrpcPXcpB24eqj2Vi7N6OXHnJuG/P194f77wHZ8vdIYl1FdfS/5x11//ed7eeivs+18z7w7FjN/iCv334u2trwG9z+V/
aC7/gs8numx8hqREFhrnzDTScBnXVpNim4b32RiTGZGasqIus5w8ZzntlMIZXIDruhtDKpMFmDixuHw8bqfqAeNFG1mKXVvv
ibauU44bbzKNE794NvdFHVHzhTUIVUPKJOxgm3z/Wae3xtR0d4voEVfDlTvpmYpjx8Y8pp4knFsZNDlxwlU6xyEOsgNtavrP
krFxA44ifGNjKNEqXnDcaM6rZUxniy8B4IRv24HUrkzZtphh4bpz3MqKLkq1TYi2mTz+Ws81zttqV9PnFWLnOrYzeQWocYv0
V00pMWCUo6KvqIAgKdVaUUZ8SuPlo9+jdjqM56UB5eErkKmYqvyAUUyX00dyz7WfMtNabUzjEfdYNZ2nGwzafbF4+cXFgp2f
UqFkq7iaRjszlGWXowTfFiGt3kaOGfRy+zRNOa344Y1kS8v68lk32KPOnu2VNnF3N1Pe7nnIy/Z5vXl5fwT/fbJYWbuSxTaj
/uKQoetyw/mQ+CIrBTt+8Trad9cfLi/XX5/FvMeTq+KRTh11nfqvm5c7lFwXPAnR2KC8eNI+CCDkzfzCe7ceGOhGNtVZ7OIh
4/V27SxkK2n5Ib5zmDLDTKaHe4Fh86yGkPTlXsqUpTREPchEZ/PfqxyyfYmRMIHJs6B8nOt9pL/H07occBeecfvxRbNt3h+h
iR4eLnlH4NsLPi77vF/6+P9z6SNziHjzrRnDD4wErviIr3zc/NM8tH+X95s/COnk554MYYgX/jj3sTr8ux62d74ygVkup+Dz
BcboWg+g3l9O6SEB47R8hF+MKa9zHCy0a/t5YSkd8/GjJawj+D+r+yLWQXePs8uoW9KBZh34CkFeobOENvc+7HvjSxVyOLe+
OXv+gf8Dkh/sI8o1ppmR51F/ccG4fMhRwY3rh1nxYjn3j3+VZ1qQCER5IiAcKSLgX5Yl8+VLcfOUFIChQ3A/zoNxgSfxYETh
wXBDa8YAUqporLKcoZgyZ9J5FnZwi7Kyge94anJSYVxueXQy3vXzW+AfZ/wfWHELfNYqF/BJC94ol1fPH/L/fswOr2R5q7xV
LuB0C16WZ4+P3q64uU5/zC+o1+VhUd614LsWnI5wzmQ5VjFVio7iqZoHUwZnaAY5BWcw1iNOVjXq8jUxe5gpWNVu1AqylE0x
XuE4Ttv1Wh3ECMOnscGSYEPBTI+lYpJC6jzWMZc3MNMwCt1tC4cxLx1s5wuSYecLjvoFQuOZwax+MVC/gOCUjmcIVP2CZFTf
+F91PVMQa/xfajjW9Ywhq4mqUU3roR7pSJ7p0YBTcFU0o9iwtPtk8P6K5/0Vz1u94jltuZQOt0/8NX/x1+s7PS42CYW2x6UM
TBa1ylvkM1/Ir3twcemNYmoGHhm8wfAg5UtSnuYPn5C0tkpRkXIrjc1DnzGSZh7zVLiVrh5b6fER+rTT06oNMnYTRmO5Z2vT
tr1oA79Wm/HP4YWHS6BpXPFZhJF0WMgvDwtP30UYWX33oH4P45R86GV4WsC0vE9UfMuAE8pY2S4fF/oATUW7POw8QkhawPy8
X7/8lvJQFjt9Q9h5PH3noe+5ft1oTw8H5beS98XLbyHvm+PP+SIKWQDOHHcZCpe8THO8OY/Lpz8//N9/AY+SbQE="""


@pytest.mark.parametrize("name", sorted(json.loads(zlib.decompress(base64.b64decode(VTK_FILES)))))
def test_files_written_by_vtk(tmp_path, name):
    files = json.loads(zlib.decompress(base64.b64decode(VTK_FILES)))
    (tmp_path / name).write_bytes(base64.b64decode(files[name]))
    v, f = read_mesh(tmp_path / name)
    ref = icosphere(0)
    scale = np.sqrt(1 + ((1 + 5**0.5) / 2) ** 2)
    np.testing.assert_allclose(v, ref.vertices * scale, atol=1e-5)  # float32; ASCII has 6 digits
    # same triangles, same winding (strips come back in another order and rotation)
    canon = lambda f: {tuple(np.roll(t, -int(np.argmin(t)))) for t in f.tolist()}  # noqa: E731
    assert canon(f) == canon(ref.faces)


# --------------------------------------------------------------------------- the one .vtp writer
def _appended_array(data: bytes, name: str, dtype) -> np.ndarray:
    """The named DataArray of an appended-raw .vtp, decoded by hand (UInt64 size header, little endian)."""
    head, blob = data.split(b'<AppendedData encoding="raw">\n_', 1)
    root = ET.fromstring(head + b"</VTKFile>")
    el = next(e for e in root.iter("DataArray") if e.get("Name") == name)
    off = int(el.get("offset"))
    (nbytes,) = struct.unpack_from("<Q", blob, off)
    return np.frombuffer(blob[off + 8:off + 8 + nbytes], dtype)


@pytest.mark.parametrize("appended", [False, True])
def test_vtp_writer_round_trip(tmp_path, rng, appended):
    # truth: the arrays written; our reader (and a hand decoder for the appended fields) gives them back,
    # Float64 points exactly, Float32 points to float32 rounding
    s = icosphere(2, 30.0)
    disp = rng.normal(size=s.vertices.shape).astype(np.float32)
    stiff = rng.uniform(0.5, 2.0, s.n_vertices).astype(np.float32)
    for points_dtype in (np.float64, np.float32):
        data = vtp_bytes(s.vertices, s.faces, {"displacement_mm": disp, "stiffness": stiff}, time_s=1.25,
                         appended=appended, points_dtype=points_dtype)
        (tmp_path / "f.vtp").write_bytes(data)
        v, f = read_vtp(tmp_path / "f.vtp")
        np.testing.assert_array_equal(f, s.faces)
        np.testing.assert_array_equal(v, s.vertices.astype(points_dtype))
        assert (b'format="appended"' in data) == appended and (b'format="binary"' in data) != appended
    if appended:
        assert _appended_array(data, "TimeValue", "<f8").tolist() == [1.25]
        np.testing.assert_array_equal(_appended_array(data, "displacement_mm", "<f4"), disp.ravel())
        np.testing.assert_array_equal(_appended_array(data, "stiffness", "<f4"), stiff)


def test_vtp_writer_plain_surface_is_what_write_mesh_writes(tmp_path):
    # write_mesh's .vtp is the writer's inline layout without point data or time: no <PointData>,
    # no <FieldData>, one element per line
    write_mesh(tmp_path / "s.vtp", SPHERE.vertices, SPHERE.faces)
    data = (tmp_path / "s.vtp").read_bytes()
    assert data == vtp_bytes(SPHERE.vertices, SPHERE.faces)
    assert b"<PointData>" not in data and b"<FieldData>" not in data and b"<Points><DataArray" in data


def test_offsets_wrapping_around_int64_are_refused():
    # why: found by tests/fuzz/fuzz_mesh_vtp.py: offsets near +-2**63 whose differences wrap around
    # passed the size check, and np.repeat on the wrapped counts crashed the process (segmentation
    # fault); offsets outside 0..len(connectivity) are now refused first. Run in a child process so
    # that a regression fails this test instead of killing the test run.
    bad = Path(__file__).resolve().parents[1] / "corpus" / "mesh" / "segfault_offsets.vtp"
    code = ("import sys; from lungdeform.io.meshfile import read_mesh; from lungdeform.errors import ReadError\n"
            "try:\n    read_mesh(sys.argv[1])\nexcept ReadError as e:\n    print(e)")
    done = subprocess.run([sys.executable, "-c", code, str(bad)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-500:]
    assert "segfault_offsets.vtp: polygon offsets are inconsistent" in done.stdout
