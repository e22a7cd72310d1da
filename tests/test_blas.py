"""lungdeform.blas: the BLAS threads bounded inside the block, restored after it."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from lungdeform import blas
from lungdeform.errors import InputError


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_limited_bounds_every_blas_and_restores_it():
    # truth: threadpoolctl's own report of the loaded BLAS libraries (NumPy's and, once loaded,
    # SciPy's OpenBLAS) inside and after the block; a caller's own limit (2 here) comes back unchanged
    import scipy.linalg  # noqa: F401  (loads SciPy's BLAS, the second pool)

    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        assert before and all(n <= 2 for n in before)
        with blas.limited():
            assert all(n == 1 for n in _blas_threads())
            a = np.eye(3) * 2.0
            assert np.allclose(np.linalg.solve(a, np.ones(3)), 0.5)  # the BLAS still works inside
        assert _blas_threads() == before


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2"])
def test_limited_refuses_a_bad_count(bad):
    with pytest.raises(InputError, match="threads must be a whole number"):
        blas.limited(bad)
