"""Atomic writes leave either the new file or the old one, never a partial file."""

import pytest

from lungdeform.atomic import atomic_path, write_json, write_text


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
