"""Run inside Blender (``blender -b --factory-startup --python this.py -- FILE OUT.json RATE T1 T2 …``, or with
the ``bpy`` module: ``python this.py -- …``): import a ``.glb`` with Blender's glTF importer or a
``.usd``/``.usdc``/``.usda``/``.usdz`` with its USD importer, evaluate the scene at times T (s) and write
``OUT.json``: Blender's version and build options, the scene's frame rate, the actions, and per mesh its
vertex and face counts, shape keys, modifiers and, at each time, the enclosed volume (mm³, in the
mesh's own frame: for glb the model's LPS mm) and the world positions of every vertex (Blender's
Z-up frame, metres). RATE maps a time to a frame, ``frame = round(T · RATE)``: ``scene`` uses the
scene's frame rate after the import (the glTF importer keys at that rate); a number gives it (the USD
importer keys time code i at frame i, so RATE is the file's ``timeCodesPerSecond``)."""

import json
import sys
import warnings

import numpy as np

with warnings.catch_warnings():  # numpy 1.24–1.26 warn on looking np.bool up
    warnings.simplefilter("ignore")
    if not hasattr(np, "bool"):  # Debian's Blender 3.4 glTF add-on still uses np.bool (gone in numpy 1.24)
        np.bool = bool

import bpy  # noqa: I001, E402  (first: as a module, bpy sets up addon_utils and bmesh)
import addon_utils  # noqa: E402
import bmesh  # noqa: E402

args = sys.argv[sys.argv.index("--") + 1:]
path, out_path, rate, times = args[0], args[1], args[2], [float(t) for t in args[3:]]
bpy.ops.wm.read_factory_settings(use_empty=True)
out = {"blender": bpy.app.version_string, "usd_built": bool(getattr(bpy.app.build_options, "usd", False))}
if path.lower().endswith(".glb"):
    addon_utils.enable("io_scene_gltf2")
    bpy.ops.import_scene.gltf(filepath=path)
elif not out["usd_built"]:  # Debian's Blender 3.4 is built without USD: say so instead of failing
    print("RESULT " + json.dumps(out))
    sys.exit(0)
else:
    bpy.ops.wm.usd_import(filepath=path)
scene = bpy.context.scene
fps = scene.render.fps / scene.render.fps_base
per_s = fps if rate == "scene" else float(rate)
out.update({"fps": fps, "frames": [], "actions": sorted(a.name for a in bpy.data.actions), "meshes": {}})
meshes = [o for o in bpy.data.objects if o.type == "MESH"]
for o in meshes:
    keys = o.data.shape_keys.key_blocks if o.data.shape_keys else []
    out["meshes"][o.name] = {"vertices": len(o.data.vertices), "faces": len(o.data.polygons),
                             "shape_keys": [k.name for k in keys], "modifiers": [m.type for m in o.modifiers],
                             "volume_mm3": [], "world_m": []}
for t in times:
    frame = round(t * per_s)
    out["frames"].append(frame)
    scene.frame_set(frame)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for o in meshes:
        bm = bmesh.new()
        bm.from_object(o, depsgraph)  # shape keys, their animated values and modifiers applied
        rec = out["meshes"][o.name]
        rec["volume_mm3"].append(bm.calc_volume(signed=True))
        co = np.array([v.co[:] for v in bm.verts], float).reshape(-1, 3)
        world = np.array(o.evaluated_get(depsgraph).matrix_world)
        rec["world_m"].append((co @ world[:3, :3].T + world[:3, 3]).tolist())
        bm.free()
with open(out_path, "w") as fh:
    json.dump(out, fh)
print("RESULT " + json.dumps({k: out[k] for k in ("blender", "usd_built", "fps", "frames", "actions")}))
