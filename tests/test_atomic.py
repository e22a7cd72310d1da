"""Atomic writes leave either the new file or the old one, never a partial file."""

import pytest

from lungdeform.atomic import atomic_dir, atomic_path, write_json, write_text


def test_success_replaces_and_cleans_up(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    write_text(target, "new")
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    assert oct(target.stat().st_mode & 0o777) != oct(0o600)  # ordinary permissions, not mkstemp's


def test_failure_keeps_the_old_file(tmp_path):
    target = tmp_path / "m.json"
    write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert target.read_text().strip().startswith("{") and '"a": 1' in target.read_text()
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]


def test_unwritable_folder_names_the_target_not_the_temporary(tmp_path, monkeypatch):
    # a read-only folder (simulated: tests may run as root, who can write anywhere) used to report
    # "error: /out/.model.npz.m2_yo8ap.npz: Read-only file system", a file the user never named
    import errno
    import tempfile

    from lungdeform.atomic import write_bytes

    def refuse(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(tmp_path / ".model.npz.abc123.npz"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(OSError) as info:
        write_bytes(tmp_path / "model.npz", b"x")
    assert info.value.filename == str(tmp_path / "model.npz") and info.value.errno == errno.EROFS
    assert list(tmp_path.iterdir()) == []


def test_finite_json_makes_strict_json():
    # NaN and infinities (also numpy's, inside arrays and nested containers) become null, so the
    # output parses with a strict reader; finite values are unchanged
    import json
    import math

    import numpy as np

    from lungdeform.atomic import finite_json

    data = {"a": float("nan"), "b": [1.0, np.inf, np.float64(2.5)], "c": np.array([np.nan, 3.0]), "d": "x", "e": 4}
    text = json.dumps(finite_json(data), allow_nan=False)
    back = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    assert back == {"a": None, "b": [1.0, None, 2.5], "c": [None, 3.0], "d": "x", "e": 4}
    assert not math.isnan(back["b"][2])


def test_atomic_dir_publishes_whole_or_nothing(tmp_path):
    # a folder written through atomic_dir appears only complete; a failure inside leaves the previous
    # folder as it was and no temporary folder beside it
    out = tmp_path / "set"
    with atomic_dir(out) as tmp:
        (tmp / "a.txt").write_text("1")
        assert not out.exists()
    assert [p.name for p in out.iterdir()] == ["a.txt"]
    with pytest.raises(RuntimeError):
        with atomic_dir(out) as tmp:
            (tmp / "b.txt").write_text("2")
            raise RuntimeError("stopped")
    assert [p.name for p in out.iterdir()] == ["a.txt"] and [p.name for p in tmp_path.iterdir()] == ["set"]
    with atomic_dir(out) as tmp:
        (tmp / "c.txt").write_text("3")
    assert [p.name for p in out.iterdir()] == ["c.txt"] and [p.name for p in tmp_path.iterdir()] == ["set"]


def test_a_target_under_a_regular_file_is_named(tmp_path):
    # why: mkdir said only "File exists" (naming neither the output nor the file in its way)
    (tmp_path / "plain").write_text("x")
    with pytest.raises(NotADirectoryError) as info:
        write_text(tmp_path / "plain" / "sub" / "out.txt", "y")
    assert info.value.filename == str(tmp_path / "plain" / "sub" / "out.txt")
    assert f"{tmp_path / 'plain'} is a file, not a folder" in info.value.strerror


def test_a_set_of_files_appears_whole_or_not_at_all(tmp_path):
    # why: warp --phases wrote phase 0 before phase 1 was computed; atomic_paths renames the set at the end
    from lungdeform.atomic import atomic_paths

    paths = [tmp_path / f"p{i}.txt" for i in range(3)]
    with pytest.raises(RuntimeError):
        with atomic_paths(paths) as tmps:
            tmps[0].write_text("0")
            raise RuntimeError("stopped after the first")
    assert list(tmp_path.iterdir()) == []
    with atomic_paths(paths) as tmps:
        for i, t in enumerate(tmps):
            t.write_text(str(i))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p0.txt", "p1.txt", "p2.txt"]


def test_only_a_dead_writers_temporaries_are_removed(tmp_path):
    # why: names carry the writer's process id: a dead writer's leftovers go, a live one's and
    # the user's own hidden files (not of the temporary pattern) stay
    import os
    import subprocess
    import sys

    from lungdeform.atomic import remove_stale

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    gone = [tmp_path / f".a.mha.{dead.pid}.x1y2z3w4.mha", tmp_path / f".a.mha.{dead.pid}.q1w2e3r4.partial"]
    kept = [tmp_path / f".a.mha.{os.getpid()}.x1y2z3w4.mha", tmp_path / ".a.mha.5.mha", tmp_path / ".b.mha.1.x1y2z3w4",
            tmp_path / "a.mha"]
    gone[1].mkdir()
    for p in [gone[0], *kept]:
        p.write_text("x")
    remove_stale(tmp_path / "a.mha")
    assert sorted(tmp_path.iterdir()) == sorted(kept)


def test_write_npz_reads_back_as_numpy_writes_it_and_an_exception_leaves_nothing(tmp_path, monkeypatch):
    # why: numpy.load is the reader; the archive must hold the same arrays (dtypes, shapes, values) as
    # numpy.savez/savez_compressed write. An exception part way (a signal while a member is written)
    # must leave no file and no archive half-closed for the garbage collector (numpy.savez did:
    # "Exception ignored in ZipFile.__del__", an error under filterwarnings = error)
    import numpy as np

    from lungdeform.atomic import write_npz
    rng = np.random.default_rng(7)
    arrays = {"a": rng.normal(size=(5, 3)), "b": np.arange(6, dtype=np.int32).reshape(2, 3), "s": np.array("x/y"),
              "lung/left/u": rng.normal(size=(4, 3)).astype(np.float32)}
    for compress in (False, True):
        path = write_npz(tmp_path / f"m{compress}.npz", arrays, compress=compress)
        np.savez(tmp_path / "ref.npz", **arrays)
        with np.load(path) as got, np.load(tmp_path / "ref.npz") as ref:
            assert sorted(got.files) == sorted(ref.files)
            for k in ref.files:
                assert got[k].dtype == ref[k].dtype and np.array_equal(got[k], ref[k])
    calls = []

    def failing(member, value, allow_pickle=False):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(member, value, allow_pickle=allow_pickle)

    real = np.lib.format.write_array
    monkeypatch.setattr(np.lib.format, "write_array", failing)
    with pytest.raises(KeyboardInterrupt):
        write_npz(tmp_path / "cut.npz", arrays)
    assert not [p for p in tmp_path.iterdir() if "cut" in p.name]


def test_outputs_appear_together_even_when_the_renaming_is_interrupted(tmp_path, monkeypatch):
    # why (issue 36): files renamed one by one at the end left the first ones when a signal came
    # between two renames (warp --phases to .mha after SIGTERM: ct_phase00 … left). Truth: an
    # interruption at the third rename puts every target back as it was (the previous file of the
    # same name restored, the new folder gone) and leaves no temporary name
    import os

    from lungdeform.atomic import staged_outputs

    (tmp_path / "old.txt").write_text("previous")
    calls = {"n": 0}
    real = os.rename

    def interrupted(a, b):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(a, b)

    monkeypatch.setattr(os, "rename", interrupted)
    with pytest.raises(KeyboardInterrupt), staged_outputs() as staging:
        staging.file(tmp_path / "old.txt").write_text("new")
        (staging.folder(tmp_path / "out") / "a.csv").write_text("a")
        staging.file(tmp_path / "sub" / "rs.dcm").write_bytes(b"rs")
    monkeypatch.setattr(os, "rename", real)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.txt"]
    assert (tmp_path / "old.txt").read_text() == "previous"
    # uninterrupted: all three, an existing folder's own files kept
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "mine.txt").write_text("kept")
    with staged_outputs() as staging:
        staging.file(tmp_path / "old.txt").write_text("new")
        (staging.folder(tmp_path / "out") / "a.csv").write_text("a")
        staging.file(tmp_path / "sub" / "rs.dcm").write_bytes(b"rs")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.txt", "out", "sub"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.csv", "mine.txt"]
    assert (tmp_path / "old.txt").read_text() == "new" and (tmp_path / "sub" / "rs.dcm").read_bytes() == b"rs"


def test_a_failed_write_leaves_no_folder_it_made(tmp_path):
    # why (issue 36): a refused run left the empty folders made for its output (validate copd's case
    # folder). Truth: after the failure only what was there before
    from lungdeform.atomic import made_folder

    with pytest.raises(RuntimeError), atomic_path(tmp_path / "a" / "b" / "c.txt") as tmp:
        tmp.write_text("x")
        raise RuntimeError("refused")
    with pytest.raises(RuntimeError), atomic_dir(tmp_path / "d" / "e"):
        raise RuntimeError("refused")
    with pytest.raises(RuntimeError), made_folder(tmp_path / "f" / "g"):
        raise RuntimeError("refused")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError), made_folder(tmp_path / "f") as f:  # a long run keeps what it finished
        write_text(f / "case1" / "metrics.json", "{}")
        raise RuntimeError("case 2 refused")
    assert (tmp_path / "f" / "case1" / "metrics.json").exists()
