"""The threads of the BLAS libraries loaded (NumPy's and SciPy's OpenBLAS), bounded around a dense step.

NumPy and SciPy each bundle their own OpenBLAS, each with a thread pool as wide as the machine. On
the few-thousand-row systems of this package (CPD's M-step, the landmark correction's solves) the
threads gain little, and on a machine whose cores are busy they spin at their barriers: measured on
DIR-Lab COPDgene case 1's left lung (docs/FITTING.md, "The fit against registration"), one lung's fit
took 109 s wall and 49 s CPU with the default threads under a load of 16 on two cores, 64 s and 26 s
with one. :func:`limited` bounds both pools inside a ``with`` block and restores them on leaving
(``threadpoolctl``, a required dependency): nothing is set for the process, so a caller's own BLAS
use, before or after, keeps its setting. This module sits in the lowest layer and imports only
:mod:`lungdeform.errors`.
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits

from lungdeform.errors import InputError


def limited(threads: int = 1):
    """A context manager: inside it, every BLAS library loaded uses at most ``threads`` threads
    (``threadpoolctl.threadpool_limits``; the previous limits come back on leaving). It costs a few
    milliseconds (it lists the loaded libraries): put it around a whole dense step, not one product."""
    if not (isinstance(threads, int) and threads >= 1):
        raise InputError(f"threads must be a whole number >= 1, got {threads!r}")
    return threadpool_limits(limits=threads, user_api="blas")
