"""Helpers shared by the export, server and browser tests: a small two-lung model, and node tools."""

from __future__ import annotations

import os
import shutil
import subprocess
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
VIEWER_DIR = REPO / "viewer"
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")


def ellipsoid(side: str, subdivisions: int = 3):
    """A lung-sized ellipsoid (semi-axes 60, 80, 110 mm) centred at x = ±90 mm, LPS."""
    from lungdeform.geometry.mesh import Surface, icosphere

    s = icosphere(subdivisions)
    centre = np.array([90.0 if side == "left" else -90.0, 0.0, 0.0])
    return Surface(s.vertices * np.array([60.0, 80.0, 110.0]) + centre, s.faces, side)


@lru_cache(maxsize=4)
def two_lungs(subdivisions: int = 3):
    """A built two-lung model (Table I constants, supine), cached for the session."""
    from lungdeform.model.lung import Model, build_lung

    lungs = {side: build_lung(ellipsoid(side, subdivisions), side, default="paper") for side in ("left", "right")}
    return Model(lungs, {"source": "test ellipsoids", "subdivisions": subdivisions})


@lru_cache(maxsize=1)
def embedded_lungs():
    """The embedded demo lungs (Coronacases 001, about 3,000 vertices each) built as ``lungdeform demo``
    builds them (population default, supine), cached for the session."""
    from lungdeform.data import default_lungs
    from lungdeform.model.lung import build_model

    return build_model(default_lungs())


def node_modules_or_skip(*packages: str) -> Path:
    """The viewer's folder if node and its node_modules (with ``packages``) are installed, else skip."""
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    for p in packages:
        if not (VIEWER_DIR / "node_modules" / p).is_dir():
            pytest.skip(f"viewer/node_modules/{p} missing: run 'npm ci' in viewer/ (make test does)")
    return VIEWER_DIR


def run_node(args: list[str], cwd: Path = VIEWER_DIR, env: dict | None = None, timeout: float = 300):
    return subprocess.run(["node", *args], cwd=cwd, capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=timeout,
                          env={**os.environ, **(env or {})})
