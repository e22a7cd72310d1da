"""Tests of lungdeform.playback.export: glTF binary (morph targets, animation, extras) and the VTK time series."""

from __future__ import annotations

import json
import os
import stat
import struct
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from lungdeform.geometry.mesh import signed_volume
from lungdeform.model.displacement import volume_tensors
from lungdeform.playback import export as E
from lungdeform.playback import markers as M
from lungdeform.playback import schedule as S
from tests.browser.support import node_modules_or_skip, run_node, two_lungs
from tests.playback.test_markers import INTERIOR, _marker_at


@pytest.fixture(scope="module")
def model():
    return two_lungs(3)


def _glb_json(data: bytes) -> tuple[dict, bytes]:
    # the GLB container by hand (independent of pygltflib): header, JSON chunk, BIN chunk
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    jlen, jtype = struct.unpack_from("<I4s", data, 12)
    assert jtype == b"JSON"
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack_from("<I4s", data, 20 + jlen)
    assert btype == b"BIN\0"
    return doc, data[28 + jlen:28 + jlen + blen]


def _accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {5126: np.float32, 5125: np.uint32}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    a = np.frombuffer(blob, dtype, acc["count"] * width, view.get("byteOffset", 0) + acc.get("byteOffset", 0))
    return a.reshape(acc["count"], width) if width > 1 else a


def test_basis_targets_recombine_to_the_tidal_target(model):
    # a built model's displacement is the calibrated recombination of the basis, so the least-squares
    # factor reproduces target 0 exactly (up to rounding) with the model's own force weights
    for lung in model.lungs.values():
        targets, kappa = E.lung_targets(lung)
        recombined = np.tensordot(lung.force_weights, targets[1:], axes=1)
        np.testing.assert_allclose(recombined, targets[0], atol=1e-9 * np.abs(targets[0]).max())
        assert kappa > 0


def test_tidal_weights_give_exact_volumes(model):
    # truth: the enclosed volume of p + λ·T0 measured directly
    lung = model.lungs["right"]
    targets, _ = E.lung_targets(lung)
    dv = np.array([-40.0, 0.0, 125.0, 250.0, 600.0])
    for d, lam in zip(dv, E.tidal_weights(lung, dv)):
        v = signed_volume(lung.surface.vertices + lam * targets[0], lung.surface.faces) / 1000
        assert v == pytest.approx(lung.volume_ee_ml + d, rel=1e-9)
    # at the calibration volume the exact weight is 1 (the linear reading is exact there)
    assert E.tidal_weights(lung, [lung.calibration_ml])[0] == pytest.approx(1.0, rel=1e-9)


def test_glb_layout_and_animation(model, tmp_path):
    trace = S.plain_cycle(500, 4.0)
    path = E.export_glb(model, tmp_path / "m.glb", trace)
    doc, blob = _glb_json(path.read_bytes())
    meta = doc["extras"]["lungdeform"]
    assert meta["schema"] == "lungdeform.glb" and meta["lungs"] == ["left", "right"]
    root = doc["nodes"][doc["scenes"][0]["nodes"][0]]
    assert root["scale"] == [0.001] * 3
    # root rotation maps LPS (x, y, z) to glTF (x, z, -y): check on the basis vectors
    qx, qy, qz, qw = root["rotation"]
    r = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
                  [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
                  [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 1, 0], atol=1e-12)  # head is up
    np.testing.assert_allclose(r @ [0, -1, 0], [0, 0, 1], atol=1e-12)  # anterior is +Z (forward)
    np.testing.assert_allclose(r, E.LPS_TO_Y_UP, atol=1e-12)  # the one rotation USD applies to its points
    shares = S.lung_shares(model)
    times = _accessor(doc, blob, doc["animations"][0]["samplers"][0]["input"])
    np.testing.assert_allclose(times, trace.t_s, rtol=1e-6)
    for mi, mesh in enumerate(doc["meshes"]):
        name = mesh["name"]
        lung = model.lungs[name]
        prim = mesh["primitives"][0]
        pos = _accessor(doc, blob, prim["attributes"]["POSITION"])
        np.testing.assert_allclose(pos, lung.surface.vertices, rtol=1e-6)  # topology and positions once
        nrm = _accessor(doc, blob, prim["attributes"]["NORMAL"])
        np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-6)
        faces = _accessor(doc, blob, prim["indices"]).reshape(-1, 3)
        np.testing.assert_array_equal(faces, lung.surface.faces)
        assert len(prim["targets"]) == 5 and mesh["extras"]["targetNames"] == list(E.TARGET_NAMES)
        t0 = _accessor(doc, blob, prim["targets"][0]["POSITION"])
        np.testing.assert_allclose(t0, lung.displacement * lung.calibration_ml / lung.unit_ml, rtol=1e-5,
                                   atol=1e-5)
        # animation: weights (k, 5) on this node give the curve's volume share exactly
        ch = next(c for c in doc["animations"][0]["channels"] if doc["nodes"][c["target"]["node"]]["name"] == name)
        assert ch["target"]["path"] == "weights"
        w = _accessor(doc, blob, doc["animations"][0]["samplers"][ch["sampler"]]["output"]).reshape(-1, 5)
        assert np.all(w[:, 1:] == 0)
        for k in (0, 30, 60):  # t = 0, 1, 2 s
            v = signed_volume(lung.surface.vertices + float(w[k, 0]) * t0.astype(float), lung.surface.faces)
            assert v / 1000 == pytest.approx(lung.volume_ee_ml + shares[name] * trace.volume_ml[k], rel=1e-6)
        ex = mesh["extras"]["lungdeform"]
        assert ex["share"] == pytest.approx(0.5) and "supine" in ex["orientations"]


def test_glb_passes_khronos_validator(model, tmp_path):
    viewer = node_modules_or_skip("gltf-validator")
    path = tmp_path / "m.glb"
    anchors = M.marker_anchors(model, np.array([[90.0, 0.0, 0.0], [-90.0, 10.0, 100.0]]), ["tumour", "apex"])
    E.export_glb(model, path, S.plain_cycle(), anchors)
    res = run_node(["scripts/validate-glb.mjs", str(path)], cwd=viewer)
    report = json.loads(res.stdout)
    issues = report["issues"]
    print(f"gltf-validator {report['validatorVersion']}: {issues['numErrors']} errors, "
          f"{issues['numWarnings']} warnings, {issues['numInfos']} infos, {issues['numHints']} hints; "
          f"{path.stat().st_size} bytes")
    assert res.returncode == 0 and issues["numErrors"] == 0, issues["messages"]
    assert issues["numWarnings"] == 0, issues["messages"]
    assert report["info"]["hasMorphTargets"] and report["info"]["animationCount"] == 1


def test_glb_in_threejs_gltfloader(model, tmp_path):
    # three.js's GLTFLoader + AnimationMixer in node (viewer/tests/gltf.test.ts) against Python's numbers
    viewer = node_modules_or_skip("three", "vitest")
    from lungdeform.playback.trajectory import place_points, point_trajectories

    trace = S.plain_cycle(500, 4.0)
    path = E.export_glb(model, tmp_path / "m.glb", trace, M.marker_anchors(model, INTERIOR, list("abcd")))
    shares = S.lung_shares(model)
    times = [0.0, 0.5, 1.0, 2.0, 3.3]  # key frames of the 30 Hz plain cycle
    track = point_trajectories(model, INTERIOR, place_points(model, INTERIOR), trace.sample(times))
    expect = {"times": times, "lungs": {},
              "markers": [{"label": lab, "lung": str(lung), "positions": track[:, j].tolist()}
                          for j, (lab, lung) in enumerate(zip("abcd", place_points(model, INTERIOR).lungs))]}
    for name, lung in model.lungs.items():
        dv = shares[name] * trace.sample(times)
        targets, _ = E.lung_targets(lung)
        a0, a1, a2, a3 = volume_tensors(lung.surface.vertices, lung.surface.faces, targets[1:])
        table = E.orientation_table(lung, a1, a2, a3)
        expect["lungs"][name] = {"weights": E.tidal_weights(lung, dv).tolist(),
                                 "volume_ml": (lung.volume_ee_ml + dv).tolist(),
                                 "orientations": {k: v["basis_weights"] for k, v in table.items()}}
    (tmp_path / "expect.json").write_text(json.dumps(expect))
    res = run_node([str(viewer / "node_modules/vitest/vitest.mjs"), "run", "tests/gltf.test.ts"], cwd=viewer,
                   env={"LUNGDEFORM_GLB": str(path), "LUNGDEFORM_EXPECT": str(tmp_path / "expect.json"),
                        "NO_COLOR": "1"})
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "4 passed" in res.stdout, res.stdout[-2000:]


def test_glb_markers_follow_track_over_the_animation(model, tmp_path):
    # truth: lungdeform.playback.trajectory (what `lungdeform track` writes) at the curve's volumes; the glb
    # carries float32 animation weights, so agreement is to ~1e-6 of the motion
    from lungdeform.playback.trajectory import place_points, point_trajectories

    trace = S.plain_cycle(500, 4.0)
    doc, blob = _glb_json(E.glb_bytes(model, trace, M.marker_anchors(model, INTERIOR)))
    meta = doc["extras"]["lungdeform"]
    assert meta["schema_version"] == E.GLB_SCHEMA_VERSION == 2 and "tidal_mm" in meta["marker_motion"]
    markers = meta["markers"]
    assert all("vertices" not in m and len(m["tidal_mm"]) == 3 for m in markers)
    track = point_trajectories(model, INTERIOR, place_points(model, INTERIOR), trace.volume_ml)  # (k, 4, 3)
    weights = {}
    for ch in doc["animations"][0]["channels"]:
        w = _accessor(doc, blob, doc["animations"][0]["samplers"][ch["sampler"]]["output"]).reshape(-1, 5)
        weights[doc["nodes"][ch["target"]["node"]]["name"]] = w[:, 0].astype(float)
    for j, m in enumerate(markers):
        got = np.array([_marker_at(m, lam) for lam in weights[m["lung"]]])
        np.testing.assert_allclose(got, track[:, j], atol=1e-4)
        assert np.ptp(got, axis=0).max() > 1.0  # mm: it does move


def _read_vtp(path):
    # VTK XML PolyData with raw appended data (UInt64 block headers) read by hand
    raw = path.read_bytes()
    head, _, tail = raw.partition(b'<AppendedData encoding="raw">\n_')
    root = ET.fromstring(head.decode() + "</VTKFile>")
    arrays = {}
    types = {"Float32": np.float32, "Float64": np.float64, "Int64": np.int64, "Int32": np.int32}
    for da in root.iter("DataArray"):
        off = int(da.get("offset"))
        n = struct.unpack_from("<Q", tail, off)[0]
        a = np.frombuffer(tail, types[da.get("type")], n // np.dtype(types[da.get("type")]).itemsize, off + 8)
        comps = int(da.get("NumberOfComponents", "1"))
        arrays[da.get("Name")] = a.reshape(-1, comps) if comps > 1 else a
    return arrays


def test_pvd_time_series(model, tmp_path):
    trace = S.plain_cycle(500, 4.0)
    path = E.export_pvd(model, tmp_path / "series.pvd", trace, fps=5)
    entries = ET.parse(path).getroot().find("Collection").findall("DataSet")
    assert len(entries) == 2 * 21  # 2 lungs × (4 s × 5 fps + 1)
    shares = S.lung_shares(model)
    for e in entries:
        f = tmp_path / e.get("file")
        a = _read_vtp(f)
        lung = model.lungs[e.get("name")]
        t = float(e.get("timestep"))
        assert a["TimeValue"][0] == pytest.approx(t, abs=1e-6)
        np.testing.assert_array_equal(a["connectivity"].reshape(-1, 3), lung.surface.faces)
        np.testing.assert_allclose(a["Points"], lung.surface.vertices + a["displacement_mm"], atol=1e-4)
        vol = signed_volume(a["Points"].astype(float), lung.surface.faces) / 1000
        assert vol == pytest.approx(lung.volume_ee_ml + shares[lung.side] * trace.sample(t), rel=1e-5)
    # a second export replaces the frames folder: no stale or temporary files are left
    E.export_pvd(model, path, S.plain_cycle(500, 2.0), fps=5)
    assert len(list((tmp_path / "series_frames").iterdir())) == 2 * 11
    assert sorted(p.name for p in tmp_path.iterdir()) == ["series.pvd", "series_frames"]


def test_pvd_frames_folder_follows_the_umask(model, tmp_path):
    # every other output is created with the umask's permissions; the frames folder was a
    # tempfile.mkdtemp renamed into place and kept its 0700 (others could read the .pvd, not its frames)
    old = os.umask(0o022)
    try:
        path = E.export_pvd(model, tmp_path / "s.pvd", S.plain_cycle(500, 1.0), fps=2)
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "s_frames").stat().st_mode) == 0o755  # 0o777 & ~0o022, as mkdir
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_pvd_frames_readable_by_lungdeform_io(model, tmp_path):
    io = pytest.importorskip("lungdeform.io.meshfile")  # an independent .vtp reader, when present
    path = E.export_pvd(model, tmp_path / "s.pvd", S.plain_cycle(500, 1.0), fps=2)
    v, f = io.read_mesh(tmp_path / "s_frames" / "left_0001.vtp")
    lung = model.lungs["left"]
    np.testing.assert_array_equal(f, lung.surface.faces)
    assert signed_volume(np.asarray(v, float), f) / 1000 > lung.volume_ee_ml
    assert path.exists()


def test_failed_export_leaves_nothing(model, tmp_path, monkeypatch):
    def boom(*_a, **_k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(E, "vtp_bytes", boom)
    with pytest.raises(RuntimeError):
        E.export_pvd(model, tmp_path / "s.pvd")
    monkeypatch.setattr(E, "glb_bytes", boom)
    with pytest.raises(RuntimeError):
        E.export_glb(model, tmp_path / "m.glb")
    assert list(tmp_path.iterdir()) == []


def test_glb_in_blender(tmp_path):
    # Blender's own glTF importer and animation evaluation (Debian's blender, which make test installs):
    # shape keys named after the targets, one action per lung; the enclosed volume at t follows the
    # curve, and every vertex's world position (Blender is Z up: the glTF Y-up metres come back as LPS
    # / 1000) is within 1e-4 m of lungdeform's own playback (exact volume scales, Playback.seek)
    import shutil
    import subprocess

    from lungdeform.playback.trajectory import lung_scales
    from tests.browser.support import REPO, embedded_lungs

    if shutil.which("blender") is None:
        pytest.skip("blender is not installed (make test installs Debian's blender and python3-numpy as root)")
    model = embedded_lungs()
    trace = S.plain_cycle(500, 4.0)
    path = E.export_glb(model, tmp_path / "m.glb", trace)
    times = [0.0, 1.0, 2.0]
    out = tmp_path / "blender.json"
    res = subprocess.run(["blender", "-b", "--factory-startup", "--python",
                          str(REPO / "tests" / "browser" / "blender_import.py"), "--", str(path), str(out), "scene",
                          *map(str, times)], capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=300,
                         check=False)
    assert res.returncode == 0 and out.exists(), res.stdout[-2000:] + res.stderr[-2000:]
    got = json.loads(out.read_text())
    assert len(got["actions"]) == 2
    shares = S.lung_shares(model)
    scales = lung_scales(model, trace.sample(times))
    worst = {}
    for name, lung in model.lungs.items():
        mesh = got["meshes"][name]
        assert mesh["vertices"] == lung.n_vertices and mesh["faces"] == len(lung.surface.faces)
        assert mesh["shape_keys"] == ["Basis", *E.TARGET_NAMES]
        expected = lung.volume_ee_ml + shares[name] * trace.sample(times)
        np.testing.assert_allclose(np.array(mesh["volume_mm3"]) / 1000, expected, rtol=1e-5)
        pb = lung.playback(np.float64)
        expect_m = np.array([pb.seek(s).copy() for s in scales[name]]) / 1000
        pts = np.array(mesh["world_m"])
        worst[name] = np.abs(pts - expect_m).max()
        assert worst[name] < 1e-4
        assert np.abs(pts[2] - pts[0]).max() > 5e-3  # it breathes: more than 5 mm at end-inhalation
    print(f"Blender {got['blender']} glTF import of the embedded lungs: largest difference "
          + ", ".join(f"{k} {v:.2e} m" for k, v in worst.items()))


def test_provenance_with_nan_exports_as_strict_json(tmp_path):
    # a fitted model's provenance holds NaN (e.g. no landmark error without landmarks): the glb's
    # JSON and the model file's provenance must still be strict JSON (null), or glTF readers fail
    from lungdeform.io.modelfile import load_model, save_model
    from lungdeform.model.lung import Model

    m = two_lungs(2)
    nan_model = Model(dict(m.lungs), {"fit": {"landmark_rms_in_fit_mm": float("nan"), "objective": 1.5}})
    doc, _ = _glb_json(E.glb_bytes(nan_model, S.plain_cycle()))
    fit = doc["extras"]["lungdeform"]["provenance"]["fit"]  # (the glTF writer drops null members)
    assert fit.get("landmark_rms_in_fit_mm") is None and fit["objective"] == 1.5
    back = load_model(save_model(tmp_path / "nan.npz", nan_model))
    assert back.provenance["fit"]["landmark_rms_in_fit_mm"] is None


def test_an_end_inhale_model_is_exported_at_end_exhale_with_its_scan_weight(model, tmp_path):
    # why: a glb's POSITION is end-exhale and its weights start there (viewers play 0 … 1); a model
    # built from an end-inhale scan is written moved down to end-exhale, exactly by the volume cubic:
    # truths: POSITION encloses the scan's volume less the lung's share of 500 mL; POSITION plus
    # scan_weight times target 0 is the scan; the animation's volumes are the curve's above end-exhale
    from lungdeform.model.lung import Model
    from lungdeform.model.scan_state import ScanState
    inhaled = Model(model.lungs, model.provenance, ScanState("end-inhale", 500.0))
    trace = S.plain_cycle(500, 4.0)
    pts = np.array([[90.0, 0.0, 0.0], [-90.0, 10.0, 20.0]])
    doc, blob = _glb_json(E.glb_bytes(inhaled, trace, M.marker_anchors(inhaled, pts)))
    assert doc["extras"]["lungdeform"]["scan_state"]["above_end_exhale_ml"] == 500.0
    weight = {m["name"]: m["extras"]["lungdeform"]["scan_weight"] for m in doc["meshes"]}
    for p, marker in zip(pts, doc["extras"]["lungdeform"]["markers"]):  # moved down with their lung
        at_scan = np.add(marker["position_mm"], weight[marker["lung"]] * np.asarray(marker["tidal_mm"]))
        np.testing.assert_allclose(at_scan, p, atol=1e-9)
    shares = S.lung_shares(inhaled)
    for mesh in doc["meshes"]:
        lung, ex = inhaled.lungs[mesh["name"]], mesh["extras"]["lungdeform"]
        prim = mesh["primitives"][0]
        pos = _accessor(doc, blob, prim["attributes"]["POSITION"]).astype(float)
        t0 = _accessor(doc, blob, prim["targets"][0]["POSITION"]).astype(float)
        ee_ml = lung.volume_ee_ml - shares[mesh["name"]] * 500.0
        assert signed_volume(pos, lung.surface.faces) / 1000 == pytest.approx(ee_ml, rel=1e-5)
        assert ex["volume_ee_ml"] == pytest.approx(ee_ml, rel=1e-9) and ex["scan_weight"] > 0
        np.testing.assert_allclose(pos + ex["scan_weight"] * t0, lung.surface.vertices, atol=2e-3)
        ch = next(c for c in doc["animations"][0]["channels"] if doc["nodes"][c["target"]["node"]]["name"] == mesh["name"])
        w = _accessor(doc, blob, doc["animations"][0]["samplers"][ch["sampler"]]["output"]).reshape(-1, 5)
        assert w[0, 0] == pytest.approx(0.0, abs=1e-7) and w[60, 0] == pytest.approx(ex["scan_weight"], rel=1e-5)
