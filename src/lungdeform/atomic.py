"""Atomic file and folder writes: write to a temporary file (folder) beside the target, then rename.

A failure (an exception, Ctrl-C, SIGTERM: the CLI turns it into Ctrl-C) leaves no half-written
output: the temporary file or folder is removed, any previous file or folder at the target is
untouched, and the folders created to hold it are removed again (:func:`make_parent`,
:func:`remove_made`). A command writing several outputs stages them (:func:`staged_outputs`,
:func:`staged_dir`, :func:`atomic_paths`): they appear together at the end, or not at all, also when
the renaming itself is interrupted (:func:`commit_all`); :func:`made_folder` is for
long runs that keep what they finished (resumable), and remove only the empty folders they made. Temporary names carry the writer's process id, so what a killed run left (SIGKILL, a
power cut) is recognised and removed by the next write to the same target (:func:`remove_stale`).
Files and folders get the ordinary permissions of the umask (not the 0600/0700 of :mod:`tempfile`).
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import shutil
import tempfile
import uuid
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from lungdeform.errors import ReadError


def make_parent(path) -> list[Path]:
    """Create ``path``'s folder (and its parents); returns the folders it created, the deepest last
    (:func:`remove_made` takes them away again after a failure). A path under a regular file is
    refused with an :class:`OSError` naming ``path`` and the file in its way (``mkdir`` says only
    "File exists")."""
    path = Path(path)
    missing = []
    for above in path.parents:
        if above.exists():
            if not above.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, f"{above} is a file, not a folder", str(path))
            break
        missing.append(above)
    path.parent.mkdir(parents=True, exist_ok=True)
    return missing[::-1]


def remove_made(folders) -> None:
    """Remove ``folders`` (made by :func:`make_parent` or :func:`made_folder`, the deepest last) that
    are still empty, the deepest first: a failed run leaves no folder it created."""
    for folder in reversed(list(folders)):
        try:
            Path(folder).rmdir()
        except OSError:  # not empty (something else is in it now), or gone: left as it is
            break


@contextmanager
def made_folder(path) -> Iterator[Path]:
    """The folder ``path``, created with the parents it lacks for the block; when the block fails (an
    exception, Ctrl-C) the folders this created are removed while empty, so a refused run leaves no
    folder behind, while a long run that finished part of its work (a case folder, complete) keeps it
    and resumes from it. Every output inside is written atomically by its own writer."""
    path = Path(path)
    made = make_parent(path / "_")
    try:
        yield path
    except BaseException:
        remove_made(made)
        raise


class Staging:
    """The outputs of one command, written to hidden temporary names beside their targets and renamed
    into place together by :func:`staged_outputs` (:meth:`commit`), or all removed (:meth:`discard`)."""

    def __init__(self):
        self._files: list[tuple[Path, Path]] = []  # (temporary, target)
        self._folders: list[tuple[Path, Path]] = []
        self._made: list[Path] = []

    def file(self, path, suffix: str | None = None) -> Path:
        """A temporary file beside ``path`` (the target's suffix, or ``suffix``) that becomes ``path``."""
        path = Path(path)
        self._made += make_parent(path)
        remove_stale(path)
        try:
            fd, tmp = tempfile.mkstemp(prefix=_prefix(path), suffix=path.suffix if suffix is None else suffix,
                                       dir=path.parent)
        except OSError as exc:  # name the output the user asked for, not the hidden temporary file
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file ordinary permissions
        self._files.append((Path(tmp), path))
        return Path(tmp)

    def folder(self, path) -> Path:
        """A temporary folder beside ``path`` for what a command writes into the folder ``path``: it
        becomes ``path`` when ``path`` does not exist, else each of its entries moves into ``path``
        (a file of the same name replaced, the folder's other files kept)."""
        path = Path(path)
        if path.exists() and not path.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, f"{path} is a file, not a folder", str(path))
        self._made += make_parent(path)
        remove_stale(path)
        try:
            tmp = Path(tempfile.mkdtemp(prefix=_prefix(path), suffix=".partial", dir=path.parent))
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp creates 0700
        self._folders.append((tmp, path))
        return tmp

    def commit(self) -> None:
        """Rename every output into place, all or none (:func:`commit_all`)."""
        moves = list(self._files)
        for tmp, path in self._folders:
            moves += [(tmp, path)] if not path.exists() else [(e, path / e.name) for e in sorted(tmp.iterdir())]
        commit_all(moves)
        for tmp, path in self._folders:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def discard(self) -> None:
        """Remove every temporary output and the folders made for them."""
        for tmp, _ in self._files:
            tmp.unlink(missing_ok=True)
        for tmp, _ in self._folders:
            shutil.rmtree(tmp, ignore_errors=True)
        remove_made(self._made)


@contextmanager
def staged_outputs() -> Iterator[Staging]:
    """A :class:`Staging` for the outputs of one command: each written to its temporary name
    (:meth:`Staging.file`, :meth:`Staging.folder`); when the block ends they appear together, and on
    a failure (an exception, Ctrl-C, SIGTERM, also while they are being renamed) none does and every
    target is as it was (:func:`commit_all`)."""
    staging = Staging()
    try:
        yield staging
        staging.commit()
    except BaseException:
        staging.discard()
        raise


def commit_all(moves) -> None:
    """Rename each ``(temporary, target)`` of ``moves``, all or none: a target that exists is moved
    aside first and removed at the end; when a rename fails or is interrupted, the targets renamed
    so far go back to their temporary names and the ones moved aside are put back."""
    done, aside = [], []
    try:
        for tmp, target in moves:
            target = Path(target)
            if target.exists() or target.is_symlink():
                old = target.parent / f"{_prefix(target)}{uuid.uuid4().hex[:8]}.old"
                os.rename(target, old)
                aside.append((old, target))
            os.rename(tmp, target)
            done.append((tmp, target))
    except BaseException:
        for tmp, target in reversed(done):
            os.rename(target, tmp)
        for old, target in reversed(aside):
            os.rename(old, target)
        raise
    for old, _ in aside:
        old.unlink() if old.is_symlink() or not old.is_dir() else shutil.rmtree(old, ignore_errors=True)


@contextmanager
def staged_dir(path) -> Iterator[Path]:
    """Yield a hidden folder beside ``path`` for every output a command writes into the folder
    ``path`` (:meth:`Staging.folder`); at the end of the block they appear there together. On a
    failure (an exception, Ctrl-C, SIGTERM) nothing appears and ``path`` is as it was: not created
    when it did not exist, its files untouched."""
    with staged_outputs() as staging:
        yield staging.folder(path)


@contextmanager
def atomic_path(path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success it replaces ``path``.

    ``suffix`` (default: the target's own) keeps writers that choose a format by file name happy.
    """
    path = Path(path)
    made = make_parent(path)
    remove_stale(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=_prefix(path), suffix=path.suffix if suffix is None else suffix,
                                   dir=path.parent)
    except OSError as exc:  # name the output the user asked for, not the hidden temporary file
        remove_made(made)
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file ordinary permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        remove_made(made)  # the folders made for it: a failed write leaves none
        raise


@contextmanager
def atomic_paths(paths, suffixes=None) -> Iterator[list[Path]]:
    """Yield a temporary path beside each of ``paths`` (:func:`atomic_path`, ``suffixes`` its
    ``suffix`` per path); once the block has written them all each replaces its target, and on a
    failure all are removed: a set of files (the phases of a 4-D CT) appears whole or not at all."""
    suffixes = [None] * len(paths) if suffixes is None else list(suffixes)
    with staged_outputs() as staging:  # renamed all or none, also when interrupted while renaming
        yield [staging.file(p, x) for p, x in zip(paths, suffixes)]


def _prefix(path: Path) -> str:
    """The start of a temporary name beside ``path``: hidden, the target's name, this process's id."""
    return f".{path.name}.{os.getpid()}."


def remove_stale(path) -> None:
    """Remove the temporary files and folders beside ``path`` that a writer left when it was killed
    (SIGKILL, a power cut): named :func:`_prefix` + 8 random characters, by a process that is gone.
    Each folder is listed once per process (:data:`_HIDDEN`), so writing many files into one folder
    stays linear."""
    path = Path(path)
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(\d+)\.[a-z0-9_]{{8}}(?:\..+)?")
    hidden = _hidden(path.parent)
    for name in [n for n in hidden if pattern.fullmatch(n) and not _alive(int(pattern.fullmatch(n).group(1)))]:
        p = path.parent / name
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
        hidden.discard(name)


#: Per folder (its absolute path), the hidden names it held when this process first wrote there.
_HIDDEN: dict[str, set[str]] = {}


def _hidden(folder: Path) -> set[str]:
    key = os.path.abspath(folder)
    if key not in _HIDDEN:
        try:
            _HIDDEN[key] = {e.name for e in os.scandir(folder) if e.name.startswith(".")}
        except OSError:
            return set()
    return _HIDDEN[key]


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (this one included)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        return True
    except (OverflowError, ValueError):
        return False
    return True


def _umask() -> int:
    """The process umask (read by setting and restoring it)."""
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextmanager
def atomic_dir(path) -> Iterator[Path]:
    """Yield a fresh hidden folder beside ``path`` (mode ``0o777 & ~umask``, like ``mkdir``); on
    success it is renamed to ``path`` (:func:`replace_dir`), so that ``path`` holds the whole set or
    its previous content; on failure (an exception, Ctrl-C) it is removed."""
    path = Path(path)
    made = make_parent(path)
    remove_stale(path)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=_prefix(path), suffix=".partial", dir=path.parent))
    except OSError as exc:  # name the output the user asked for, not the hidden temporary folder
        remove_made(made)
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    try:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp creates 0700
        yield tmp
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        remove_made(made)  # the folders made for it (a case folder above a lung's): a failed run leaves none
        raise


def replace_dir(src, dst) -> None:
    """Rename the complete folder ``src`` to ``dst``; a previous ``dst`` is moved aside first (and
    put back if the rename fails) and removed after, so ``dst`` never holds a mix of the two."""
    src, dst = Path(src), Path(dst)
    old = None
    if dst.exists() or dst.is_symlink():
        old = dst.parent / f"{_prefix(dst)}{uuid.uuid4().hex[:8]}.old"
        os.rename(dst, old)
    try:
        os.rename(src, dst)
    except BaseException:
        if old is not None:
            os.rename(old, dst)
        raise
    if old is not None:
        old.unlink() if old.is_symlink() or not old.is_dir() else shutil.rmtree(old, ignore_errors=True)


def write_bytes(path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_npz(path, arrays: dict, *, compress: bool = False) -> Path:
    """Write ``arrays`` (name → array) as a NumPy ``.npz`` archive (what :func:`numpy.load` reads,
    as :func:`numpy.savez` writes it), atomically. Every zip member and the archive are closed by
    ``with`` blocks, so an exception (a signal) part way leaves no archive half-closed for the
    garbage collector, which ``numpy.savez`` does (its clean-up then fails on the closed file)."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with (atomic_path(path) as tmp, open(tmp, "wb") as fh,
          zipfile.ZipFile(fh, "w", compression=method, allowZip64=True) as archive):
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
    return Path(path)


def write_text(path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def jsonable(value):
    """``json.dumps`` default for numpy scalars and arrays; anything else is an error."""

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def finite_json(value):
    """``value`` with every float NaN or infinity (also inside numpy arrays, lists and dicts)
    replaced by ``None``: strict JSON (``null``), which every reader accepts; bare ``NaN`` is not
    JSON and JavaScript's ``JSON.parse`` rejects it."""


    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return finite_json(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path, data, *, strict: bool = False, **kwargs) -> Path:
    """``data`` as JSON (indent 2, numpy values converted) written atomically; ``strict``: NaN and
    infinities become ``null`` (:func:`finite_json`), so any JSON reader accepts the file."""
    kwargs.setdefault("indent", 2)
    kwargs.setdefault("default", jsonable)
    if strict:
        data = finite_json(data)
        kwargs["allow_nan"] = False
    return write_text(path, json.dumps(data, **kwargs) + "\n")


def read_schema_json(path, schema: str, version: int, what: str) -> dict:
    """The JSON object in ``path`` whose ``schema`` and ``schema_version`` are ``schema`` and
    ``version``; :class:`~lungdeform.errors.ReadError` naming the file and ``what`` it should be otherwise."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ReadError(f"{p}: not a readable {what} ({exc.__class__.__name__}: {exc})") from exc
    if not isinstance(data, dict) or data.get("schema") != schema or data.get("schema_version") != version:
        raise ReadError(f"{p}: not a {schema} file of version {version}")
    return data
