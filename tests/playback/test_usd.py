"""Tests of lungdeform.playback.usd: OpenUSD / USDZ export, played back by usd-core in a fresh process and by Blender.

Truth throughout is lungdeform's own playback of the same curve, computed without the exporter: the
exact volume scales of :func:`lungdeform.playback.trajectory.lung_scales`, the lung's
:class:`~lungdeform.model.lung.Playback`, and the LPS → Y-up rotation written out by hand.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from lungdeform.errors import InputError, MissingDependencyError
from lungdeform.geometry.mesh import signed_volume
from lungdeform.playback import schedule as S
from lungdeform.playback import usd as U
from lungdeform.playback.trajectory import lung_scales
from tests.browser.support import REPO, embedded_lungs, two_lungs

pxr = pytest.importorskip("pxr", reason="usd-core is not installed (pip install 'lungdeform[usd]'; make test does)")

HERE = Path(__file__).resolve().parent
CODES = [0, 30, 60]  # time codes of the 30 Hz plain cycle: t = 0, 1, 2 s (rest, mid-inhalation, end-inhalation)
#: Blender as a Python module with its USD importer (make test installs it in .venv-blender/).
BPY_PYTHON = Path(os.environ.get("LUNGDEFORM_BPY_PYTHON", REPO / ".venv-blender" / "bin" / "python"))


@pytest.fixture(scope="module")
def model():
    return two_lungs(3)


@pytest.fixture(scope="module")
def lungs():
    # the embedded demo lungs (Coronacases 001, about 3,000 vertices each): the model users meet first
    return embedded_lungs()


def played_lps_mm(model, trace, times) -> dict[str, np.ndarray]:
    """Per lung ``(f, n, 3)`` mm LPS: lungdeform's own playback of ``trace`` at ``times`` (s)."""
    scales = lung_scales(model, trace.sample(times))
    out = {}
    for name, lung in model.lungs.items():
        pb = lung.playback(np.float64)
        out[name] = np.array([pb.seek(s).copy() for s in scales[name]])
    return out


def y_up_m(lps_mm: np.ndarray) -> np.ndarray:
    # the documented rotation, by hand: (X, Y, Z) = (x, z, -y) / 1000
    return np.stack([lps_mm[..., 0], lps_mm[..., 2], -lps_mm[..., 1]], axis=-1) / 1000


def run_usd_playback(path: Path, tmp_path: Path, codes=CODES) -> dict:
    out = tmp_path / f"{path.name}.json"
    res = subprocess.run([sys.executable, str(HERE / "usd_playback.py"), str(path), str(out), *map(str, codes)],
                         capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=600, check=False)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(out.read_text())


# --------------------------------------------------------------------------- frames
def test_even_curve_is_played_on_its_own_samples():
    trace = S.plain_cycle(500, 4.0)  # 121 samples, 30 Hz
    frames = U.usd_frames(trace)
    assert not frames.resampled and frames.fps == pytest.approx(30.0, rel=1e-12)
    np.testing.assert_array_equal(frames.volume_ml, trace.volume_ml)
    # a curve CSV rounded to 6 significant digits (what `breathe` writes) is still even
    rounded = S.VolumeTrace(np.array([float(f"{t:.6g}") for t in trace.t_s * 7.31]), trace.volume_ml)
    assert not U.usd_frames(rounded).resampled


def test_uneven_curve_or_fps_is_resampled():
    t = np.array([0.0, 0.5, 0.7, 2.0, 3.0])
    trace = S.VolumeTrace(t, np.array([0.0, 100.0, 150.0, 400.0, 0.0]))
    frames = U.usd_frames(trace)
    assert frames.resampled and frames.fps == pytest.approx(30.0) and len(frames.t_s) == 91
    np.testing.assert_allclose(frames.volume_ml, np.interp(frames.t_s, t, trace.volume_ml))  # linear, as glTF
    assert U.usd_frames(S.plain_cycle(500, 4.0), fps=10).fps == pytest.approx(10.0)
    assert len(U.usd_frames(S.plain_cycle(500, 4.0), fps=10).t_s) == 41


# --------------------------------------------------------------------------- layout
def test_stage_layout_blend_shapes_and_weights(model, tmp_path):
    from pxr import Usd, UsdGeom, UsdShade, UsdSkel

    trace = S.plain_cycle(500, 4.0)
    path = U.export_usd(model, tmp_path / "m.usda", trace)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/Lungs" and stage.GetDefaultPrim().IsA(UsdSkel.Root)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetTimeCodesPerSecond()) == (0, 120, 30)
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Lungs/Skeleton"))
    assert list(skel.GetJointsAttr().Get()) == ["root"]
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Lungs/Breathing"))
    assert list(anim.GetBlendShapesAttr().Get()) == ["left_tidal", "right_tidal"]
    assert anim.GetBlendShapeWeightsAttr().GetTimeSamples() == list(range(121))  # every frame, integer codes
    assert not any(p.GetTypeName().endswith("Light") for p in stage.Traverse())
    shares = S.lung_shares(model)
    for k, (name, lung) in enumerate(model.lungs.items()):
        prim = stage.GetPrimAtPath(f"/Lungs/{name}")
        mesh, binding = UsdGeom.Mesh(prim), UsdSkel.BindingAPI(prim)
        assert prim.HasAPI(UsdSkel.BindingAPI) and mesh.GetSubdivisionSchemeAttr().Get() == "none"
        np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get()), y_up_m(lung.surface.vertices), atol=1e-8)
        normals = np.array(mesh.GetNormalsAttr().Get())
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-6)
        # outward: the normals point away from the centroid on average (a rotation keeps the winding)
        assert np.mean(np.sum(normals * (y_up_m(lung.surface.vertices) - y_up_m(lung.surface.vertices).mean(0)), 1)) > 0
        np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), lung.surface.faces)
        assert list(binding.GetBlendShapesAttr().Get()) == [f"{name}_tidal"]
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(binding.GetBlendShapeTargetsRel().GetTargets()[0]))
        d_mm = lung.displacement * lung.calibration_ml / lung.unit_ml  # weight 1 = +calibration_ml
        np.testing.assert_allclose(np.array(shape.GetOffsetsAttr().Get()), y_up_m(d_mm), atol=1e-9)
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        shader = UsdShade.Shader(material.GetSurfaceOutput().GetConnectedSources()[0][0].source.GetPrim())
        assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
        # weights make each lung's volume its share of the curve exactly (measured on the mesh)
        for code in (0, 17, 60, 95):
            w = anim.GetBlendShapeWeightsAttr().Get(code)[k]
            vol = signed_volume(lung.surface.vertices + w * d_mm, lung.surface.faces) / 1000
            assert vol == pytest.approx(lung.volume_ee_ml + shares[name] * trace.volume_ml[code], rel=1e-6)


def test_usda_excerpt_of_the_embedded_demo(lungs, tmp_path):
    # the skeleton, a blend shape and the first weights as a reader sees them (printed for the docs)
    text = U.export_usd(lungs, tmp_path / "demo.usda", S.plain_cycle()).read_text()
    for needle in ('upAxis = "Y"', "metersPerUnit = 1", 'defaultPrim = "Lungs"', "timeCodesPerSecond = 30",
                   'def SkelRoot "Lungs"', 'def Skeleton "Skeleton"', 'uniform token[] joints = ["root"]',
                   'def SkelAnimation "Breathing"', 'uniform token[] blendShapes = ["left_tidal", "right_tidal"]',
                   "0: [0, 0],", 'def BlendShape "tidal"', "rel skel:blendShapeTargets = </Lungs/left/tidal>",
                   'uniform token subdivisionScheme = "none"', 'uniform token info:id = "UsdPreviewSurface"'):
        assert needle in text, needle
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if 'def Skeleton "Skeleton"' in ln)
    print("\n".join(ln[:160] for ln in lines[start:start + 16]))


# --------------------------------------------------------------------------- played by usd-core
@pytest.mark.parametrize("suffix, baked", [(".usda", False), (".usdc", False), (".usdz", False), (".usdc", True)])
def test_usd_core_plays_what_lungdeform_plays(lungs, tmp_path, suffix, baked):
    # a fresh process with usd-core alone skins the file (UsdSkel.BakeSkinning: blend shapes applied by
    # usd-core, not by us); its world positions at three time codes equal lungdeform's own playback of
    # the same curve (exact volume scales, Playback.seek) rotated to Y-up metres by hand, within 1e-6 m;
    # and every validator usd-core registers finds no error
    trace = S.plain_cycle(500, 4.0)
    path = U.export_usd(lungs, tmp_path / f"demo{suffix}", trace, baked=baked)
    got = run_usd_playback(path, tmp_path)
    assert got["skinned"] == ([] if baked else ["/Lungs"])
    assert (got["up_axis"], got["meters_per_unit"], got["default_prim"]) == ("Y", 1.0, "/Lungs")
    assert (got["start"], got["end"], got["time_codes_per_second"]) == (0, 120, 30)
    errors = [i for i in got["issues"] if "Error" in i["type"]]
    assert errors == [], errors
    expect = played_lps_mm(lungs, trace, np.array(CODES) / 30.0)
    worst = {}
    for name in lungs.lungs:
        pts = np.array(got["meshes"][name]["points_m"])
        worst[name] = np.abs(pts - y_up_m(expect[name])).max()
        assert worst[name] < 1e-6
        assert np.abs(pts[2] - pts[0]).max() > 5e-3  # it breathes: more than 5 mm at end-inhalation
    print(f"usd-core {got['usd_version']} {path.name}{' (baked)' if baked else ''}: largest difference "
          + ", ".join(f"{k} {v:.2e} m" for k, v in worst.items())
          + f"; {got['validators']} validators, {len(got['issues'])} issues")


def test_validators_catch_a_broken_binding(model, tmp_path):
    # the validation above can fail: the same file with one mesh's SkelBindingAPI removed is an error
    text = U.export_usd(model, tmp_path / "m.usda", S.plain_cycle()).read_text()
    broken = tmp_path / "broken.usda"
    broken.write_text(text.replace('prepend apiSchemas = ["MaterialBindingAPI", "SkelBindingAPI"]',
                                   'prepend apiSchemas = ["MaterialBindingAPI"]', 1))
    got = run_usd_playback(broken, tmp_path, [0])
    assert any("Error" in i["type"] and "SkelBindingAPI" in i["message"] for i in got["issues"]), got["issues"]


def _zip_entries(path: Path) -> list[tuple[str, int, int]]:
    # (name, compression method, data offset) from each local file header, read by hand
    data = path.read_bytes()
    out = []
    for info in zipfile.ZipFile(path).infolist():
        sig, method = struct.unpack_from("<IxxxxH", data, info.header_offset)
        assert sig == 0x04034B50
        name_len, extra_len = struct.unpack_from("<HH", data, info.header_offset + 26)
        out.append((info.filename, method, info.header_offset + 30 + name_len + extra_len))
    return out


def test_usdz_package(model, tmp_path):
    # ARKit's rules (usd-core's packager): first entry the .usdc layer, every entry stored (method 0,
    # no compression), its data 64-byte aligned
    path = U.export_usd(model, tmp_path / "lungs.usdz", S.plain_cycle())
    entries = _zip_entries(path)
    assert entries[0][0] == "lungs.usdc"
    for name, method, offset in entries:
        assert method == 0 and offset % 64 == 0, (name, method, offset)
    assert [p.name for p in tmp_path.iterdir()] == ["lungs.usdz"]  # no temporary layer left behind


# --------------------------------------------------------------------------- failures
def test_missing_usd_core_names_the_extra(model, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pxr", None)  # import pxr now raises ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install 'lungdeform\[usd\]'"):
        U.export_usd(model, tmp_path / "m.usdz")
    assert list(tmp_path.iterdir()) == []


def test_bad_suffix_and_failed_write_leave_nothing(model, tmp_path, monkeypatch):
    with pytest.raises(InputError, match=r"\.usd, \.usdc, \.usda, \.usdz"):
        U.export_usd(model, tmp_path / "m.glb")

    def boom(*_a, **_k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(U, "_write_layer", boom)
    for name in ("m.usdc", "m.usdz"):
        with pytest.raises(RuntimeError):
            U.export_usd(model, tmp_path / name)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_baked_size_estimate(model, tmp_path, suffix):
    # the estimate behind the 500 MB warning against the file written: crate stores each of the
    # symmetric breath's repeated shapes once (61 distinct of 121 frames), usda writes every frame as text
    trace = S.plain_cycle()
    path = U.export_usd(model, tmp_path / f"m{suffix}", trace, baked=True)
    estimate = U.baked_bytes(model, U.lung_weights(model, U.usd_frames(trace)), suffix)
    assert 0.85 * estimate < path.stat().st_size < 1.15 * estimate, (estimate, path.stat().st_size)


# --------------------------------------------------------------------------- played by Blender
def _blender_commands() -> list[tuple[str, list[str]]]:
    found = []
    if shutil.which("blender"):
        found.append(("blender", ["blender", "-b", "--factory-startup", "--python"]))
    if BPY_PYTHON.is_file():
        found.append(("bpy", [str(BPY_PYTHON)]))
    return found


def run_blender(command: list[str], path: Path, tmp_path: Path, rate: str, times) -> dict:
    out = tmp_path / f"{path.name}.blender.json"
    res = subprocess.run([*command, str(REPO / "tests" / "browser" / "blender_import.py"), "--", str(path), str(out),
                          rate, *map(str, times)], capture_output=True, text=True, encoding="utf-8",
                         errors="replace", timeout=600, check=False)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    if not out.exists():
        return json.loads(next(ln for ln in res.stdout.splitlines() if ln.startswith("RESULT "))[7:])
    return json.loads(out.read_text())


@pytest.mark.parametrize("suffix, baked", [(".usdc", False), (".usdz", False), (".usdc", True)],
                         ids=["usdc-blend-shapes", "usdz-blend-shapes", "usdc-baked"])
@pytest.mark.parametrize("which", ["blender", "bpy"])
def test_usd_in_blender(lungs, tmp_path, which, suffix, baked):
    # Blender's USD importer (headless), frames at the file's time codes: every vertex's world position
    # (Blender is Z up: world = LPS / 1000 after its Y-up conversion) within 1e-4 m of lungdeform's playback
    commands = dict(_blender_commands())
    if which not in commands:
        pytest.skip("Debian's blender is not installed (make test installs it as root)" if which == "blender" else
                    f"{BPY_PYTHON} missing: Blender as a module (bpy, requirements-blender.lock; make test installs it)")
    trace = S.plain_cycle(500, 4.0)
    path = U.export_usd(lungs, tmp_path / f"demo{suffix}", trace, baked=baked)
    times = np.array(CODES) / 30.0
    got = run_blender(commands[which], path, tmp_path, "30", times)
    if not got["usd_built"]:
        pytest.skip(f"Blender {got['blender']} ({which}) is built without USD (bpy.app.build_options.usd is False): "
                    "it imports no USD file; the USD import is tested with Blender as a module (bpy)")
    assert got["frames"] == CODES
    expect = played_lps_mm(lungs, trace, times)
    worst = {}
    for name, lung in lungs.lungs.items():
        mesh = got["meshes"][name]
        assert mesh["vertices"] == lung.n_vertices and mesh["faces"] == len(lung.surface.faces)
        if not baked:
            assert mesh["shape_keys"] == ["Basis", f"{name}_tidal"]
        pts = np.array(mesh["world_m"])
        worst[name] = np.abs(pts - expect[name] / 1000).max()
        assert worst[name] < 1e-4
        assert np.abs(pts[2] - pts[0]).max() > 5e-3
    print(f"Blender {got['blender']} USD import of {path.name}{' (baked)' if baked else ' (blend shapes)'}: "
          "largest difference " + ", ".join(f"{k} {v:.2e} m" for k, v in worst.items()))
