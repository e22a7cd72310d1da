"""The package's architecture is a contract (docs/ARCHITECTURE.md): layers, no import cycles, short
functions, one plotting module. Each figure is measured from the source here, so a change that breaks
the contract fails ``make test``.
"""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "lungdeform"
REPO = PACKAGE.parents[1]
#: optional dependencies: the only imports allowed inside functions
#: fcntl: POSIX only (the cohort lock); pxr: usd-core, the extra "usd"; itk: itk-elastix, the extra "bench"
OPTIONAL = {"distributed", "dask", "fcntl", "pxr", "itk"}
MAX_FUNCTION_LINES = 80
#: Parameters a function may take (``self``/``cls`` not counted; ``*args`` and ``**kwargs`` count one each).
MAX_PARAMETERS = 8
#: Functions still over MAX_PARAMETERS, with their count today: a ratchet. None may grow, none may be
#: added, and one that drops to the limit must leave this list. Empty since issue 29: typer commands
#: take one options dataclass (cli/common.py ``takes``), numba kernels their inputs grouped in tuples.
WIDE_FUNCTIONS: dict[str, int] = {}


def _modules() -> dict[str, ast.Module]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = (path, ast.parse(path.read_text(encoding="utf-8")))
    return out


MODULES = _modules()


def _imported(name: str, path: Path, node) -> list[str]:
    """The lungdeform modules an import statement of module ``name`` names (relative ones resolved)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.split(".")[0] == "lungdeform"]
    base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    if node.level:
        base = base[: len(base) - node.level + 1]
        module = ".".join(base + ([node.module] if node.module else []))
    else:
        module = node.module or ""
    if module.split(".")[0] != "lungdeform":
        return []
    # `from package import submodule` names the submodule when it is one
    subs = [f"{module}.{a.name}" for a in node.names if f"{module}.{a.name}" in MODULES]
    return subs + [module]


def _graph() -> dict[str, set[str]]:
    graph = {}
    for name, (path, tree) in MODULES.items():
        deps = set()
        for node in ast.walk(tree):  # function-local and TYPE_CHECKING imports count too
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                deps.update(d for d in _imported(name, path, node) if d in MODULES and d != name)
        graph[name] = deps
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_between_modules():
    # a package __init__ importing its own submodules is not a cycle of concern; every other
    # strongly connected component is (truth: Tarjan's algorithm over every import statement)
    graph = {m: {d for d in deps if not m.startswith(d + ".") and not (d.startswith(m + ".") and
                                                                        MODULES[m][0].name == "__init__.py")}
             for m, deps in _graph().items()}
    assert _cycles(graph) == []


def test_cycle_detector_finds_a_cycle():
    # the detector itself: a → b → c → a is one component, d alone is none
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_layers_contract_passes_lint_imports():
    # import-linter checks the layers and independence contracts of pyproject.toml
    exe = Path(sys.executable).parent / "lint-imports"
    if not exe.exists():
        exe = shutil.which("lint-imports")
    if exe is None:
        pytest.skip("lint-imports is not installed (make test installs it into .venv)")
    res = subprocess.run([str(exe), "--config", str(REPO / "pyproject.toml")], cwd=REPO, capture_output=True,
                         encoding="utf-8", errors="replace", timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "BROKEN" not in res.stdout and "KEPT" in res.stdout


def test_package_root_holds_few_modules_and_the_subpackages_are_many():
    root = [p.stem for p in PACKAGE.glob("*.py") if p.stem not in ("__init__", "__main__")]
    subpackages = [p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()]
    assert len(root) <= 6, root
    assert len(subpackages) >= 8, subpackages


def test_every_subpackage_says_what_it_owns_and_may_import():
    for init in PACKAGE.glob("*/__init__.py"):
        doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))) or ""
        assert "May import" in doc or init.parent.name in ("cli", "data"), init


def test_functions_are_short():
    long = []
    for name, (_, tree) in MODULES.items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{name}:{node.name} ({n} lines)")
    assert long == []


def _parameters(node: ast.FunctionDef | ast.AsyncFunctionDef, method: bool) -> int:
    """How many parameters ``node`` takes: positional, keyword-only, ``*args`` and ``**kwargs``; a
    method's ``self``/``cls`` (its first parameter) not counted."""
    a = node.args
    names = [p.arg for p in a.posonlyargs + a.args]
    if method and names and names[0] in ("self", "cls"):
        names = names[1:]
    return len(names) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)


def _parameter_counts() -> dict[str, int]:
    """``module:qualname`` → parameters, for every function and method of the package."""
    counts = {}
    for name, (_, tree) in MODULES.items():
        def walk(body, prefix, in_class):
            for node in body:
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    counts[f"{name}:{prefix}{node.name}"] = _parameters(node, in_class)
                    walk(node.body, f"{prefix}{node.name}.", False)
                elif isinstance(node, ast.ClassDef):
                    walk(node.body, f"{prefix}{node.name}.", True)
        walk(tree.body, "", False)
    return counts


def test_parameter_counter_counts_every_kind_of_parameter():
    # the counter behind the limit, on a known signature: a, b, *c, d, **e = 5; a method's self is free
    tree = ast.parse("def f(a, b=1, *c, d, **e): pass\nclass K:\n    def m(self, x, /, y): pass\n")
    assert _parameters(tree.body[0], method=False) == 5
    assert _parameters(tree.body[1].body[0], method=True) == 2
    assert _parameters(tree.body[1].body[0], method=False) == 3


def test_functions_take_few_parameters():
    counts = _parameter_counts()
    wide = {k: n for k, n in counts.items() if n > MAX_PARAMETERS}
    new = {k: n for k, n in wide.items() if k not in WIDE_FUNCTIONS}
    assert new == {}, f"more than {MAX_PARAMETERS} parameters: group them in a config object"
    grown = {k: (WIDE_FUNCTIONS[k], n) for k, n in wide.items() if n > WIDE_FUNCTIONS.get(k, n)}
    assert grown == {}
    fixed = sorted(k for k in WIDE_FUNCTIONS if counts.get(k, 0) <= MAX_PARAMETERS)
    assert fixed == [], "now within the limit (or gone): remove from WIDE_FUNCTIONS"


def test_imports_inside_functions_only_for_optional_dependencies():
    local = []
    for name, (_, tree) in MODULES.items():
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for node in ast.walk(fn):
                    if isinstance(node, ast.Import):
                        mods = [a.name for a in node.names]
                    elif isinstance(node, ast.ImportFrom):
                        mods = ["lungdeform" if node.level else node.module or ""]
                    else:
                        continue
                    local += [f"{name}:{fn.name} imports {m}" for m in mods if m.split(".")[0] not in OPTIONAL]
    assert local == []


def test_matplotlib_backend_chosen_nowhere_and_plots_in_one_package():
    use, users = [], set()
    for name, (path, tree) in MODULES.items():
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "use"
                    and getattr(getattr(node.func, "value", None), "id", "") == "matplotlib"):
                use.append(name)
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                if any(m.split(".")[0] == "matplotlib" for m in mods):
                    users.add(name)
    assert use == []
    assert all(u.startswith("lungdeform.plot.") for u in users), sorted(users)


def test_no_references_to_documents_outside_the_repository():
    # "issue N" and the project's METHOD notes are not in the repository: cite the paper's
    # equations and docs/ instead
    bad = []
    for name, (path, _) in MODULES.items():
        text = path.read_text(encoding="utf-8")
        bad += [f"{name}: {m.group(0)}" for m in re.finditer(r"(?i:\bissue \d+)|\bMETHOD\b", text)]
    assert bad == []


#: Methods that change a list, dict or set in place.
MUTATORS = {"append", "extend", "insert", "remove", "pop", "popitem", "clear", "update", "setdefault", "add",
            "discard", "sort", "reverse", "__setitem__", "__delitem__"}


def _module_containers(tree: ast.Module) -> set[str]:
    """Names a module binds at its top level to a list, dict or set (a display, a comprehension or a call)."""
    names = set()
    for node in tree.body:
        targets, value = [], None
        if isinstance(node, ast.Assign):
            targets, value = node.targets, node.value
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            targets, value = [node.target], node.value
        mutable = isinstance(value, (ast.List, ast.Dict, ast.Set, ast.ListComp, ast.DictComp, ast.SetComp)) or (
            isinstance(value, ast.Call) and getattr(value.func, "id", "") in {"list", "dict", "set", "defaultdict"})
        if mutable:
            names.update(t.id for t in targets if isinstance(t, ast.Name))
    return names


def _local_names(fn) -> set[str]:
    """Names bound inside function ``fn`` (its parameters and assignments), which shadow the module's."""
    args = fn.args
    names = {a.arg for a in [*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg] if a}
    for node in ast.walk(fn):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
    return names


def module_state(tree: ast.Module) -> list[str]:
    """What in ``tree`` changes module state from a function: a ``global`` statement, or a module-level
    list, dict or set assigned into, deleted from or changed by a method in a function."""
    containers, found = _module_containers(tree), []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        if isinstance(fn, ast.Lambda):
            shared = containers
        else:
            shared = containers - _local_names(fn)
        for node in ast.walk(fn):
            if isinstance(node, ast.Global):
                found += [f"{getattr(fn, 'name', 'lambda')}: global {', '.join(node.names)}"]
            target = None
            if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign, ast.Delete)):
                for t in getattr(node, "targets", None) or [node.target]:
                    if isinstance(t, ast.Subscript) and isinstance(t.value, ast.Name):
                        target = t.value.id
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                  and node.func.attr in MUTATORS and isinstance(node.func.value, ast.Name)):
                target = node.func.value.id
            if target in shared:
                found.append(f"{getattr(fn, 'name', 'lambda')}: changes module-level {target}")
    return found


def test_module_state_detector_finds_what_it_should():
    # each pattern the rule forbids is found, and a local of the same name or a read is not
    bad = ast.parse("CACHE = {}\nSEEN = []\nON = None\n"
                    "def a():\n    global ON\n    ON = True\n"
                    "def b(k):\n    CACHE[k] = 1\n"
                    "def c(x):\n    SEEN.append(x)\n"
                    "def d():\n    del CACHE['k']\n")
    assert module_state(bad) == ["a: global ON", "b: changes module-level CACHE", "c: changes module-level SEEN",
                                 "d: changes module-level CACHE"]
    good = ast.parse("TABLE = {'a': 1}\n"
                     "def e(k):\n    return TABLE[k]\n"
                     "def f():\n    TABLE = {}\n    TABLE['x'] = 1\n    return TABLE\n"
                     "def g(TABLE):\n    TABLE.update(a=2)\n")
    assert module_state(good) == []


#: Module state kept on purpose, with the reason.
KEPT_STATE = {
    # every atomic write removes its target's stale temporaries; listing a folder once per process
    # (not once per write) keeps writing n files into one folder linear, and it caches the file
    # system, not a setting: no caller sees another's choices through it
    "lungdeform.atomic._hidden: changes module-level _HIDDEN",
}


def test_no_module_state():
    # library and CLI code pass state explicitly (a context object, a cache the caller owns): a
    # module-level value changed by a function is shared by every caller in the process
    found = []
    for name, (_, tree) in MODULES.items():
        found += [f"{name}.{f}" for f in module_state(tree)]
    assert sorted(set(found) - KEPT_STATE) == []
    assert KEPT_STATE <= set(found)  # a kept entry that is gone must leave this list too
