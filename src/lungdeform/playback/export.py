"""Export a lung model for 3-D engines (glTF 2.0 binary) and for ParaView (VTK ``.pvd`` + ``.vtp``).

glTF layout (``.glb``, written with pygltflib)
----------------------------------------------
Topology is written once; positions move by morph targets (displacements), never one mesh per frame.

- Scene: a root node ``patient`` whose rotation and scale map the model frame (**LPS millimetres**:
  x → patient left, y → posterior, z → head) to glTF's frame (**Y up, +Z forward, metres**):
  glTF ``(X, Y, Z) = 0.001 · (x, z, −y)``. Vertex data stay in LPS mm, so every number in the
  ``extras`` (gravity vectors, frame boxes) is in the same frame as the vertices.
- One child node and mesh per lung (``left``, ``right``), one triangle primitive each:
  ``POSITION`` (end-exhale p, mm), ``NORMAL`` (unit, end-exhale), ``_STIFFNESS`` (SCALAR, relative
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
  ``A3 (4,4,4)`` are in the mesh extras). For the model's own gravity, use target 0 alone with the
  cubic ``tidal_volume_poly_mm3``. The mesh extras also list, for the five named orientations, the
  basis weights ``λ·w`` that add exactly ``calibration_ml``.
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
to share topology across files, so each frame file repeats it (binary, appended raw). Every frame
carries ``displacement_mm`` (x − p) beside the positions. Use the ``.glb`` for compact storage.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pygltflib as g

from lungdeform import __version__
from lungdeform.atomic import finite_json, write_bytes
from lungdeform.constants import GRAVITY
from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.mesh import vertex_normals
from lungdeform.model.displacement import scale_for_volume, smallest_positive_root
from lungdeform.model.force import force_weights
from lungdeform.model.lung import LungModel, Model

from .schedule import VolumeTrace, lung_shares, plain_cycle

GLB_SCHEMA = "lungdeform.glb"
#: 2: markers carry ``tidal_mm`` (interior field) instead of anchor vertices and weights.
GLB_SCHEMA_VERSION = 2
MARKER_MOTION = ("a marker of lung L at morph weight λ of L's target 0 ('tidal') is at position_mm + λ·tidal_mm "
                 "(mm, LPS; interior field of lungdeform.interior.field); re-oriented playback (targets 1-4) has "
                 "no exact marker motion")
TARGET_NAMES = ("tidal", "basis_1", "basis_x", "basis_y", "basis_z")
#: Root-node rotation (x, y, z, w) taking LPS to glTF: (x, y, z) → (x, z, −y); a −90° turn about x.
LPS_TO_GLTF_ROTATION = (-np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5))
MM_TO_M = 0.001


# --------------------------------------------------------------------------- morph targets
def volume_tensors(vertices: np.ndarray, faces: np.ndarray, targets: np.ndarray):
    """Exact volume of ``vertices + Σ_k w_k · targets[k]`` as a cubic form in ``w``.

    Parameters
    ----------
    vertices : (n, 3) float, mm; faces : (m, 3) int, outward; targets : (K, n, 3) float, mm.

    Returns
    -------
    a0 : float, mm³; a1 : (K,); a2 : (K, K) symmetric; a3 : (K, K, K) symmetric, mm³, with
    ``V(w) = a0 + a1·w + wᵀ a2 w + a3(w, w, w)`` (same face trilinearity as
    :func:`lungdeform.model.displacement.volume_polynomial`).
    """
    p = vertices - vertices.mean(axis=0)
    pa, pb, pc = (p[faces[:, c]] for c in range(3))
    u = [[t[faces[:, c]] for c in range(3)] for t in targets]  # u[k][corner] : (m, 3)
    kk = len(targets)
    dot = lambda a, b: float(np.einsum("ij,ij->", a, b))  # noqa: E731
    a0 = dot(pa, np.cross(pb, pc)) / 6.0
    a1 = np.array([dot(u[k][0], np.cross(pb, pc)) + dot(pa, np.cross(u[k][1], pc))
                   + dot(pa, np.cross(pb, u[k][2])) for k in range(kk)]) / 6.0
    a2 = np.zeros((kk, kk))
    a3 = np.zeros((kk, kk, kk))
    for j in range(kk):
        for k in range(kk):
            bc = np.cross(u[j][1], u[k][2])
            a2[j, k] = (dot(u[j][0], np.cross(u[k][1], pc)) + dot(u[j][0], np.cross(pb, u[k][2]))
                        + dot(pa, bc)) / 6.0
            for i in range(kk):
                a3[i, j, k] = dot(u[i][0], bc) / 6.0
    a2 = 0.5 * (a2 + a2.T)
    a3 = sum(np.transpose(a3, perm) for perm in
             ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))) / 6.0
    return a0, a1, a2, a3


def lung_targets(lung: LungModel) -> tuple[np.ndarray, float]:
    """``targets : (5, n, 3) float`` mm (see the module table) and the basis factor κ."""
    s_cal = lung.calibration_ml / lung.unit_ml
    tidal = lung.displacement * s_cal
    basis = lung.basis_displacement
    raw = np.tensordot(lung.force_weights, basis, axes=1)
    denom = float(np.einsum("ij,ij->", raw, raw))
    kappa = float(np.einsum("ij,ij->", raw, tidal)) / denom if denom > 0 else 1.0
    return np.concatenate([tidal[None], kappa * basis]), kappa


def tidal_weights(lung: LungModel, delta_ml) -> np.ndarray:
    """Weights ``λ (k,)`` of target 0 that make the lung's volume exactly ``V_EE + delta_ml`` (mL)."""
    s_cal = lung.calibration_ml / lung.unit_ml
    poly = lung.volume_poly
    out = np.empty(len(delta_ml))
    for i, dv in enumerate(np.asarray(delta_ml, float)):
        out[i] = scale_for_volume(poly, float(dv)) / s_cal
    return out


def cubic_root(a1: float, a2: float, a3: float, target: float) -> float:
    """``λ`` with ``a1 λ + a2 λ² + a3 λ³ = target``: the root nearest 0 on the side of ``target``."""
    if target == 0:
        return 0.0
    poly = np.array([0.0, a1, a2, a3])
    if target > 0:
        return smallest_positive_root(poly, target)
    return scale_for_volume(poly, target / 1000.0)


def orientation_table(lung: LungModel, a1, a2, a3) -> dict:
    """For each named orientation: gravity (LPS), force weights w, and basis weights ``λ·w`` that
    add exactly ``calibration_ml`` to the lung's volume."""
    out = {}
    for name, g in GRAVITY.items():
        w = force_weights(lung.frame, g, lung.constants)
        try:
            lam = cubic_root(float(a1 @ w), float(w @ a2 @ w),
                             float(np.einsum("ijk,i,j,k->", a3, w, w, w)), lung.calibration_ml * 1000.0)
        except LungdeformError:
            continue  # this gravity does not grow this lung (possible only for odd constants)
        out[name] = {"gravity": list(map(float, g)), "force_weights": w.tolist(),
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


def glb_bytes(model: Model, trace: VolumeTrace | None = None, markers: list[dict] | None = None) -> bytes:
    """The model as a glTF 2.0 binary (see the module docstring for the layout)."""


    trace = trace or plain_cycle()
    shares = lung_shares(model)
    gl = g.GLTF2(asset=g.Asset(version="2.0", generator=f"lungdeform {__version__}"))
    gl.buffers, gl.bufferViews, gl.accessors = [g.Buffer()], [], []
    blob = _Blob(gl)
    root = g.Node(name="patient", rotation=list(LPS_TO_GLTF_ROTATION), scale=[MM_TO_M] * 3, children=[])
    gl.nodes = [root]
    gl.meshes, gl.materials = [], []
    times = blob.add(trace.t_s.astype(np.float32), g.SCALAR, minmax=True)
    anim = g.Animation(name="breathing", samplers=[], channels=[])
    lungs_meta = []
    for name, lung in model.lungs.items():
        p, f = lung.surface.vertices, lung.surface.faces
        targets, kappa = lung_targets(lung)
        a0, a1, a2, a3 = volume_tensors(p, f, targets[1:])
        nrm = vertex_normals(p, f)
        if np.any(np.linalg.norm(nrm, axis=1) < 0.5):
            raise LungdeformError(f"lung '{name}' has vertices with no faces (zero normals)")
        attrs = g.Attributes(
            POSITION=blob.add(p.astype(np.float32), g.VEC3, g.ARRAY_BUFFER, minmax=True),
            NORMAL=blob.add(nrm.astype(np.float32), g.VEC3, g.ARRAY_BUFFER),
        )
        attrs._STIFFNESS = blob.add(lung.stiffness.astype(np.float32), g.SCALAR, g.ARRAY_BUFFER)
        attrs._FORCE_BASIS = blob.add(lung.force_basis.T.astype(np.float32), g.VEC4, g.ARRAY_BUFFER)
        tgt = [{"POSITION": blob.add(t.astype(np.float32), g.VEC3, g.ARRAY_BUFFER, minmax=True)}
               for t in targets]
        idx = blob.add(f.astype(np.uint32).reshape(-1), g.SCALAR, g.ELEMENT_ARRAY_BUFFER, minmax=True)
        color = [0.93, 0.55, 0.55, 1.0] if lung.side == "left" else [0.55, 0.7, 0.93, 1.0]
        gl.materials.append(g.Material(name=f"{name} tissue", doubleSided=False,
                                       pbrMetallicRoughness=g.PbrMetallicRoughness(
                                           baseColorFactor=color, metallicFactor=0.0, roughnessFactor=0.6)))
        s_cal = lung.calibration_ml / lung.unit_ml
        meta = {
            "lung": name, "side": lung.side, "n_vertices": int(lung.n_vertices),
            "targets": list(TARGET_NAMES), "units": "mm", "frame": "LPS",
            "calibration_ml": lung.calibration_ml, "unit_ml": lung.unit_ml, "share": shares[name],
            "volume_ee_ml": lung.volume_ee_ml, "gravity": lung.gravity.tolist(),
            "basis_factor": kappa,
            "tidal_volume_poly_mm3": (lung.volume_poly * s_cal ** np.arange(4)).tolist(),
            "basis_volume_tensors_mm3": {"a0": a0, "a1": a1.tolist(), "a2": a2.tolist(), "a3": a3.tolist()},
            "lung_frame": {"axes": lung.frame.axes.tolist(), "lower": lung.frame.lower.tolist(),
                           "upper": lung.frame.upper.tolist()},
            "constants": lung.constants.tolist(),
            "stiffness_range": [float(lung.stiffness.min()), float(lung.stiffness.max())],
            "orientations": orientation_table(lung, a1, a2, a3),
        }
        lungs_meta.append(meta)
        gl.meshes.append(g.Mesh(name=name, weights=[0.0] * len(targets),
                                primitives=[g.Primitive(attributes=attrs, indices=idx, targets=tgt,
                                                        material=len(gl.materials) - 1)],
                                extras={"targetNames": list(TARGET_NAMES), "lungdeform": meta}))
        gl.nodes.append(g.Node(name=name, mesh=len(gl.meshes) - 1))
        root.children.append(len(gl.nodes) - 1)
        lam = tidal_weights(lung, shares[name] * trace.volume_ml)
        w = np.zeros((len(lam), len(targets)), np.float32)
        w[:, 0] = lam
        out = blob.add(w.reshape(-1), g.SCALAR)
        anim.samplers.append(g.AnimationSampler(input=times, output=out, interpolation=g.ANIM_LINEAR))
        anim.channels.append(g.AnimationChannel(sampler=len(anim.samplers) - 1,
                                                target=g.AnimationChannelTarget(node=len(gl.nodes) - 1,
                                                                                path="weights")))
    gl.animations = [anim]
    gl.scenes = [g.Scene(name="lungs", nodes=[0])]
    gl.scene = 0
    gl.extras = {"lungdeform": {
        "schema": GLB_SCHEMA, "schema_version": GLB_SCHEMA_VERSION,
        "frame": "vertex data in LPS mm; root node 'patient' maps to glTF Y-up metres: (x, z, -y)/1000",
        "curve": {"source": trace.source, "shifted_ml": trace.shifted_ml,
                  "t_s": trace.t_s.tolist(), "volume_ml": trace.volume_ml.tolist(),
                  "meaning": "volume of both lungs above end-exhale; each lung takes 'share' of it"},
        "lungs": [m["lung"] for m in lungs_meta],
        "markers": markers or [],
        "marker_motion": MARKER_MOTION,
        # strict JSON: a fit's provenance holds NaN (e.g. no landmark error), which glTF's JSON refuses
        "provenance": finite_json(json.loads(json.dumps(model.provenance, default=str))),
    }}
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
def _vtp_bytes(points: np.ndarray, faces: np.ndarray, point_data: dict[str, np.ndarray], time_s: float) -> bytes:
    """One VTK XML PolyData file, binary appended raw (UInt64 headers, little endian)."""
    blocks: list[bytes] = []
    offset = 0

    def put(a: np.ndarray) -> int:
        nonlocal offset
        raw = np.ascontiguousarray(a).astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
        blocks.append(np.uint64(len(raw)).tobytes() + raw)
        at = offset
        offset += 8 + len(raw)
        return at

    vtk_type = {np.dtype(np.float32): "Float32", np.dtype(np.float64): "Float64", np.dtype(np.int32): "Int32",
                np.dtype(np.int64): "Int64"}

    def darray(name: str, a: np.ndarray) -> str:
        comps = 1 if a.ndim == 1 else a.shape[1]
        return (f'<DataArray type="{vtk_type[a.dtype]}" Name="{name}" NumberOfComponents="{comps}" '
                f'format="appended" offset="{put(a)}"/>')

    time = darray("TimeValue", np.array([time_s], np.float64))
    pts = darray("Points", points.astype(np.float32))
    pd = "".join(darray(k, v) for k, v in point_data.items())
    conn = darray("connectivity", faces.astype(np.int64).reshape(-1))
    offs = darray("offsets", np.arange(3, 3 * len(faces) + 1, 3, dtype=np.int64))
    head = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n'
        f"<PolyData><FieldData>{time}</FieldData>"
        f'<Piece NumberOfPoints="{len(points)}" NumberOfVerts="0" NumberOfLines="0" NumberOfStrips="0" '
        f'NumberOfPolys="{len(faces)}"><PointData>{pd}</PointData><Points>{pts}</Points>'
        f"<Polys>{conn}{offs}</Polys></Piece></PolyData>\n"
        '<AppendedData encoding="raw">\n_'
    )
    return head.encode() + b"".join(blocks) + b"\n</AppendedData>\n</VTKFile>\n"


def export_pvd(model: Model, path, trace: VolumeTrace | None = None, fps: float = 10.0,
               progress=None) -> Path:
    """Write ``path`` (``.pvd``) and its frames ``<stem>_frames/<lung>_<k>.vtp`` (time series for
    ParaView). The frames folder is written beside the ``.pvd`` in a temporary folder and renamed
    into place; the ``.pvd`` is written last, atomically."""
    path = Path(path)
    if not fps > 0:
        raise InputError(f"fps must be > 0, got {fps}")
    trace = trace or plain_cycle()
    say = progress or (lambda _m: None)
    shares = lung_shares(model)
    duration = float(trace.t_s[-1] - trace.t_s[0])
    n = max(int(round(duration * fps)), 1) + 1
    times = np.linspace(trace.t_s[0], trace.t_s[-1], n)
    dv = trace.sample(times)
    frames_name = f"{path.stem}_frames"
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        tmp_dir = Path(tempfile.mkdtemp(prefix=f".{frames_name}.", dir=path.parent))
    except OSError as exc:  # name the output asked for, not the hidden temporary folder
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    entries = []
    try:
        for part, (name, lung) in enumerate(model.lungs.items()):
            lam = tidal_weights(lung, shares[name] * dv)
            tidal = lung.displacement * (lung.calibration_ml / lung.unit_ml)
            p, f = lung.surface.vertices, lung.surface.faces
            stiff = lung.stiffness.astype(np.float32)
            say(f"{name}: {n} frames")
            for k, (t, l) in enumerate(zip(times, lam)):
                disp = (l * tidal).astype(np.float32)
                fname = f"{name}_{k:04d}.vtp"
                (tmp_dir / fname).write_bytes(_vtp_bytes(p + disp, f, {"displacement_mm": disp,
                                                                       "stiffness": stiff}, float(t)))
                entries.append(f'<DataSet timestep="{t:.6g}" part="{part}" name="{name}" '
                               f'file="{frames_name}/{fname}"/>')
        final_dir = path.parent / frames_name
        old = None
        if final_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{frames_name}.old.", dir=path.parent))
            os.replace(final_dir, old / "x")
        os.replace(tmp_dir, final_dir)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
    pvd = ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="1.0" byte_order="LittleEndian">\n'
           "<Collection>\n" + "\n".join(entries) + "\n</Collection>\n</VTKFile>\n")
    write_bytes(path, pvd.encode())
    return path
