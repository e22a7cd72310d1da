"""Export a lung model for 3-D engines (glTF 2.0 binary) and for ParaView (VTK ``.pvd`` + ``.vtp``).

glTF layout (``.glb``, written with pygltflib)
----------------------------------------------
Topology is written once; positions move by morph targets (displacements), never one mesh per frame.

- Scene: a root node ``patient`` whose rotation and scale map the model frame (**LPS millimetres**:
  x → patient left, y → posterior, z → head) to glTF's frame (**Y up, +Z forward, metres**):
  glTF ``(X, Y, Z) = 0.001 · (x, z, −y)``. Vertex data stay in LPS mm, so every number in the
  ``extras`` (gravity vectors, frame boxes) is in the same frame as the vertices.
- One child node and mesh per lung (``left``, ``right``), one triangle primitive each:
  ``POSITION`` (end-exhale p, mm: a model built from a scan above end-exhale, e.g. end-inhale, is
  moved down to end-exhale by the exact volume cubic, and the mesh extras' ``scan_weight`` is the
  weight of target 0 at which it is the scan; the asset extras' ``scan_state`` says where the scan
  lies, :mod:`lungdeform.model.scan_state`), ``NORMAL`` (unit, end-exhale), ``_STIFFNESS`` (SCALAR, relative
  Young's modulus), ``_FORCE_BASIS`` (VEC4: elastostatic force for the fields 1, x̂, ŷ, ẑ), and
  ``indices`` (uint32). Morph targets have ``POSITION`` only (normals change little: the tidal
  displacement is a few mm on a 100–300 mm lung).
- Morph targets (mm), per lung:

  ====  =========  ==============================================================================
  k     name       displacement
  ====  =========  ==============================================================================
  0     ``tidal``  ``u · calibration_ml/unit_ml``: the model's own calibrated displacement for its
                   gravity; weight 1 is +calibration_ml in the paper's linear reading
  1–4   ``basis``  ``κ · F_k · d`` for the fields k = 1, x̂, ŷ, ẑ, with κ the least-squares factor
                   that makes ``Σ w_k(g_model) · target_k = target_0``
  ====  =========  ==============================================================================

  So any gravity g is ``weights[1:5] = λ · w(g)``, ``w = force_weights(frame, g, constants)``
  (the frame box and c1…c9 are in extras), with ``λ`` the root of the exact volume cubic
  ``A1·w λ + (wᵀA2w) λ² + A3(w,w,w) λ³ = ΔV`` (mm³; tensors ``A1 (4,)``, ``A2 (4,4)``,
  ``A3 (4,4,4)`` are in the mesh extras; :func:`lungdeform.model.displacement.volume_tensors`). For
  the model's own gravity, use target 0 alone with the cubic ``tidal_volume_poly_mm3``. The mesh
  extras also list, for the five named orientations, the basis weights ``λ·w`` that add exactly
  ``calibration_ml``.
- Markers (``--markers``; asset ``extras.lungdeform.markers``, :func:`lungdeform.playback.markers.marker_anchors`;
  schema version 2): per marker ``label``, ``position_mm`` (end-exhale), ``lung``, ``inside``,
  ``distance_mm`` and ``tidal_mm``, its displacement per unit weight of its lung's target 0:
  ``x(λ) = position_mm + λ·tidal_mm`` with the λ that drives ``tidal`` (the animation's), from the
  lung's interior field (:attr:`lungdeform.model.lung.LungModel.interior`), not from nearby vertices, so
  a point deep inside moves as ``lungdeform track`` moves it. Three multiply-adds per marker per
  frame. Re-oriented playback (targets 1–4) has no exact marker motion (the landmark correction
  belongs to the scan's posture; the surface-driven field would need one interpolation per basis field):
  a player may keep markers on ``λ_tidal(ΔV)·tidal_mm``, the model's own gravity at the same volume.
  (Schema 1 tied markers to 4 surface vertices with inverse-distance weights instead.)
- Animation ``breathing``: one ``weights`` channel per lung, LINEAR, sampled at the curve's times;
  ``weights = [λ(t), 0, 0, 0, 0]`` where ``λ(t)`` makes the lung's volume exactly
  ``V_EE + share · ΔV(t)`` (cubic inverted per key; ``share`` = the lung's ``calibration_ml`` over
  the sum of both). The curve itself is in the asset extras.

The breathing curve played (a :class:`lungdeform.playback.schedule.VolumeTrace`: a curve CSV, a simulated
preset, or :func:`lungdeform.playback.schedule.plain_cycle` by default) and each lung's ``share`` of it are
:mod:`lungdeform.playback.schedule`.

VTK time series: ParaView's ``.pvd`` lists one ``.vtp`` per (lung, time step); VTK XML has no way
to share topology across files, so each frame file repeats it (binary, appended raw, written by
:func:`lungdeform.io.vtk.vtp_bytes`). Every frame carries ``displacement_mm`` (x − p) beside the
positions. Use the ``.glb`` for compact storage.

The displacement and volume math (targets, volume tensors, exact weights for a volume) is
:mod:`lungdeform.model.displacement`; this module lays it out in files.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pygltflib as g

from lungdeform import __version__
from lungdeform.atomic import atomic_dir, finite_json, write_bytes
from lungdeform.constants import GRAVITY
from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.mesh import Surface, vertex_normals
from lungdeform.io.vtk import vtp_bytes
from lungdeform.model.displacement import (
    calibration_units,
    cubic_along,
    cubic_in_weight,
    morph_targets,
    scale_for_volume,
    scales_for_volumes,
    tidal_displacement,
    volume_tensors,
)
from lungdeform.model.force import force_weights
from lungdeform.model.lung import LungModel, Model
from lungdeform.progress import Progress, silent

from .schedule import VolumeTrace, lung_shares, plain_cycle

GLB_SCHEMA = "lungdeform.glb"
#: 2: markers carry ``tidal_mm`` (interior field) instead of anchor vertices and weights.
GLB_SCHEMA_VERSION = 2
MARKER_MOTION = ("a marker of lung L at morph weight λ of L's target 0 ('tidal') is at position_mm + λ·tidal_mm "
                 "(mm, LPS; interior field of lungdeform.interior); re-oriented playback (targets 1-4) has "
                 "no exact marker motion")
TARGET_NAMES = ("tidal", "basis_1", "basis_x", "basis_y", "basis_z")
#: The one rotation from patient LPS to an engine's Y-up frame: (x, y, z) → (x, z, −y), a −90° turn about x
#: (head up, anterior toward +Z). glTF applies it on the root node (:data:`LPS_TO_GLTF_ROTATION`); USD
#: applies it to the vertex data (:func:`lps_to_y_up_m`, :mod:`lungdeform.playback.usd`).
LPS_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: :data:`LPS_TO_Y_UP` as the root-node quaternion (x, y, z, w) of the glTF export.
LPS_TO_GLTF_ROTATION = (-np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5))
MM_TO_M = 0.001


def lps_to_y_up_m(points_mm: np.ndarray) -> np.ndarray:
    """``points_mm : (n, 3) float`` mm, LPS (positions or displacements) as ``(n, 3) float`` metres in the
    Y-up frame of glTF and USD: ``(X, Y, Z) = 0.001 · (x, z, −y)`` (:data:`LPS_TO_Y_UP`)."""
    return np.ascontiguousarray((MM_TO_M * np.asarray(points_mm, float)) @ LPS_TO_Y_UP.T)


def lung_normals(name: str, lung: LungModel) -> np.ndarray:
    """``(n, 3) float`` unit end-exhale vertex normals of ``lung`` (LPS); a vertex on no face is refused."""
    nrm = vertex_normals(lung.surface.vertices, lung.surface.faces)
    if np.any(np.linalg.norm(nrm, axis=1) < 0.5):
        raise LungdeformError(f"lung '{name}' has vertices with no faces (zero normals)")
    return nrm


def frame_times(trace: VolumeTrace, fps: float) -> np.ndarray:
    """``(k,) float`` s: evenly spaced frames over the whole trace, at about ``fps`` frames per second
    (``round(duration·fps)`` intervals, at least 1), first and last on the trace's ends."""
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be > 0, got {fps}")
    duration = float(trace.t_s[-1] - trace.t_s[0])
    n = max(round(duration * fps), 1) + 1
    return np.linspace(trace.t_s[0], trace.t_s[-1], n)


# --------------------------------------------------------------------------- morph targets
def lung_units(lung: LungModel) -> float:
    """The lung's calibration volume in units (``calibration_ml / unit_ml``): target 0 is weight 1."""
    return calibration_units(lung.calibration_ml, lung.unit_ml)


def lung_targets(lung: LungModel) -> tuple[np.ndarray, float]:
    """``targets : (5, n, 3) float`` mm (see the module table) and the basis factor κ of ``lung``
    (:func:`lungdeform.model.displacement.morph_targets`)."""
    return morph_targets(lung.displacement, lung.basis_displacement, lung.force_weights, lung_units(lung))


def tidal_weights(lung: LungModel, delta_ml) -> np.ndarray:
    """Weights ``λ (k,)`` of target 0 that make the lung's volume exactly ``V_EE + delta_ml`` (mL)."""
    return scales_for_volumes(lung.volume_poly, delta_ml) / lung_units(lung)


def orientation_table(lung: LungModel, a1, a2, a3) -> dict:
    """For each named orientation: gravity (LPS), force weights w, and basis weights ``λ·w`` that
    add exactly ``calibration_ml`` to the lung's volume (``a1, a2, a3``: the basis targets' volume
    tensors, mm³, :func:`lungdeform.model.displacement.volume_tensors`)."""
    out = {}
    for name, gravity in GRAVITY.items():
        w = force_weights(lung.frame, gravity, lung.constants)
        try:
            lam = scale_for_volume(cubic_along(a1, a2, a3, w), lung.calibration_ml)
        except LungdeformError:
            continue  # this gravity does not grow this lung (possible only for odd constants)
        out[name] = {"gravity": list(map(float, gravity)), "force_weights": w.tolist(),
                     "basis_weights": (lam * w).tolist()}
    return out


# --------------------------------------------------------------------------- glTF
class _Blob:
    """Binary chunk builder: one bufferView and accessor per array, 4-byte aligned."""

    def __init__(self, gl):
        self.gl, self.parts, self.size = gl, [], 0

    def add(self, array: np.ndarray, kind: str, target=None, minmax: bool = False) -> int:
        a = np.ascontiguousarray(array)
        ctype = {np.dtype(np.float32): g.FLOAT, np.dtype(np.uint32): g.UNSIGNED_INT}[a.dtype]
        data = a.tobytes()
        pad = (-len(data)) % 4
        self.gl.bufferViews.append(g.BufferView(buffer=0, byteOffset=self.size, byteLength=len(data),
                                                target=target))
        self.parts.append(data + b"\0" * pad)
        self.size += len(data) + pad
        acc = g.Accessor(bufferView=len(self.gl.bufferViews) - 1, componentType=ctype,
                         count=len(a), type=kind)
        if minmax:
            flat = a.reshape(len(a), -1)
            acc.min, acc.max = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        self.gl.accessors.append(acc)
        return len(self.gl.accessors) - 1


def _primitive(blob: _Blob, name: str, lung: LungModel, targets: np.ndarray, material: int) -> g.Primitive:
    """The lung's triangle primitive: vertex attributes, indices and morph targets in ``blob``."""
    p, f = lung.surface.vertices, lung.surface.faces
    nrm = lung_normals(name, lung)
    attrs = g.Attributes(
        POSITION=blob.add(p.astype(np.float32), g.VEC3, g.ARRAY_BUFFER, minmax=True),
        NORMAL=blob.add(nrm.astype(np.float32), g.VEC3, g.ARRAY_BUFFER),
    )
    attrs._STIFFNESS = blob.add(lung.stiffness.astype(np.float32), g.SCALAR, g.ARRAY_BUFFER)
    attrs._FORCE_BASIS = blob.add(lung.force_basis.T.astype(np.float32), g.VEC4, g.ARRAY_BUFFER)
    tgt = [{"POSITION": blob.add(t.astype(np.float32), g.VEC3, g.ARRAY_BUFFER, minmax=True)}
           for t in targets]
    idx = blob.add(f.astype(np.uint32).reshape(-1), g.SCALAR, g.ELEMENT_ARRAY_BUFFER, minmax=True)
    return g.Primitive(attributes=attrs, indices=idx, targets=tgt, material=material)


def _material(name: str, lung: LungModel) -> g.Material:
    color = [0.93, 0.55, 0.55, 1.0] if lung.side == "left" else [0.55, 0.7, 0.93, 1.0]
    return g.Material(name=f"{name} tissue", doubleSided=False,
                      pbrMetallicRoughness=g.PbrMetallicRoughness(
                          baseColorFactor=color, metallicFactor=0.0, roughnessFactor=0.6))


def _lung_extras(name: str, lung: LungModel, share: float, kappa: float, tensors) -> dict:
    """The mesh extras ``lungdeform`` of one lung (see the module docstring)."""
    a0, a1, a2, a3 = tensors
    return {
        "lung": name, "side": lung.side, "n_vertices": int(lung.n_vertices),
        "targets": list(TARGET_NAMES), "units": "mm", "frame": "LPS",
        "calibration_ml": lung.calibration_ml, "unit_ml": lung.unit_ml, "share": share,
        "volume_ee_ml": lung.volume_ee_ml, "gravity": lung.gravity.tolist(),
        "basis_factor": kappa,
        "tidal_volume_poly_mm3": cubic_in_weight(lung.volume_poly, lung_units(lung)).tolist(),
        "basis_volume_tensors_mm3": {"a0": a0, "a1": a1.tolist(), "a2": a2.tolist(), "a3": a3.tolist()},
        "lung_frame": {"axes": lung.frame.axes.tolist(), "lower": lung.frame.lower.tolist(),
                       "upper": lung.frame.upper.tolist()},
        "constants": lung.constants.tolist(),
        "stiffness_range": [float(lung.stiffness.min()), float(lung.stiffness.max())],
        "orientations": orientation_table(lung, a1, a2, a3),
    }


def _add_lung(gl, blob: _Blob, anim, times: int, name: str, lung: LungModel, share: float,
              trace: VolumeTrace) -> dict:
    """Add one lung (material, mesh, node under the root, animation channel); return its extras."""
    targets, kappa = lung_targets(lung)
    tensors = volume_tensors(lung.surface.vertices, lung.surface.faces, targets[1:])
    primitive = _primitive(blob, name, lung, targets, len(gl.materials))
    gl.materials.append(_material(name, lung))
    meta = _lung_extras(name, lung, share, kappa, tensors)
    gl.meshes.append(g.Mesh(name=name, weights=[0.0] * len(targets), primitives=[primitive],
                            extras={"targetNames": list(TARGET_NAMES), "lungdeform": meta}))
    gl.nodes.append(g.Node(name=name, mesh=len(gl.meshes) - 1))
    gl.nodes[0].children.append(len(gl.nodes) - 1)
    lam = tidal_weights(lung, share * trace.volume_ml)
    w = np.zeros((len(lam), len(targets)), np.float32)
    w[:, 0] = lam
    out = blob.add(w.reshape(-1), g.SCALAR)
    anim.samplers.append(g.AnimationSampler(input=times, output=out, interpolation=g.ANIM_LINEAR))
    anim.channels.append(g.AnimationChannel(sampler=len(anim.samplers) - 1,
                                            target=g.AnimationChannelTarget(node=len(gl.nodes) - 1,
                                                                            path="weights")))
    return meta


def _asset_extras(model: Model, trace: VolumeTrace, lungs_meta: list[dict], markers) -> dict:
    return {"lungdeform": {
        "schema": GLB_SCHEMA, "schema_version": GLB_SCHEMA_VERSION,
        "frame": "vertex data in LPS mm; root node 'patient' maps to glTF Y-up metres: (x, z, -y)/1000",
        "curve": {"source": trace.source, "shifted_ml": trace.shifted_ml,
                  "t_s": trace.t_s.tolist(), "volume_ml": trace.volume_ml.tolist(),
                  "meaning": "volume of both lungs above end-exhale; each lung takes 'share' of it"},
        "scan_state": {**model.scan.record(),
                       "meaning": "the breathing state of the scan the model was built from; POSITION is end-exhale, "
                                  "the scan is each lung's target-0 weight 'scan_weight'"},
        "lungs": [m["lung"] for m in lungs_meta],
        "markers": markers or [],
        "marker_motion": MARKER_MOTION,
        # strict JSON: a fit's provenance holds NaN (e.g. no landmark error), which glTF's JSON refuses
        "provenance": finite_json(json.loads(json.dumps(model.provenance, default=str))),
    }}


def at_end_exhale(model: Model, markers: list[dict] | None = None) -> tuple[dict[str, LungModel], list[dict] | None, dict]:
    """The model's lungs moved from their scan to end-exhale (each by its share of the scan's height
    above end-exhale, :mod:`lungdeform.model.scan_state`; exact by the volume cubic), the markers
    (:func:`lungdeform.playback.markers.marker_anchors`, at the scan) moved with them, and per lung the
    weight of target 0 at which the mesh is the scan (0 for an end-exhale scan: nothing moves)."""
    shares = lung_shares(model)
    lungs, weights = {}, {}
    for name, lung in model.lungs.items():
        down = scale_for_volume(lung.volume_poly, -shares[name] * model.scan.above_ee_ml)  # units, <= 0
        lungs[name] = lung if down == 0 else replace(
            lung, surface=Surface(lung.positions_at(down), lung.surface.faces, f"{lung.surface.name} at end-exhale"))
        weights[name] = -down / lung_units(lung)
    if markers:
        markers = [{**m, "position_mm": (np.asarray(m["position_mm"], float)
                                         - weights[m["lung"]] * np.asarray(m["tidal_mm"], float)).tolist()}
                   for m in markers]
    return lungs, markers, weights


def glb_bytes(model: Model, trace: VolumeTrace | None = None, markers: list[dict] | None = None) -> bytes:
    """The model as a glTF 2.0 binary (see the module docstring for the layout). A model whose scan
    lies above end-exhale is written at end-exhale (:func:`at_end_exhale`): POSITION, the markers and
    the animation's weights start there, and each lung's ``scan_weight`` says where the scan is."""
    trace = trace or plain_cycle()
    shares = lung_shares(model)
    lungs, markers, scan_weights = at_end_exhale(model, markers)
    gl = g.GLTF2(asset=g.Asset(version="2.0", generator=f"lungdeform {__version__}"))
    gl.buffers, gl.bufferViews, gl.accessors = [g.Buffer()], [], []
    blob = _Blob(gl)
    gl.nodes = [g.Node(name="patient", rotation=list(LPS_TO_GLTF_ROTATION), scale=[MM_TO_M] * 3, children=[])]
    gl.meshes, gl.materials = [], []
    times = blob.add(trace.t_s.astype(np.float32), g.SCALAR, minmax=True)
    anim = g.Animation(name="breathing", samplers=[], channels=[])
    lungs_meta = [_add_lung(gl, blob, anim, times, name, lung, shares[name], trace) for name, lung in lungs.items()]
    for name, meta in zip(lungs, lungs_meta):  # the mesh's own extras dict: where the scan is
        meta["scan_weight"] = scan_weights[name]
    gl.animations = [anim]
    gl.scenes = [g.Scene(name="lungs", nodes=[0])]
    gl.scene = 0
    gl.extras = _asset_extras(model, trace, lungs_meta, markers)
    data = b"".join(blob.parts)
    gl.buffers[0].byteLength = len(data)
    gl.set_binary_blob(data)
    return b"".join(gl.save_to_bytes())


def export_glb(model: Model, path, trace: VolumeTrace | None = None, markers: list[dict] | None = None) -> Path:
    """Write :func:`glb_bytes` to ``path`` atomically; return the path."""
    path = Path(path)
    write_bytes(path, glb_bytes(model, trace, markers))
    return path


# --------------------------------------------------------------------------- VTK time series
def export_pvd(model: Model, path, trace: VolumeTrace | None = None, fps: float = 10.0,
               progress: Progress | None = None) -> Path:
    """Write ``path`` (``.pvd``) and its frames ``<stem>_frames/<lung>_<k>.vtp`` (time series for
    ParaView). The frames folder is written beside the ``.pvd`` in a temporary folder and renamed
    into place; the ``.pvd`` is written last, atomically."""
    path = Path(path)
    trace = trace or plain_cycle()
    times = frame_times(trace, fps)
    n = len(times)
    say = progress or silent
    shares = lung_shares(model)
    dv = trace.sample(times)
    frames_name = f"{path.stem}_frames"
    entries = []
    with atomic_dir(path.parent / frames_name) as tmp_dir:  # folder mode follows the umask
        for part, (name, lung) in enumerate(model.lungs.items()):
            lam = tidal_weights(lung, shares[name] * (dv - model.scan.above_ee_ml))  # from the scan, p
            tidal = tidal_displacement(lung.displacement, lung_units(lung))
            p, f = lung.surface.vertices, lung.surface.faces
            stiff = lung.stiffness.astype(np.float32)
            say(f"{name}: {n} frames")
            for k, (t, weight) in enumerate(zip(times, lam)):
                disp = (weight * tidal).astype(np.float32)
                fname = f"{name}_{k:04d}.vtp"
                frame = vtp_bytes(p + disp, f, {"displacement_mm": disp, "stiffness": stiff}, time_s=float(t),
                                  appended=True, points_dtype=np.float32)
                (tmp_dir / fname).write_bytes(frame)
                entries.append(f'<DataSet timestep="{t:.6g}" part="{part}" name="{name}" '
                               f'file="{frames_name}/{fname}"/>')
    pvd = ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="1.0" byte_order="LittleEndian">\n'
           "<Collection>\n" + "\n".join(entries) + "\n</Collection>\n</VTKFile>\n")
    write_bytes(path, pvd.encode())
    return path
