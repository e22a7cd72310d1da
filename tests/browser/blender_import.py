"""Run inside Blender (``blender -b --factory-startup --python this.py -- FILE.glb T1 T2 …``): import a
.glb with Blender's own glTF importer, evaluate its animation at times T (s) and print one line
``RESULT {json}`` with each mesh's vertex count, shape keys, actions and enclosed volume (mm³, the
mesh's local frame) at each time."""

import json
import sys

import numpy as np

if not hasattr(np, "bool"):  # Debian's Blender 3.4 glTF add-on still uses np.bool (gone in numpy 1.24)
    np.bool = bool

import addon_utils  # noqa: E402
import bmesh  # noqa: E402
import bpy  # noqa: E402

args = sys.argv[sys.argv.index("--") + 1:]
path, times = args[0], [float(t) for t in args[1:]]
bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable("io_scene_gltf2")
bpy.ops.import_scene.gltf(filepath=path)
scene = bpy.context.scene
fps = scene.render.fps / scene.render.fps_base
out = {"fps": fps, "actions": sorted(a.name for a in bpy.data.actions), "meshes": {}}
for o in bpy.data.objects:
    if o.type == "MESH":
        keys = o.data.shape_keys.key_blocks if o.data.shape_keys else []
        out["meshes"][o.name] = {"vertices": len(o.data.vertices), "faces": len(o.data.polygons),
                                 "shape_keys": [k.name for k in keys], "volume_mm3": []}
for t in times:
    scene.frame_set(int(round(t * fps)))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for o in bpy.data.objects:
        if o.type == "MESH":
            bm = bmesh.new()
            bm.from_object(o, depsgraph)  # shape keys and their animated values applied
            out["meshes"][o.name]["volume_mm3"].append(bm.calc_volume(signed=True))
            bm.free()
print("RESULT " + json.dumps(out))
