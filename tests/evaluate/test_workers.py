"""Worker processes that fit lungs side by side (lungdeform.evaluate.workers): results in order, timed
in the worker, errors re-raised, and an interrupted parent leaves no half-written folder."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from lungdeform.atomic import atomic_dir
from lungdeform.errors import InputError
from lungdeform.evaluate.workers import LungWorkers


def _burn(seconds: float, tag: str) -> tuple[str, int]:
    """Busy for ``seconds`` of CPU; the tag and the worker's pid."""
    t0 = time.process_time()
    while time.process_time() - t0 < seconds:
        pass
    return tag, os.getpid()


def _meet(folder: str, tag: str, other: str) -> bool:
    """Leave a file named ``tag`` in ``folder`` and wait (up to 60 s) for the file ``other``: True
    when both tasks were running at the same time."""
    open(os.path.join(folder, tag), "w").close()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if os.path.exists(os.path.join(folder, other)):
            return True
        time.sleep(0.02)
    return False


def _refuse(message: str):
    raise InputError(message)


def _write_slowly(folder: str, flag: str) -> str:
    """Write into an atomic folder, say so through ``flag``, then wait to be interrupted."""
    with atomic_dir(folder) as tmp:
        (tmp / "half.txt").write_text("half")
        with open(flag, "w") as f:
            f.write(str(tmp))
        time.sleep(60)
    return "finished"


def test_tasks_run_in_worker_processes_in_order_and_timed_there(tmp_path):
    # truth: each task returns its own tag, in the order given, from another process; each record's
    # CPU is its worker's (≥ the 0.3 s burnt; this process, waiting, burns almost none); two tasks
    # that each wait for the other finish only if they run at the same time (two workers)
    c0 = time.process_time()
    with LungWorkers(2) as workers:
        done = workers.map(_burn, [(0.3, "left"), (0.3, "right")])
        met = workers.map(_meet, [(str(tmp_path), "left", "right"), (str(tmp_path), "right", "left")])
    assert [d.value[0] for d in done] == ["left", "right"]
    assert os.getpid() not in {d.value[1] for d in done}
    assert all(d.cpu_seconds >= 0.29 and d.seconds >= d.cpu_seconds * 0.5 for d in done)
    assert time.process_time() - c0 < 0.5
    assert [m.value for m in met] == [True, True]


def test_an_error_in_a_task_is_raised_in_the_parent():
    # truth: a task's InputError comes back as the same error, with its message
    with LungWorkers(1) as workers, pytest.raises(InputError, match="no lung here"):
        workers.map(_refuse, [("no lung here",)])


def test_workers_count_is_checked():
    with pytest.raises(InputError, match="workers must be a whole number >= 1, got 0"):
        LungWorkers(0)
    with pytest.raises(InputError, match="inside `with LungWorkers"):
        LungWorkers(1).map(_burn, [(0.0, "x")])


def test_an_interrupted_parent_leaves_no_half_written_folder(tmp_path):
    # truth: Ctrl-C in the parent while a worker writes into an atomic folder: the worker is told
    # (SIGTERM), its task unwinds and removes the temporary folder; no output folder is left, and the
    # KeyboardInterrupt reaches the caller
    flag = tmp_path / "started"
    out = tmp_path / "lung"

    def interrupt_once_started():
        deadline = time.monotonic() + 60
        while not flag.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.2)
        os.kill(os.getpid(), signal.SIGINT)

    timer = threading.Thread(target=interrupt_once_started, daemon=True)
    # Ctrl-C as Python handles it (a test runner's worker process may ignore SIGINT)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with LungWorkers(1) as workers:
            timer.start()
            with pytest.raises(KeyboardInterrupt):
                workers.map(_write_slowly, [(str(out), str(flag))])
    finally:
        signal.signal(signal.SIGINT, previous)
    timer.join()
    half = flag.read_text()
    assert not os.path.exists(half) and not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["started"]
