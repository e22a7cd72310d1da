"""Issue 37's 4-D CT target: a 10-phase 4-D CT fit (one lung) against a two-scan fit of the same lung.

Both in one process with ``lungdeform fit``'s defaults and ``--no-baselines``, after one untimed
warm-up (the numba caches loaded), five timed runs of each (``--repeats``), alternating; the ratio
of the medians, wall and CPU (the process's, every thread). The 4-D CT is the phantom of
``tests/fourdct_phantom.py``, a full cycle of 10 phases in one DICOM Frame of Reference (the lungs
scaled per axis by ``1 + 0.06 (1 − cos(2π p / 10)) / 2`` at phase ``p``); the two scans are its phases 0 % and 50 %
(``--align none``, as the 4-D CT, whose phases share the frame). docs/FITTING.md, issue 37.

Usage (from the repository root; about a minute on a quiet machine; WORK is made if missing and
its phantom reused)::

    .venv/bin/python scripts/fourdct_ratio.py WORK
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.fourdct_phantom

from lungdeform.cli.main import main  # noqa: E402
from tests.fourdct_phantom import write_cycle  # noqa: E402

FRAME_UID = "1.2.826.0.1.3680043.2.1125.99"


def _fit(args: list[str], out: Path) -> tuple[float, float]:
    """Wall and CPU seconds of one ``lungdeform fit`` of the right lung into ``out``."""
    t, c = time.perf_counter(), time.process_time()
    if main(["fit", *args, "--out", str(out), "--side", "right", "--no-baselines"]) != 0:
        raise SystemExit(f"lungdeform fit {' '.join(args)} failed")
    return time.perf_counter() - t, time.process_time() - c


def run(work: Path, repeats: int = 5) -> dict[str, list[tuple[float, float]]]:
    """The phantom in ``work/ct4d`` (written once), a warm-up, then ``repeats`` timed fits of each."""
    ct = work / "ct4d"
    if not ct.exists():
        scales = [1.0 + 0.06 * (1 - np.cos(2 * np.pi * p / 10)) / 2 for p in range(10)]
        write_cycle(ct, np.random.default_rng(0), scales, frame_uid=FRAME_UID)
    inputs = {"two": [str(ct / "phase0"), str(ct / "phase5"), "--align", "none"], "ten": [str(ct)]}
    _fit(inputs["two"], work / "warm")
    rows: dict[str, list[tuple[float, float]]] = {"two": [], "ten": []}
    for k in range(repeats):
        for name, args in inputs.items():
            rows[name].append(_fit(args, work / f"{name}{k}"))
    return rows


def cli(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="a working folder (the phantom and the fits' outputs)")
    parser.add_argument("--repeats", type=int, default=5, help="timed fits of each (default 5)")
    a = parser.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    rows = run(a.work, max(1, a.repeats))
    for name, r in rows.items():
        print(f"{name}: wall {[round(w, 2) for w, _ in r]} s, CPU {[round(c, 2) for _, c in r]} s")
    med = {name: np.median(np.array(r), axis=0) for name, r in rows.items()}
    wall, cpu = med["ten"] / med["two"]
    print(f"ratio ten phases / two scans: wall {wall:.2f}, CPU {cpu:.2f} (target <= 2)")
    return 0


if __name__ == "__main__":
    raise SystemExit(cli())
