"""Shared fixtures. Real-data tests use ``data_dir`` and skip, with the reason, without it."""

from __future__ import annotations

import locale as _locale
import os
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    """A local, seeded generator: every test that draws numbers is reproducible."""
    return np.random.default_rng(20080101)


@pytest.fixture(scope="session")
def traces_validated(data_dir, tmp_path_factory):
    """``run(command, *extra) -> (exit code, metrics dict, OUT)``: a ``lungdeform validate …`` command
    (``DATA`` standing for the shared breathing traces, ``OUT`` for a fresh folder, ``extra`` options
    appended) run once per session, whichever test asks first; its outputs are only read.

    Why: the real-data tests of ``validate breathing``, ``gating`` and ``prediction`` and the test of
    the documented tables (tests/test_docs_figures.py) read the same runs, a few minutes of CI each."""
    import json
    import shlex

    from lungdeform.cli.main import main

    traces = require_path(data_dir, "breathing-traces")
    runs = {}

    def run(command: str, *extra: str):
        key = (command, *extra)
        if key not in runs:
            out = tmp_path_factory.mktemp("validated") / "out"
            tokens = [traces.as_posix() if t == "DATA" else out.as_posix() if t == "OUT" else t for t in shlex.split(command)]
            assert tokens[:2] == ["lungdeform", "validate"], command
            code = main([*tokens[1:], *extra])
            runs[key] = (code, json.loads((out / "metrics.json").read_text(encoding="utf-8")), out)
        return runs[key]

    return run


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``$LUNGDEFORM_DATA`` (the shared real-data folder), or skip."""
    value = os.environ.get("LUNGDEFORM_DATA")
    if not value:
        pytest.skip("real data not available: set LUNGDEFORM_DATA=../shared/data to run this test")
    # Absolute: CI sets the relative ``../shared/data``, and tests write manifests into ``tmp_path``
    # whose relative paths would then resolve against the wrong folder.
    path = Path(value).resolve()
    if not path.is_dir():
        pytest.skip(f"LUNGDEFORM_DATA={value} is not a directory")
    return path


@pytest.fixture(scope="session")
def coronacases_001(data_dir):
    """The real Coronacases 001 lobe map (read once per run; tests must not modify it)."""
    from lungdeform.io.image import read_image

    return read_image(require_path(data_dir, "coronacases-lung-lobes", "Coronacases_001_lobes.nii.gz"))


def require_path(base: Path, *parts: str) -> Path:
    """``base/parts`` or skip, naming what is missing."""
    path = base.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data missing: {path}")
    return path


def ellipsoid_lung(side: str = "left", subdivisions: int = 3):
    """A lung-sized ellipsoid (semi-axes 45 × 70 × 110 mm, ≈ 1.45 L) on the patient's ``side``
    (LPS: left lung at x > 0), for tests that need a plausible closed lung surface."""
    from lungdeform.geometry.mesh import Surface, icosphere

    s = icosphere(subdivisions, 1.0)
    x = 90.0 if side == "left" else -90.0
    v = s.vertices * np.array([45.0, 70.0, 110.0]) + np.array([x, 20.0, -150.0])
    return Surface(v, s.faces, side)


@pytest.fixture
def left_lung():
    return ellipsoid_lung("left")


@pytest.fixture
def right_lung():
    return ellipsoid_lung("right")


#: The process locale when the tests started (before any GDCM call could change it).
_START_LOCALE = _locale.setlocale(_locale.LC_ALL)


@pytest.fixture(autouse=True)
def _process_locale_restored():
    # GDCM's DICOM writer (used to build test series, also in module-scoped fixtures) leaves the
    # process locale at "C", which turns every later open() without an explicit encoding ASCII:
    # every test starts and ends with the locale the session started with
    if _locale.setlocale(_locale.LC_ALL) != _START_LOCALE:
        _locale.setlocale(_locale.LC_ALL, _START_LOCALE)
    yield
    if _locale.setlocale(_locale.LC_ALL) != _START_LOCALE:
        _locale.setlocale(_locale.LC_ALL, _START_LOCALE)
