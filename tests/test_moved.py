"""Module paths of before 0.8 fail with one line naming the path now (lungdeform._moved)."""

import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

import lungdeform
from lungdeform._moved import MOVED


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_path_fails_naming_the_new_one(old):
    # truth: the new path imports (the message would send a user nowhere otherwise) and the old one
    # raises ModuleNotFoundError whose one line names both paths
    new, version = MOVED[old]
    assert importlib.import_module(f"lungdeform.{new}").__name__ == f"lungdeform.{new}"
    with pytest.raises(ModuleNotFoundError) as caught:
        importlib.import_module(f"lungdeform.{old}")
    assert str(caught.value) == f"lungdeform.{old} moved to lungdeform.{new} in {version} (docs/CHANGELOG.md)"
    assert f"lungdeform.{old}" not in sys.modules


def test_every_import_form_names_the_new_path():
    # `from package import name` swallows a ModuleNotFoundError that names the module it looked
    # for (and says "cannot import name"); each form a user writes must show the new path
    for statement in ("import lungdeform.mesh", "from lungdeform import mesh",
                      "from lungdeform.mesh import Surface", "import lungdeform.sliding as s"):
        with pytest.raises(ModuleNotFoundError, match=r"moved to lungdeform\.(geometry\.mesh|interior\.sliding)"):
            exec(statement, {})


def test_a_typo_is_still_the_usual_module_not_found():
    # only the names of MOVED are answered: anything else fails as Python says it
    with pytest.raises(ModuleNotFoundError, match=r"No module named 'lungdeform\.mehs'"):
        importlib.import_module("lungdeform.mehs")


def test_every_target_is_a_module_and_no_old_path_is_one():
    # a target that moved again would send users to a path that fails too; an old path that is a
    # module again would never be answered (the finder sits last): both are mistakes in MOVED
    root = Path(lungdeform.__file__).parent
    for old, (new, _version) in MOVED.items():
        assert importlib.util.find_spec(f"lungdeform.{new}").origin.startswith(str(root)), new
        parts = old.split(".")
        assert not root.joinpath(*parts[:-1], parts[-1] + ".py").exists(), old
        assert not root.joinpath(*parts).is_dir(), old


def test_the_finder_is_installed_once_and_last():
    # reloading the package must not stack finders, and a real module must always win over it
    code = ("import importlib, sys, lungdeform\n"
            "importlib.reload(lungdeform); importlib.reload(lungdeform)\n"
            "names = [type(f).__name__ for f in sys.meta_path]\n"
            "print(names.count('MovedModuleFinder'), names[-1])")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(Path(lungdeform.__file__).parent.parent)})
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["1", "MovedModuleFinder"]


def test_release_note_lists_every_moved_path():
    # docs/CHANGELOG.md lists old → new for users; it must be MOVED exactly, row by row, or the page
    # would send a user to a path that fails (or leave one out)
    doc = (Path(__file__).parents[1] / "docs" / "CHANGELOG.md").read_text(encoding="utf-8")
    table = doc.split("| old path | path now | moved in |", 1)[1].split("\n\n", 1)[0]
    documented = {}
    for row in table.strip().splitlines()[1:]:
        old, new, version = (cell.strip(" `") for cell in row.strip().strip("|").split("|"))
        documented[old.removeprefix("lungdeform.")] = (new.removeprefix("lungdeform."), version)
    assert documented == MOVED


def test_names_of_the_old_plot_module_fail_naming_their_module():
    # truth: each name is defined in the module the message names; `plot.NAME` and `from
    # lungdeform.plot import NAME` both show that one line (motion: a module of the same name now)
    import lungdeform.plot as plot

    doc = (Path(__file__).parents[1] / "docs" / "CHANGELOG.md").read_text(encoding="utf-8")
    for name, module in plot.MOVED.items():
        assert hasattr(importlib.import_module(f"lungdeform.plot.{module}"), name), (name, module)
        assert f"`{name}`" in doc.split(f"| `plot.{module}` |", 1)[1].split("\n", 1)[0], name
        if name == module:
            continue
        expected = f"lungdeform.plot.{name} moved to lungdeform.plot.{module}.{name} in 0.8 (docs/CHANGELOG.md)"
        with pytest.raises(ImportError) as caught:
            getattr(plot, name)
        assert str(caught.value) == expected
        with pytest.raises(ImportError, match=rf"moved to lungdeform\.plot\.{module}\.{name} "):
            exec(f"from lungdeform.plot import {name}", {})
    with pytest.raises(AttributeError):
        plot.not_a_figure  # noqa: B018
    assert not hasattr(plot, "not_a_figure")
