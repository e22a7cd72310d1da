"""Mesh files in and out: round trips, files written by other software, and every kind of bad input."""

from __future__ import annotations

import os

import numpy as np
import pytest

from lungdeform.errors import InputError, MaskError, MeshError, ReadError, UnitsError
from lungdeform.geometry.mesh import check_surface, icosphere, signed_volume
from lungdeform.io import meshfile as lio
from lungdeform.io.meshfile import WRITE_SUFFIXES, load, load_surface, read_mesh, write_mesh

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
    # all labels as one mask: two large separate pieces (the right one 83 % of the left) are not
    # one lung, so the smaller is not dropped silently: refused, naming the file and the volumes
    with pytest.raises(MaskError, match="lobes.nii.gz: any non-zero label has 2 large separate components"):
        load(tmp_path / "lobes.nii.gz", smooth_iterations=0)
    with pytest.raises(InputError, match="units"):
        load(tmp_path / "lobes.nii.gz", units="m")


def test_load_unknown_and_missing(tmp_path):
    (tmp_path / "a.txt").write_text("x")
    with pytest.raises(ReadError, match=r"a\.txt: unknown format"):
        load(tmp_path / "a.txt")
    with pytest.raises(ReadError, match="no such file"):
        load(tmp_path / "nothing.nii.gz")


def test_stl_writer_refuses_vertices_it_would_weld(tmp_path):
    # two vertices 1e-7 mm apart are one float32 position: the STL would read back welded, as
    # another (here pinched) surface, so writing it is refused; OBJ keeps float64 and round-trips
    from tests.geometry.test_remesh import touching_poles

    v, f = touching_poles()
    with pytest.raises(MeshError, match=r"poles\.stl: 2 vertices share a float32 position"):
        write_mesh(tmp_path / "poles.stl", v, f)
    assert not (tmp_path / "poles.stl").exists()
    back, _ = load_surface(write_mesh(tmp_path / "poles.obj", v, f))
    assert len(back.vertices) == len(v)


def test_welded_stl_from_elsewhere_is_refused_in_one_line(tmp_path):
    # another program's STL of the same surface: its reader welds the two poles into a pinch
    from tests.geometry.test_remesh import touching_poles

    v, f = touching_poles()
    path = tmp_path / "other.stl"
    write_soup_stl(path, v[f])
    with pytest.raises(MeshError, match=r"other\.stl: surface is not 2-manifold") as info:
        load_surface(path)
    assert "\n" not in str(info.value)


def write_soup_stl(path, triangles):
    """A binary STL of ``triangles : (m, 3, 3)`` mm as any program writes it (float32 corners,
    zero normals), without lungdeform's checks."""
    import struct

    rec = np.zeros(len(triangles), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = triangles
    path.write_bytes(b"other".ljust(80, b" ") + struct.pack("<I", len(rec)) + rec.tobytes())
    return path
