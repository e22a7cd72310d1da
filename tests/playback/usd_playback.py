"""Run in a fresh Python process (``python usd_playback.py FILE OUT.json CODE …``): open a USD or USDZ file
with usd-core alone (no lungdeform), skin it as any UsdSkel client would (``UsdSkel.BakeSkinning`` over
the file's time range: blend shapes and joints applied to the points) and write ``OUT.json``: the stage
metadata, per mesh the world-space points (``UsdGeom.Xformable.ComputeLocalToWorldTransform``) at each
time code CODE, and the errors and warnings of every validator usd-core registers (``UsdValidation``)."""

import json
import sys

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdSkel, UsdValidation


def validate(stage) -> list[dict]:
    """Every registered validator (core, UsdGeom, UsdShade, UsdSkel, the USDZ/ARKit package rules …) on ``stage``."""
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    return [{"type": str(e.GetType()), "name": str(e.GetName()), "message": e.GetMessage()} for e in errors]


def main(path: str, out_path: str, codes: list[float]) -> None:
    stage = Usd.Stage.Open(path)
    out = {"usd_version": ".".join(map(str, Usd.GetVersion())),
           "validators": len(UsdValidation.ValidationRegistry().GetOrLoadAllValidators()),
           "issues": validate(stage),  # before skinning: the file as written
           "up_axis": str(UsdGeom.GetStageUpAxis(stage)), "meters_per_unit": UsdGeom.GetStageMetersPerUnit(stage),
           "default_prim": str(stage.GetDefaultPrim().GetPath()), "time_codes_per_second": stage.GetTimeCodesPerSecond(),
           "start": stage.GetStartTimeCode(), "end": stage.GetEndTimeCode(), "skinned": [], "meshes": {}}
    for prim in stage.Traverse():
        if prim.IsA(UsdSkel.Root):
            UsdSkel.BakeSkinning(UsdSkel.Root(prim), Gf.Interval(stage.GetStartTimeCode(), stage.GetEndTimeCode()))
            out["skinned"].append(str(prim.GetPath()))
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            rows = []
            for code in codes:
                local = np.array(mesh.GetPointsAttr().Get(code), float)
                m = np.array(mesh.ComputeLocalToWorldTransform(code))  # row vectors: p' = [p 1] · M
                rows.append((local @ m[:3, :3] + m[3, :3]).tolist())
            out["meshes"][prim.GetName()] = {"points_m": rows, "faces": len(mesh.GetFaceVertexCountsAttr().Get())}
    with open(out_path, "w") as fh:
        json.dump(out, fh)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], [float(c) for c in sys.argv[3:]])
