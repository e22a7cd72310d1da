#!/usr/bin/env python
"""Build the small lung meshes shipped in src/lungdeform/data/ (run from the repository root).

    python scripts/make_default_lungs.py [DATA_DIR]

DATA_DIR defaults to $LUNGDEFORM_DATA or ../shared/data. Sources (licences in NOTICE and
src/lungdeform/data/README.md):

- itk-right-lung-two-volumes/CT_3D_lung_fixed_mask.mha (the smaller-volume "fixed" mask,
  Apache-2.0) -> itk_right_lung.ply
- coronacases-lung-lobes/Coronacases_001_lobes.nii.gz (CC BY 4.0), labels 1,2 -> left,
  3,4,5 -> right -> coronacases_001_left.ply, coronacases_001_right.ply

Each: lungdeform.io.mask.extract_surface (largest component, cavities filled, 1-voxel pad,
marching cubes at 0.5, world mm LPS, Taubin 10 iterations, decimation to TARGET_VERTICES,
cleanup), checked with check_surface, written as binary PLY.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from lungdeform.io.image import read_image
from lungdeform.io.mask import LOBE_LABELS, extract_surface
from lungdeform.io.meshfile import write_mesh

TARGET_VERTICES = 3000
OUT = Path(__file__).resolve().parents[1] / "src" / "lungdeform" / "data"


def main(argv: list[str]) -> int:
    data = Path(argv[0] if argv else os.environ.get("LUNGDEFORM_DATA", "../shared/data"))
    jobs = [
        (data / "itk-right-lung-two-volumes" / "CT_3D_lung_fixed_mask.mha", None, "itk_right_lung.ply"),
        (data / "coronacases-lung-lobes" / "Coronacases_001_lobes.nii.gz", LOBE_LABELS["left"],
         "coronacases_001_left.ply"),
        (data / "coronacases-lung-lobes" / "Coronacases_001_lobes.nii.gz", LOBE_LABELS["right"],
         "coronacases_001_right.ply"),
    ]
    images = {}
    for src, labels, out_name in jobs:
        if src not in images:
            images[src] = read_image(src)
        t0 = time.perf_counter()
        full = extract_surface(images[src], labels)
        small = extract_surface(images[src], labels, target_vertices=TARGET_VERTICES)
        path = write_mesh(OUT / out_name, small.surface.vertices, small.surface.faces)
        ratio = small.surface.volume / full.surface.volume - 1
        print(f"{path.name}: {small.surface.n_vertices} vertices, {len(small.surface.faces)} faces, "
              f"{small.surface.volume_ml:.1f} mL (full resolution {full.surface.volume_ml:.1f} mL, "
              f"{100 * ratio:+.2f} %), {time.perf_counter() - t0:.1f} s")
        for note in small.notes:
            print(f"    {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
