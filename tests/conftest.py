"""Shared fixtures. Real-data tests use ``data_dir`` and skip, with the reason, without it."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    """A local, seeded generator: every test that draws numbers is reproducible."""
    return np.random.default_rng(20080101)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``$LUNGDEFORM_DATA`` (the shared real-data folder), or skip."""
    value = os.environ.get("LUNGDEFORM_DATA")
    if not value:
        pytest.skip("real data not available: set LUNGDEFORM_DATA=../shared/data to run this test")
    path = Path(value)
    if not path.is_dir():
        pytest.skip(f"LUNGDEFORM_DATA={value} is not a directory")
    return path


def require_path(base: Path, *parts: str) -> Path:
    """``base/parts`` or skip, naming what is missing."""
    path = base.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data missing: {path}")
    return path
