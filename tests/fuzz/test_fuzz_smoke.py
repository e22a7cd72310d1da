"""CI smoke of the fuzz harnesses: every reader gets a short, seeded random-mutation run (no atheris
needed) from seeds written by the package's own writers, and must raise nothing but the package's
documented errors (tests/fuzz/common.py states the rule). ``make fuzz`` runs the long version."""

import importlib
from pathlib import Path

import pytest

from tests.fuzz import common

RUNS = 400  # per reader; with the 2 s cap the whole smoke stays well under a minute
SECONDS = 2.0
AT_LEAST = 50  # inputs per reader however loaded the machine (45 ran in 2.4 s once under a load of 9)


@pytest.mark.parametrize("reader", list(common.READERS))
def test_reader_raises_only_package_errors(reader, tmp_path):
    # why: a reader handed mutated bytes of a valid file must refuse them with a LungdeformError;
    # any other exception escaping it is a crash (recorded with the input that caused it).
    seeds = [p.read_bytes() for p in common.make_seeds(reader, tmp_path / "seeds")]
    rec = common.mutate_loop(reader, seeds, RUNS, SECONDS, seed=1, out=tmp_path / "out", at_least=AT_LEAST)
    assert rec.executions >= AT_LEAST, rec.stats()  # the loop ran (the seeds alone are 3 + a few)
    assert not rec.crashes, "\n".join(f"{c['key']}: {c['message']} ({c['reproducer']})" for c in rec.crashes.values())


def test_the_harness_sees_a_crash(tmp_path, monkeypatch):
    # why: a reader that leaks a ValueError must be recorded as a crash, or the smoke proves nothing.
    def leaky(path):
        raise ValueError("boom")

    monkeypatch.setitem(common.READERS, "curve", (".csv", leaky))
    rec = common.mutate_loop("curve", [b"t_s,volume_ml\n"], 5, 1.0, out=tmp_path)
    assert list(rec.crashes) == ["ValueError @ " + next(iter(rec.crashes)).split(" @ ")[1]]
    assert (tmp_path / "curve").is_dir()


@pytest.mark.parametrize("reader", list(common.READERS))
def test_each_reader_has_a_harness(reader, tmp_path, monkeypatch):
    # why: make fuzz runs tests/fuzz/fuzz_<reader>.py for every reader; its TestOneInput must take a
    # seed through the reader (a valid file: no crash recorded)
    harness = importlib.import_module(f"tests.fuzz.fuzz_{reader}")
    assert harness.READER == reader and Path(harness.__file__).name == f"fuzz_{reader}.py"
    monkeypatch.setattr(common, "_RECORDERS", {})
    harness.TestOneInput(common.make_seeds(reader, tmp_path)[0].read_bytes())
    assert common._RECORDERS[reader].executions == 1 and not common._RECORDERS[reader].crashes


def test_each_input_replaces_the_last_whole(monkeypatch):
    # why: the recorder writes every input into one file it keeps open (truncate, then write at 0);
    # the reader must see exactly that input: a short one after a long one without the long one's tail
    seen = []
    monkeypatch.setitem(common.READERS, "curve", (".csv", lambda path: seen.append(Path(path).read_bytes())))
    rec = common.Recorder("curve", None)
    for data in (b"t_s,volume_ml\n0,2500\n1,2600\n", b"short", b""):
        rec.run(data)
    rec.close()
    assert seen == [b"t_s,volume_ml\n0,2500\n1,2600\n", b"short", b""]
    assert not rec.work.exists() and not rec.crashes
