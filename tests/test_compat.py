"""The module names of lungdeform 0.4 (``lungdeform.mesh``, …) import the moved modules (lungdeform._compat)."""

import importlib
import importlib.util
import os
import pkgutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import lungdeform
from lungdeform._compat import MOVED

#: Old names that are subpackages now (they re-export their old modules' names): not aliased.
PACKAGES = ("model", "io", "breathing", "interior", "fit", "cohort", "bench")


def _forget(monkeypatch, old: str) -> None:
    """Make the next import of ``lungdeform.<old>`` go through the finder again (first import)."""
    monkeypatch.delitem(sys.modules, f"lungdeform.{old}", raising=False)
    monkeypatch.delattr(lungdeform, old, raising=False)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_name_is_the_new_module_with_a_warning(monkeypatch, old):
    # The finder returns the module at its new path itself (not a copy), registered under both
    # names, and says where the module is now; a copy would fail `is`, a silent alias the
    # deprecated_call, a wrong target the message check.
    _forget(monkeypatch, old)
    new = importlib.import_module(f"lungdeform.{MOVED[old]}")
    with pytest.deprecated_call(match=rf"lungdeform\.{old} is deprecated .* import lungdeform\.{MOVED[old]} instead"):
        alias = importlib.import_module(f"lungdeform.{old}")
    assert alias is new
    assert sys.modules[f"lungdeform.{old}"] is new
    assert new.__name__ == f"lungdeform.{MOVED[old]}"
    # the module keeps its own spec (importlib gives the alias's spec to the module it loads)
    assert new.__spec__.name == f"lungdeform.{MOVED[old]}"


def test_old_import_statements(monkeypatch):
    # The forms users wrote in 0.4, each resolved through the finder on its first import.
    from lungdeform.geometry.mesh import Surface as new_surface
    from lungdeform.interior import sliding as new_sliding

    for old in ("mesh", "trace", "sliding"):
        _forget(monkeypatch, old)
    with pytest.deprecated_call():
        from lungdeform.mesh import Surface
    with pytest.deprecated_call():
        from lungdeform.trace import read_trace
    with pytest.deprecated_call():
        import lungdeform.sliding
    assert Surface is new_surface
    assert read_trace is importlib.import_module("lungdeform.breathing.trace").read_trace
    assert lungdeform.sliding is new_sliding


def test_warning_points_at_the_importing_line(monkeypatch):
    # A DeprecationWarning is shown by default only when attributed to the user's code (__main__),
    # so it must name the file with the import statement, not importlib or _compat.
    _forget(monkeypatch, "frame")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import lungdeform.frame  # noqa: F401
    assert [Path(w.filename).name for w in caught] == [Path(__file__).name]


def test_monkeypatch_through_either_name_is_seen_through_both(monkeypatch):
    # One module object under two names: patching an attribute through the old name changes
    # what the new name sees, and the reverse.
    _forget(monkeypatch, "presets")
    with pytest.deprecated_call():
        old = importlib.import_module("lungdeform.presets")
    new = importlib.import_module("lungdeform.breathing.presets")
    monkeypatch.setattr(old, "PRESETS", {"patched": None})
    assert new.PRESETS == {"patched": None}
    monkeypatch.setattr(new, "get_preset", len)
    assert old.get_preset is len


def test_a_typo_is_still_module_not_found():
    # Only the names of MOVED are aliased: anything else fails as before.
    with pytest.raises(ModuleNotFoundError, match="lungdeform.mehs"):
        importlib.import_module("lungdeform.mehs")
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("lungdeform.mesh.nothing")


def test_old_names_of_packages_are_the_packages():
    # model, io, … are subpackages now; the finder must not shadow them (it sits last on
    # sys.meta_path and does not list them), and they re-export the old modules' main names.
    assert not set(PACKAGES) & set(MOVED)
    for name in PACKAGES:
        module = importlib.import_module(f"lungdeform.{name}")
        assert hasattr(module, "__path__"), name
    from lungdeform.model import build_model
    from lungdeform.model.lung import build_model as new

    assert build_model is new


def test_every_target_is_a_module_and_no_old_name_is_one():
    # A target that moved again would make its alias fail; an old name that became a real
    # module would be shadowed silently (the real one wins): both would be mistakes in MOVED.
    root = Path(lungdeform.__file__).parent
    for old, new in MOVED.items():
        assert importlib.util.find_spec(f"lungdeform.{new}").origin.startswith(str(root)), new
        assert not (root / f"{old}.py").exists() and not (root / old).is_dir(), old


def test_package_code_never_uses_an_old_name():
    # Importing every module of the package with DeprecationWarning as an error succeeds: the
    # package's own imports use the new paths only (an old one would raise here).
    code = ("import importlib, pkgutil, lungdeform\n"
            "names = [m.name for m in pkgutil.walk_packages(lungdeform.__path__, 'lungdeform.')]\n"
            "for name in names: importlib.import_module(name)\n"
            "print(len(names))")
    env = {**os.environ, "PYTHONPATH": str(Path(lungdeform.__file__).parent.parent)}
    run = subprocess.run([sys.executable, "-W", "error::DeprecationWarning", "-c", code],
                         capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr
    expected = sum(1 for _ in pkgutil.walk_packages(lungdeform.__path__, "lungdeform."))
    assert int(run.stdout.split()[-1]) == expected > 50



def test_documented_mapping_is_the_one_used():
    # docs/ARCHITECTURE.md ("Compatibility") lists old → new for users; it must be MOVED exactly,
    # row by row, or the page would promise an import that fails (or hide one that works).
    doc = (Path(__file__).parents[1] / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    table = doc.split("| old (≤ 0.4) | new (0.5) |", 1)[1].split("\n\n", 1)[0]
    documented = {}
    for row in table.strip().splitlines()[1:]:
        old, new = ([n.strip(" `") for n in cell.split(",")] for cell in row.strip("|").split("|"))
        assert len(old) == len(new), row
        documented.update(zip(old, new))
    assert documented == MOVED
