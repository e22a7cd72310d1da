"""Small lung surfaces shipped with lungdeform (see README.md here and NOTICE for sources).

Built by ``scripts/make_default_lungs.py``; about 3000 vertices each, closed, 2-manifold, outward,
millimetres, LPS world frame of the source scan.
"""

from __future__ import annotations

from functools import lru_cache
from importlib import resources

from lungdeform.geometry.mesh import Surface, check_surface
from lungdeform.io.meshfile import read_mesh

FILES = {
    "left": "coronacases_001_left.ply",
    "right": "coronacases_001_right.ply",
    "itk_right": "itk_right_lung.ply",
}


@lru_cache(maxsize=None)
def _load(filename: str, name: str) -> Surface:
    with resources.as_file(resources.files(__name__).joinpath(filename)) as path:
        vertices, faces = read_mesh(path)
    v, f, _ = check_surface(vertices, faces, source=f"lungdeform/data/{filename}")
    return Surface(v, f, name)


def default_lungs() -> dict[str, Surface]:
    """``{"left": Surface, "right": Surface}``: Coronacases case 001 (CC BY 4.0), lobes merged per side.

    Volumes about 1.52 L (left) and 1.81 L (right); vertices in mm, LPS.
    """
    return {side: _load(FILES[side], f"coronacases_001_{side}") for side in ("left", "right")}


def itk_right_lung() -> Surface:
    """The ITKElastix example right lung at its smaller volume (about 3.36 L; Apache-2.0), mm LPS."""
    return _load(FILES["itk_right"], "itk_right_lung")
