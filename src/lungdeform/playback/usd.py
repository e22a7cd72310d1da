"""Export a lung model as OpenUSD (``.usd``, ``.usdc``, ``.usda``) or USDZ, for Apple AR, Omniverse and film tools.

The motion of a lung is ``x(t) = p + λ(t)·d`` per vertex: one blend shape driven by one weight over time,
which is how the file carries it (UsdSkel), not a vertex cache. Written with usd-core (the optional extra
``usd``: ``pip install 'lungdeform[usd]'``).

Stage (docs/VIEWER.md, "OpenUSD and USDZ")
------------------------------------------
- Metadata: ``upAxis = "Y"``, ``metersPerUnit = 1``, ``defaultPrim = "Lungs"``; ``startTimeCode = 0``,
  ``endTimeCode = k − 1``, ``timeCodesPerSecond = framesPerSecond = fps`` (time code ``i`` is frame ``i``
  of the curve, at ``t = i/fps`` s); ``customLayerData["lungdeform"]``: schema, frame, the curve played.
- Vertex data are **metres, Y up**: patient LPS millimetres go through the one rotation of the glTF
  export (:data:`lungdeform.playback.export.LPS_TO_Y_UP`): ``(X, Y, Z) = 0.001 · (x, z, −y)`` (head up,
  anterior toward +Z); here it is applied to the points, so no prim has a transform.
- ``/Lungs`` (``SkelRoot``, kind ``component``):

  - ``Skeleton``: one joint ``root``, identity bind and rest transforms, ``skel:animationSource`` →
    ``Breathing``;
  - ``Breathing`` (``SkelAnimation``): the joint's identity transform, ``blendShapes = [left_tidal,
    right_tidal]`` and ``blendShapeWeights`` sampled at every integer time code: ``[λ_left(t_i), λ_right(t_i)]``
    with ``λ`` the weight that makes the lung's volume exactly ``V_EE + share · ΔV(t_i)``
    (:func:`lungdeform.playback.export.tidal_weights`; ``λ = 1`` is ``+calibration_ml``);
  - ``left``, ``right`` (``Mesh``, ``SkelBindingAPI``): end-exhale ``points`` (point3f), ``normals``
    (vertex), triangles, ``subdivisionScheme = "none"``, ``extent`` over the whole breath, rigidly bound to
    the joint (``jointIndices [0]``, ``jointWeights [1]``, constant), ``skel:blendShapes =
    [<lung>_tidal]`` → child ``tidal`` (``BlendShape``): ``offsets`` = the lung's tidal target
    ``d = u · calibration_ml/unit_ml`` in metres (the glb's morph target 0), every point;
    ``customData["lungdeform"]``: side, share, volumes, calibration;
  - ``Materials``: one ``UsdPreviewSurface`` material per lung (no textures, no lights).

- ``baked=True``: no skeleton; ``/Lungs`` is an ``Xform`` and each ``Mesh`` has ``points`` (and
  ``extent``) time-sampled at every time code, a vertex cache (:data:`BAKED_WARN_BYTES`).
- USDZ: the stage is written as ``<stem>.usdc`` and packaged by usd-core's ARKit packager
  (``UsdUtils.CreateNewARKitUsdzPackage``): first layer ``.usdc``, entries stored uncompressed and
  64-byte aligned.

Frames: a curve whose samples are evenly spaced (within 1 % of a frame) is played on its own samples,
``fps = (k − 1)/duration``; any other curve, or any curve with ``fps`` given, is sampled by linear
interpolation at ``fps`` (:func:`usd_frames`).
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from lungdeform import __version__
from lungdeform.atomic import atomic_path
from lungdeform.errors import InputError, LungdeformError, MissingDependencyError
from lungdeform.model.displacement import tidal_displacement
from lungdeform.model.lung import LungModel, Model

from .export import LPS_TO_Y_UP, frame_times, lps_to_y_up_m, lung_normals, lung_units, tidal_weights
from .schedule import VolumeTrace, lung_shares, plain_cycle

USD_SCHEMA = "lungdeform.usd"
USD_SCHEMA_VERSION = 1
#: The file suffixes the exporter writes (``.usd`` is binary crate, as ``.usdc``).
USD_SUFFIXES = (".usd", ".usdc", ".usda", ".usdz")
#: A baked file (vertex cache) past this size is worth a warning: the blend-shape file is a few MB.
BAKED_WARN_BYTES = 500_000_000
#: A curve is played on its own samples when each lies within this fraction of a frame of an even grid.
EVEN_TOLERANCE = 0.01
#: Frames per second a curve with uneven samples is resampled at, unless ``fps`` is given.
DEFAULT_FPS = 30.0
ROOT = "/Lungs"
JOINT = "root"
COLORS = {"left": (0.93, 0.55, 0.55), "right": (0.55, 0.7, 0.93)}


def require_usd() -> SimpleNamespace:
    """The usd-core modules the exporter uses (``Gf, Kind, Sdf, Tf, Usd, UsdGeom, UsdShade, UsdSkel,
    UsdUtils, Vt``), or :class:`MissingDependencyError` naming the extra."""
    try:
        from pxr import Gf, Kind, Sdf, Tf, Usd, UsdGeom, UsdShade, UsdSkel, UsdUtils, Vt
    except ImportError as exc:
        raise MissingDependencyError("USD export needs usd-core, the optional extra 'usd': "
                                     "pip install 'lungdeform[usd]'") from exc
    return SimpleNamespace(Gf=Gf, Kind=Kind, Sdf=Sdf, Tf=Tf, Usd=Usd, UsdGeom=UsdGeom, UsdShade=UsdShade,
                           UsdSkel=UsdSkel, UsdUtils=UsdUtils, Vt=Vt)


@dataclass(frozen=True)
class UsdFrames:
    """The frames a USD file plays: time code ``i`` at ``t_s[i] = i/fps``.

    t_s : (k,) float, s, from 0; volume_ml : (k,) float, mL, both lungs above end-exhale; fps : float,
    time codes (frames) per second; resampled : whether the curve was interpolated (uneven samples,
    or ``fps`` asked for) rather than played on its own samples.
    """

    t_s: np.ndarray
    volume_ml: np.ndarray
    fps: float
    resampled: bool


def usd_frames(trace: VolumeTrace, fps: float | None = None) -> UsdFrames:
    """The frames of ``trace`` at integer time codes: its own samples when they are evenly spaced (within
    :data:`EVEN_TOLERANCE` of a frame) and ``fps`` is None, else linear interpolation at ``fps`` frames per
    second (:data:`DEFAULT_FPS` when None) over the whole trace (:func:`lungdeform.playback.export.frame_times`)."""
    t = np.asarray(trace.t_s, float) - trace.t_s[0]
    duration = float(t[-1])
    n = len(t) - 1
    even = np.linspace(0.0, duration, n + 1)
    if fps is None and np.max(np.abs(t - even)) <= EVEN_TOLERANCE * duration / n:
        return UsdFrames(even, np.asarray(trace.volume_ml, float), n / duration, False)
    times = frame_times(trace, DEFAULT_FPS if fps is None else fps)
    return UsdFrames(times - times[0], trace.sample(times), (len(times) - 1) / duration, True)


#: Bytes per point per frame of a baked file: crate (``.usd``, ``.usdc``, ``.usdz``) stores float32
#: triples; ``.usda`` writes them as text (about 42 characters each, measured on the embedded lungs).
BAKED_POINT_BYTES = {"crate": 12, "text": 42}


def baked_bytes(model: Model, weights: dict[str, np.ndarray], suffix: str) -> int:
    """About the size (bytes) of the baked file ``suffix`` for the frames' ``weights``
    (:func:`lung_weights`): the points of every vertex at every frame. Crate stores an array once however
    many frames repeat it (a symmetric breath plays each shape twice), so it counts distinct float32 weights."""
    text = suffix.lower() == ".usda"
    per_point = BAKED_POINT_BYTES["text" if text else "crate"]
    return sum(per_point * lung.n_vertices * (len(weights[name]) if text else len(np.unique(weights[name].astype(np.float32))))
               for name, lung in model.lungs.items())


def lung_weights(model: Model, frames: UsdFrames) -> dict[str, np.ndarray]:
    """Per lung, ``λ : (k,) float``: the weight of its tidal blend shape at each frame (volume exact)."""
    shares = lung_shares(model)
    return {name: tidal_weights(lung, shares[name] * frames.volume_ml) for name, lung in model.lungs.items()}


def _vec3f(pxr, a: np.ndarray):
    return pxr.Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, np.float32))


def _extent(pxr, lo: np.ndarray, hi: np.ndarray):
    return pxr.Vt.Vec3fArray([pxr.Gf.Vec3f(*map(float, lo)), pxr.Gf.Vec3f(*map(float, hi))])


def _stage_metadata(pxr, stage, frames: UsdFrames, trace: VolumeTrace, baked: bool) -> None:
    UsdGeom = pxr.UsdGeom
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(len(frames.t_s) - 1)
    stage.SetTimeCodesPerSecond(frames.fps)
    stage.SetFramesPerSecond(frames.fps)
    stage.SetMetadata("comment", f"lungdeform {__version__}: breathing lungs ({'vertex cache' if baked else 'blend shapes'})")
    stage.GetRootLayer().customLayerData = {"lungdeform": {
        "schema": USD_SCHEMA, "schema_version": USD_SCHEMA_VERSION, "generator": f"lungdeform {__version__}",
        "frame": "metres, Y up: (X, Y, Z) = 0.001 * (x, z, -y) of patient LPS mm (the glTF export's rotation)",
        "lps_to_y_up": pxr.Gf.Matrix3d(*LPS_TO_Y_UP.ravel().tolist()),
        "motion": "baked points per time code" if baked else
                  "points + w * tidal offsets; w = Breathing.blendShapeWeights, volume exact per frame",
        "curve_source": trace.source, "curve_shifted_ml": float(trace.shifted_ml),
        "resampled": bool(frames.resampled),
        "t_s": pxr.Vt.DoubleArray(frames.t_s.tolist()), "volume_ml": pxr.Vt.DoubleArray(frames.volume_ml.tolist()),
        "meaning": "volume_ml: both lungs above end-exhale at time code i (t_s[i]); each lung takes 'share' of it",
    }}


def _material(pxr, stage, name: str, lung: LungModel):
    """A ``UsdPreviewSurface`` material for one lung under ``/Lungs/Materials``."""
    UsdShade, Sdf = pxr.UsdShade, pxr.Sdf
    mat = UsdShade.Material.Define(stage, f"{ROOT}/Materials/{name}_tissue")
    shader = UsdShade.Shader.Define(stage, f"{mat.GetPath()}/PreviewSurface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(pxr.Gf.Vec3f(*COLORS.get(lung.side, (0.8, 0.6, 0.6))))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return mat


def _mesh(pxr, stage, name: str, lung: LungModel, share: float):
    """The lung's ``Mesh`` at end-exhale (metres, Y up): topology, normals, material, lungdeform data."""
    UsdGeom = pxr.UsdGeom
    mesh = UsdGeom.Mesh.Define(stage, f"{ROOT}/{name}")
    f = lung.surface.faces
    mesh.CreatePointsAttr(_vec3f(pxr, lps_to_y_up_m(lung.surface.vertices)))
    mesh.CreateFaceVertexCountsAttr(pxr.Vt.IntArray.FromNumpy(np.full(len(f), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(pxr.Vt.IntArray.FromNumpy(np.ascontiguousarray(f, np.int32).ravel()))
    mesh.CreateNormalsAttr(_vec3f(pxr, lung_normals(name, lung) @ LPS_TO_Y_UP.T))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateDoubleSidedAttr(False)
    pxr.UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(_material(pxr, stage, name, lung))
    mesh.GetPrim().SetCustomDataByKey("lungdeform", {
        "lung": name, "side": lung.side, "n_vertices": int(lung.n_vertices), "share": float(share),
        "calibration_ml": float(lung.calibration_ml), "unit_ml": float(lung.unit_ml),
        "volume_ee_ml": float(lung.volume_ee_ml), "blend_shape": f"{name}_tidal",
        "tidal_offsets": "d = u * calibration_ml / unit_ml (m): weight 1 adds calibration_ml",
    })
    return mesh


def _skinned_lung(pxr, stage, name: str, lung: LungModel, share: float, lam: np.ndarray) -> None:
    """One lung as a skinned mesh with its tidal blend shape (see the module docstring)."""
    UsdSkel, Sdf = pxr.UsdSkel, pxr.Sdf
    mesh = _mesh(pxr, stage, name, lung, share)
    p = lps_to_y_up_m(lung.surface.vertices)
    d = lps_to_y_up_m(tidal_displacement(lung.displacement, lung_units(lung)))
    ends = np.concatenate([p + float(lam.min()) * d, p + float(lam.max()) * d])  # linear in λ: the box's corners
    mesh.CreateExtentAttr(_extent(pxr, ends.min(axis=0), ends.max(axis=0)))
    shape = UsdSkel.BlendShape.Define(stage, f"{mesh.GetPath()}/tidal")
    shape.CreateOffsetsAttr(_vec3f(pxr, d))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([Sdf.Path(f"{ROOT}/Skeleton")])
    binding.CreateJointIndicesPrimvar(constant=True, elementSize=1).Set(pxr.Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(constant=True, elementSize=1).Set(pxr.Vt.FloatArray([1.0]))
    binding.CreateGeomBindTransformAttr(pxr.Gf.Matrix4d(1.0))
    binding.CreateBlendShapesAttr(pxr.Vt.TokenArray([f"{name}_tidal"]))
    binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])


def _skeleton(pxr, stage, weights: dict[str, np.ndarray]) -> None:
    """The one-joint ``Skeleton`` and its ``SkelAnimation`` ``Breathing`` (blend-shape weights per time code)."""
    UsdSkel, Gf, Vt, Sdf = pxr.UsdSkel, pxr.Gf, pxr.Vt, pxr.Sdf
    skel = UsdSkel.Skeleton.Define(stage, f"{ROOT}/Skeleton")
    skel.CreateJointsAttr(Vt.TokenArray([JOINT]))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    anim = UsdSkel.Animation.Define(stage, f"{ROOT}/Breathing")
    anim.CreateJointsAttr(Vt.TokenArray([JOINT]))
    anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0.0)]))
    anim.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1.0)]))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1.0)]))
    anim.CreateBlendShapesAttr(Vt.TokenArray([f"{name}_tidal" for name in weights]))
    attr = anim.CreateBlendShapeWeightsAttr()
    table = np.stack(list(weights.values()), axis=1).astype(np.float32)  # (k, lungs)
    for i, row in enumerate(table):
        attr.Set(Vt.FloatArray.FromNumpy(row), float(i))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([Sdf.Path(f"{ROOT}/Breathing")])


def _baked_lung(pxr, stage, name: str, lung: LungModel, share: float, lam: np.ndarray) -> None:
    """One lung as a ``Mesh`` whose points (and extent) are sampled at every time code."""
    mesh = _mesh(pxr, stage, name, lung, share)
    p = lps_to_y_up_m(lung.surface.vertices)
    d = lps_to_y_up_m(tidal_displacement(lung.displacement, lung_units(lung)))
    points, extent = mesh.GetPointsAttr(), mesh.CreateExtentAttr()
    for i, w in enumerate(lam):
        x = p + float(w) * d
        points.Set(_vec3f(pxr, x), float(i))
        extent.Set(_extent(pxr, x.min(axis=0), x.max(axis=0)), float(i))


def usd_stage(model: Model, trace: VolumeTrace | None = None, *, fps: float | None = None, baked: bool = False):
    """The model breathing ``trace`` (default :func:`lungdeform.playback.schedule.plain_cycle`) as an
    in-memory ``Usd.Stage`` (see the module docstring); ``fps`` as :func:`usd_frames`."""
    pxr = require_usd()
    trace = trace or plain_cycle()
    frames = usd_frames(trace, fps)
    weights = lung_weights(model, frames)
    shares = lung_shares(model)
    stage = pxr.Usd.Stage.CreateInMemory()
    _stage_metadata(pxr, stage, frames, trace, baked)
    root = (pxr.UsdGeom.Xform if baked else pxr.UsdSkel.Root).Define(stage, ROOT).GetPrim()
    stage.SetDefaultPrim(root)
    pxr.Usd.ModelAPI(root).SetKind(pxr.Kind.Tokens.component)
    pxr.UsdGeom.Scope.Define(stage, f"{ROOT}/Materials")
    if not baked:
        _skeleton(pxr, stage, weights)
    for name, lung in model.lungs.items():
        (_baked_lung if baked else _skinned_lung)(pxr, stage, name, lung, shares[name], weights[name])
    return stage


def _write_layer(pxr, stage, path: Path) -> None:
    """Export the stage's root layer to ``path`` (its suffix picks usda or crate)."""
    try:
        ok = stage.GetRootLayer().Export(str(path))
    except pxr.Tf.ErrorException as exc:
        raise LungdeformError(f"{path}: usd-core could not write the layer ({str(exc).strip()[:300]})") from exc
    if not ok:
        raise LungdeformError(f"{path}: usd-core could not write the layer")


def _package_usdz(pxr, stage, stem: str, usdz: Path) -> None:
    """Write the stage as ``<stem>.usdc`` in a temporary folder (the system's, removed after) and package
    it into ``usdz`` with usd-core's ARKit packager."""
    with tempfile.TemporaryDirectory(prefix="lungdeform-usdz-") as tmp:
        usdc = Path(tmp) / f"{stem}.usdc"
        _write_layer(pxr, stage, usdc)
        try:
            ok = pxr.UsdUtils.CreateNewARKitUsdzPackage(pxr.Sdf.AssetPath(str(usdc)), str(usdz))
        except pxr.Tf.ErrorException as exc:
            raise LungdeformError(f"{usdz}: usd-core's ARKit packager failed ({str(exc).strip()[:300]})") from exc
        if not ok:
            raise LungdeformError(f"{usdz}: usd-core's ARKit packager failed")


def export_usd(model: Model, path, trace: VolumeTrace | None = None, *, fps: float | None = None,
               baked: bool = False) -> Path:
    """Write the model breathing ``trace`` to ``path`` (``.usd``, ``.usdc``, ``.usda`` or ``.usdz``: the
    suffix picks the format) atomically; return the path. ``fps``: as :func:`usd_frames`; ``baked``:
    time-sampled points instead of blend shapes."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in USD_SUFFIXES:
        raise InputError(f"{path}: a USD file name ends in {', '.join(USD_SUFFIXES)}, not {path.suffix or 'nothing'}")
    pxr = require_usd()
    stage = usd_stage(model, trace, fps=fps, baked=baked)
    with atomic_path(path) as tmp:
        if suffix == ".usdz":
            _package_usdz(pxr, stage, path.stem, tmp)
        else:
            _write_layer(pxr, stage, tmp)
    return path
