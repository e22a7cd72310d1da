"""Mesh files in and out: round trips, files written by other software, and every kind of bad input."""

from __future__ import annotations

import base64
import json
import os
import zlib

import numpy as np
import pytest

from lungdeform import io as lio
from lungdeform.errors import InputError, MeshError, ReadError, UnitsError
from lungdeform.io import WRITE_SUFFIXES, load, load_surface, read_mesh, write_mesh
from lungdeform.mesh import check_surface, icosphere, signed_volume

SPHERE = icosphere(3, radius=60.0, center=(10.0, -20.0, 30.0))


def cube_quads():
    """A 40 mm cube as 8 vertices and 6 outward quads (exercises fan triangulation)."""
    v = 40.0 * np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                         [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    q = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [1, 2, 6, 5], [0, 4, 7, 3]]
    return v, q


CUBE_VOLUME = 40.0**3


# --------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("suffix", WRITE_SUFFIXES)
def test_round_trip_every_writable_format(tmp_path, suffix):
    # same volume (analytic sphere mesh) and same vertex count: STL's soup is merged back
    path = write_mesh(tmp_path / f"sphere{suffix}", SPHERE.vertices, SPHERE.faces)
    v, f = read_mesh(path)
    assert v.dtype == np.float64 and f.dtype == np.int64
    assert len(v) == SPHERE.n_vertices and len(f) == len(SPHERE.faces)
    rtol = 1e-6 if suffix == ".stl" else 1e-12  # STL stores float32
    assert signed_volume(v, f) == pytest.approx(SPHERE.volume, rel=rtol)
    surf, report = load_surface(path)
    assert report.repairs == ()
    assert surf.name == f"sphere{suffix}"


def test_write_is_atomic(tmp_path, monkeypatch):
    # a failure between writing and renaming leaves the old file and no temp file behind
    target = write_mesh(tmp_path / "s.ply", SPHERE.vertices, SPHERE.faces)
    before = target.read_bytes()

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_mesh(target, SPHERE.vertices * 2, SPHERE.faces)
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]


def test_write_unknown_suffix(tmp_path):
    with pytest.raises(InputError, match=r"cannot write '\.xyz'"):
        write_mesh(tmp_path / "a.xyz", SPHERE.vertices, SPHERE.faces)


def test_stl_soup_is_merged(tmp_path):
    # a triangle soup with every corner repeated: the reader must give an indexed, closed mesh
    path = write_mesh(tmp_path / "s.stl", SPHERE.vertices, SPHERE.faces)
    assert path.stat().st_size == 84 + 50 * len(SPHERE.faces)  # binary
    v, f = read_mesh(path)
    check_surface(v, f)


def test_ascii_stl(tmp_path):
    tri = SPHERE.vertices[SPHERE.faces]
    lines = ["solid s"]
    for t in tri:
        lines += ["facet normal 0 0 0", "outer loop"] + [f"vertex {x:.9e} {y:.9e} {z:.9e}" for x, y, z in t]
        lines += ["endloop", "endfacet"]
    (tmp_path / "a.stl").write_text("\n".join(lines + ["endsolid s"]) + "\n")
    v, f = read_mesh(tmp_path / "a.stl")
    assert len(v) == SPHERE.n_vertices
    assert signed_volume(v, f) == pytest.approx(SPHERE.volume, rel=1e-8)


def test_glb_from_trimesh_with_node_transforms(tmp_path):
    # two meshes in the default scene, each under a node transform; both must come back, moved
    import trimesh

    scene = trimesh.Scene()
    sphere = trimesh.Trimesh(SPHERE.vertices, SPHERE.faces, process=False)
    small = icosphere(2, radius=20.0)
    shift = np.eye(4)
    shift[:3, 3] = (200.0, 0.0, 0.0)
    rot = np.eye(4)
    rot[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    rot[:3, 3] = (0.0, 0.0, -150.0)
    scene.add_geometry(sphere, node_name="a", transform=shift)
    scene.add_geometry(trimesh.Trimesh(small.vertices, small.faces, process=False), node_name="b", transform=rot)
    (tmp_path / "s.glb").write_bytes(scene.export(file_type="glb"))
    v, f = read_mesh(tmp_path / "s.glb")
    assert len(v) == SPHERE.n_vertices + small.n_vertices
    assert signed_volume(v, f) == pytest.approx(SPHERE.volume + small.volume, rel=1e-5)
    big = v[:, 0] > 100
    np.testing.assert_allclose(v[big].mean(axis=0), SPHERE.vertices.mean(axis=0) + (200, 0, 0), atol=1e-3)
    np.testing.assert_allclose(v[~big].mean(axis=0), (0, 0, -150), atol=1e-3)


def test_gltf_with_embedded_buffers(tmp_path):
    import trimesh

    mesh = trimesh.Trimesh(SPHERE.vertices, SPHERE.faces, process=False)
    files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(mesh), embed_buffers=True)
    (tmp_path / "s.gltf").write_bytes(files["model.gltf"])
    surf, _ = load_surface(tmp_path / "s.gltf")
    assert surf.volume == pytest.approx(SPHERE.volume, rel=1e-5)


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


def test_hand_made_obj_off_ply_vtk_with_quads(tmp_path):
    v, quads = cube_quads()
    # OBJ: 1-based, texture/normal indices, negative (relative) indices, a comment
    obj = ["# cube"] + [f"v {x} {y} {z}" for x, y, z in v] + ["vt 0 0", "vn 0 0 1"]
    for q in quads:
        obj.append("f " + " ".join(f"{i - 8}/1/1" if k % 2 else f"{i + 1}//1" for k, i in enumerate(q)))
    (tmp_path / "c.obj").write_text("\n".join(obj) + "\n")
    off = ["OFF", "# comment", "8 6 12"] + [f"{x} {y} {z}" for x, y, z in v] + [f"4 {' '.join(map(str, q))}" for q in quads]
    (tmp_path / "c.off").write_text("\n".join(off) + "\n")
    ply = ["ply", "format ascii 1.0", "element vertex 8", "property float x", "property float y",
           "property float z", "element face 6", "property list uchar int vertex_indices", "end_header"]
    ply += [f"{x} {y} {z}" for x, y, z in v] + [f"4 {' '.join(map(str, q))}" for q in quads]
    (tmp_path / "c.ply").write_text("\n".join(ply) + "\n")
    vtk = ["# vtk DataFile Version 3.0", "cube", "ASCII", "DATASET POLYDATA", "POINTS 8 float"]
    vtk += [" ".join(map(str, p)) for p in v]
    vtk += ["POLYGONS 6 30"] + [f"4 {' '.join(map(str, q))}" for q in quads]
    vtk += ["POINT_DATA 8", "SCALARS s float 1", "LOOKUP_TABLE default"] + ["0"] * 8
    (tmp_path / "c.vtk").write_text("\n".join(vtk) + "\n")
    for name in ("c.obj", "c.off", "c.ply", "c.vtk"):
        surf, report = load_surface(tmp_path / name)
        assert report.n_faces == 12, name
        assert surf.volume == pytest.approx(CUBE_VOLUME), name


def test_vtk_unstructured_grid_from_meshio(tmp_path):
    import meshio

    meshio.vtk.write(str(tmp_path / "u.vtk"), meshio.Mesh(SPHERE.vertices, [("triangle", SPHERE.faces)]), binary=True)
    surf, _ = load_surface(tmp_path / "u.vtk")
    assert surf.volume == pytest.approx(SPHERE.volume)


# Files written by VTK 9.7.2 itself (vtkXMLPolyDataWriter, vtkPolyDataWriter, vtkStripper) from
# the 12-vertex icosahedron of lungdeform.mesh.icosphere(0) before normalisation, (±1, ±t, 0)
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


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("suffix", lio.MESH_SUFFIXES)
def test_missing_and_empty(tmp_path, suffix):
    with pytest.raises(ReadError, match=rf"missing{suffix}: no such file"):
        read_mesh(tmp_path / f"missing{suffix}")
    (tmp_path / f"empty{suffix}").write_bytes(b"")
    with pytest.raises(ReadError, match=rf"empty{suffix}: file is empty"):
        read_mesh(tmp_path / f"empty{suffix}")


def test_truncated_binary_stl(tmp_path):
    data = write_mesh(tmp_path / "s.stl", SPHERE.vertices, SPHERE.faces).read_bytes()
    (tmp_path / "cut.stl").write_bytes(data[: len(data) - 70])
    with pytest.raises(ReadError, match=r"cut\.stl: truncated binary STL.*1280 triangles"):
        read_mesh(tmp_path / "cut.stl")
    (tmp_path / "head.stl").write_bytes(data[:50])
    with pytest.raises(ReadError, match=r"head\.stl: truncated STL"):
        read_mesh(tmp_path / "head.stl")


@pytest.mark.parametrize("suffix", lio.MESH_SUFFIXES)
def test_garbage_bytes(tmp_path, rng, suffix):
    path = tmp_path / f"garbage{suffix}"
    path.write_bytes(rng.bytes(3000))
    with pytest.raises(ReadError, match=rf"^{tmp_path}/garbage{suffix}: ") as info:
        read_mesh(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("suffix", [".ply", ".vtk", ".vtp", ".off", ".obj"])
def test_truncated_files(tmp_path, suffix):
    path = write_mesh(tmp_path / f"s{suffix}", SPHERE.vertices, SPHERE.faces)
    data = path.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises((ReadError, MeshError), match=rf"cut{suffix}"):
        load_surface(cut)  # OBJ has no counts: it comes back open and check_surface says so


def test_unknown_suffix_lists_supported(tmp_path):
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    with pytest.raises(ReadError, match=r"a\.xyz: unknown mesh format.*\.stl, \.obj"):
        read_mesh(tmp_path / "a.xyz")


def test_point_cloud_has_no_triangles(tmp_path):
    (tmp_path / "p.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ReadError, match=r"p\.obj: no triangles"):
        read_mesh(tmp_path / "p.obj")


def test_nan_coordinates(tmp_path):
    v = SPHERE.vertices.copy()
    v[5] = np.nan
    write_mesh(tmp_path / "nan.obj", v, SPHERE.faces)
    with pytest.raises(MeshError, match=r"nan\.obj: vertex coordinates contain NaN"):
        load_surface(tmp_path / "nan.obj")


def test_open_surface(tmp_path):
    write_mesh(tmp_path / "open.stl", SPHERE.vertices, SPHERE.faces[1:])
    with pytest.raises(MeshError, match=r"open\.stl: surface is open \(3 boundary edges\)"):
        load_surface(tmp_path / "open.stl")
    with pytest.raises(MeshError, match="open"):  # repair never closes holes
        load_surface(tmp_path / "open.stl", repair=True)


def test_non_manifold(tmp_path):
    # two spheres sharing one vertex: closed, one piece, but pinched
    a = icosphere(2, radius=30.0)
    b = icosphere(2, radius=30.0, center=(60.0, 0.0, 0.0))
    ia = int(np.argmax(a.vertices[:, 0]))
    ib = int(np.argmin(b.vertices[:, 0]))
    fb = b.faces + len(a.vertices)
    fb[fb == ib + len(a.vertices)] = ia
    write_mesh(tmp_path / "pinch.obj", np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, fb]))
    with pytest.raises(MeshError, match=r"pinch\.obj: surface is not 2-manifold"):
        load_surface(tmp_path / "pinch.obj")


def test_metres_refused_then_converted(tmp_path):
    small = icosphere(3, radius=0.1)
    write_mesh(tmp_path / "m.ply", small.vertices, small.faces)
    with pytest.raises(UnitsError, match=r"m\.ply: .*use --units m"):
        load_surface(tmp_path / "m.ply")
    surf, report = load_surface(tmp_path / "m.ply", units="m")
    assert report.repairs[0] == "scaled from m to mm"
    assert surf.volume == pytest.approx(small.volume * 1e9)
    with pytest.raises(InputError, match="units"):
        load_surface(tmp_path / "m.ply", units="inch")


def test_inward_surface_repaired_and_reported(tmp_path):
    write_mesh(tmp_path / "in.off", SPHERE.vertices, SPHERE.faces[:, ::-1])
    with pytest.raises(MeshError, match=r"in\.off: faces point inward"):
        load_surface(tmp_path / "in.off")
    surf, report = load_surface(tmp_path / "in.off", repair=True)
    assert surf.volume > 0 and "flipped inward-facing orientation" in report.repairs


# --------------------------------------------------------------------------- load()
def test_load_mesh_file(tmp_path):
    write_mesh(tmp_path / "s.vtp", SPHERE.vertices, SPHERE.faces)
    [(surf, report)] = load(tmp_path / "s.vtp")
    assert report.volume_mm3 == pytest.approx(SPHERE.volume)
    with pytest.raises(InputError, match="mesh file"):
        load(tmp_path / "s.vtp", labels="left")


def test_load_label_image_gives_one_surface_per_group(tmp_path):
    # two blocks labelled like a lobe map: left = 1,2 (at +x in LPS), right = 3
    import SimpleITK as sitk

    a = np.zeros((20, 20, 40), np.int16)
    a[4:16, 4:16, 22:28] = 1
    a[4:16, 4:16, 28:34] = 2
    a[4:16, 4:16, 6:16] = 3
    img = sitk.GetImageFromArray(a)
    img.SetSpacing((2.0, 2.0, 2.0))
    sitk.WriteImage(img, str(tmp_path / "lobes.nii.gz"))
    out = load(tmp_path / "lobes.nii.gz", labels="left,right", smooth_iterations=0)
    assert [s.name for s, _ in out] == ["lobes-left", "lobes-right"]
    (left, lrep), (right, rrep) = out
    assert left.volume == pytest.approx(12 * 12 * 12 * 8, rel=0.05)
    assert right.volume == pytest.approx(12 * 12 * 10 * 8, rel=0.05)
    assert left.vertices[:, 0].mean() > right.vertices[:, 0].mean()
    [(whole, report)] = load(tmp_path / "lobes.nii.gz", smooth_iterations=0)  # all labels
    assert whole.volume == pytest.approx(left.volume, rel=0.01)  # the largest piece: labels 1+2
    assert any("kept the largest of 2 mask components" in r for r in report.repairs)
    with pytest.raises(InputError, match="units"):
        load(tmp_path / "lobes.nii.gz", units="m")


def test_load_unknown_and_missing(tmp_path):
    (tmp_path / "a.txt").write_text("x")
    with pytest.raises(ReadError, match=r"a\.txt: unknown format"):
        load(tmp_path / "a.txt")
    with pytest.raises(ReadError, match="no such file"):
        load(tmp_path / "nothing.nii.gz")
