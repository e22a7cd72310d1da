"""Follow one parameter through the static call graph and count how often its trip climbs back up the layers.

Usage (from the repository root)::

    python scripts/param_trips.py lungdeform.evaluate.pipeline:run_fit config
    python scripts/param_trips.py lungdeform.cohort.job:fit_job options [--show]

How it counts (ast only; nothing is imported or run):

- **Layers** are those of the ``layers`` contract in pyproject.toml's ``[tool.importlinter]`` (top
  first); a module's layer is that of the longest listed package it lies in.
- **Carried**: in a function, the parameter followed and any name bound to it or to a value read
  from it (``x = config``, ``folds = config.folds``, ``c = options.config()``,
  ``c = replace(config, ...)``); a value *computed* from it (``len(config.x)``) is not followed. A
  call carries it when an argument is a carried name or a value read from one (``f(config)``,
  ``g(n=config.folds)``); in the callee the parameters those arguments bind (by position or
  keyword; ``*args`` binds the rest; a carried keyword that lands in ``**kwargs`` is followed by
  its key when ``**kwargs`` is passed on) are carried in turn.
- **Calls resolved**: a name defined in the module or imported from a lungdeform module
  (``from m import f``, ``from pkg import module as M; M.f``), ``self.method`` in a class, and a
  class called (its ``__init__`` and ``__post_init__``). Methods called on other objects, builtins
  and other packages are not followed.
- **Trip**: the depth-first sequence of *stays*, one per call that carries the parameter (the entry
  function first). Each function is walked once per set of carried parameters (later calls to it
  are stays, not walked again), so loops and recursion end.
- **Returns**: how often the trip goes back to a caller before its next stay.
- **Climb**: a stay in a higher layer than the stay before it. A call can never go up a layer
  (import-linter forbids the import), so a climb is always the trip coming back from a lower layer
  and going on in a higher one: down, and up again.
"""

from __future__ import annotations

import argparse
import ast
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "lungdeform"


def layer_order(pyproject: Path) -> list[list[str]]:
    """The layers contract's packages, top layer first (``a | b`` and ``a : b`` are one layer)."""
    data = tomllib.loads(pyproject.read_text(encoding="utf-8"))
    for contract in data["tool"]["importlinter"]["contracts"]:
        if contract.get("type") == "layers":
            return [[p.strip() for p in layer.replace(":", "|").split("|")] for layer in contract["layers"]]
    raise SystemExit(f"{pyproject}: no layers contract")


def layer_of(module: str, layers: list[list[str]]) -> int:
    """Index of ``module``'s layer (0 = top); modules outside every layer sort below them all."""
    best, depth = len(layers), -1
    for i, names in enumerate(layers):
        for name in names:
            if (module == name or module.startswith(name + ".")) and name.count(".") > depth:
                best, depth = i, name.count(".")
    return best


@dataclass
class Function:
    module: str
    qualname: str
    node: ast.FunctionDef
    cls: str | None = None

    @property
    def key(self) -> str:
        return f"{self.module}:{self.qualname}"

    def params(self) -> list[str]:
        a = self.node.args
        names = [p.arg for p in a.posonlyargs + a.args]
        return names[1:] if self.cls and names and names[0] in ("self", "cls") else names


@dataclass
class Module:
    name: str
    functions: dict[str, Function] = field(default_factory=dict)  # qualname -> function
    imports: dict[str, str] = field(default_factory=dict)  # local name -> "module" or "module:attr"


def load(src: Path) -> dict[str, Module]:
    mods = {}
    for path in sorted((src / PACKAGE).rglob("*.py")):
        parts = path.relative_to(src).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        tree = ast.parse(path.read_text(encoding="utf-8"))
        mod = Module(name)
        base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                origin = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else [])) \
                    if node.level else (node.module or "")
                for a in node.names:
                    mod.imports[a.asname or a.name] = f"{origin}:{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    mod.imports[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                mod.functions[node.name] = Function(name, node.name, node)
            elif isinstance(node, ast.ClassDef):
                for item in node.body:
                    if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
                        mod.functions[f"{node.name}.{item.name}"] = Function(name, f"{node.name}.{item.name}", item,
                                                                          node.name)
                mod.functions.setdefault(node.name, None)  # a class: its __init__/__post_init__ when called
        mods[name] = mod
    return mods


def _target(mods: dict[str, Module], module: str, name: str) -> list[Function]:
    """The functions a call of ``name`` in ``module`` runs (a class: its __init__ and __post_init__)."""
    mod = mods.get(module)
    if mod is None:
        return []
    if name in mod.functions:
        if mod.functions[name] is not None:
            return [mod.functions[name]]
        return [f for q in (f"{name}.__init__", f"{name}.__post_init__") if (f := mod.functions.get(q))]
    ref = mod.imports.get(name)
    if ref and ":" in ref:
        origin, attr = ref.split(":")
        if f"{origin}.{attr}" in mods:  # `from package import module`: not a call target
            return []
        return _target(mods, origin, attr) if origin in mods and origin != module else []
    return []


def resolve(mods: dict[str, Module], fn: Function, call: ast.Call) -> list[Function]:
    f = call.func
    if isinstance(f, ast.Name):
        return _target(mods, fn.module, f.id)
    if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name):
        head = f.value.id
        if head == "self" and fn.cls:
            m = mods[fn.module].functions.get(f"{fn.cls}.{f.attr}")
            return [m] if m else []
        ref = mods[fn.module].imports.get(head)
        if ref:
            module = ref.replace(":", ".")
            if module in mods:
                return _target(mods, module, f.attr)
    return []


def _root(node: ast.AST) -> ast.AST:
    """The name an expression reads from: ``config`` of ``config``, ``config.folds``,
    ``options.config()``, ``*config``; anything else is itself."""
    while True:
        if isinstance(node, ast.Starred):
            node = node.value
        elif isinstance(node, ast.Attribute):
            node = node.value
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            node = node.func.value
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "replace" and node.args:
            node = node.args[0]  # dataclasses.replace(config, ...): a changed copy
        else:
            return node


def _mentions(node: ast.AST, carried: set[str]) -> bool:
    """Whether ``node`` is a carried name or a value read from one (module docstring)."""
    root = _root(node)
    return isinstance(root, ast.Name) and root.id in carried


def carried_names(fn: Function, start: set[str]) -> set[str]:
    """``start`` and every local name bound (by assignment or a for loop) to a value mentioning them."""
    carried = set(start)
    changed = True
    while changed:
        changed = False
        for node in ast.walk(fn.node):
            pairs = []
            if isinstance(node, ast.Assign):
                pairs = [(t, node.value) for t in node.targets]
            elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and node.value is not None:
                pairs = [(node.target, node.value)]
            elif isinstance(node, ast.For):
                pairs = [(node.target, node.iter)]
            elif isinstance(node, ast.withitem) and node.optional_vars is not None:
                pairs = [(node.optional_vars, node.context_expr)]
            for target, value in pairs:
                if _mentions(value, carried):
                    names = [target] if isinstance(target, ast.Name) else \
                        list(target.elts) if isinstance(target, (ast.Tuple, ast.List)) else []
                    for n in names:  # `self.x = config` binds no local name
                        if isinstance(n, ast.Name) and n.id not in carried:
                            carried.add(n.id)
                            changed = True
    return carried


def bound(callee: Function, call: ast.Call, carried: set[str], method_call: bool) -> set[str]:
    """The callee's parameters that the call's carrying arguments bind."""
    a = callee.node.args
    positional = [p.arg for p in a.posonlyargs + a.args]
    if positional and positional[0] in ("self", "cls") and (callee.cls or method_call):
        positional = positional[1:]
    out = set()
    for i, arg in enumerate(call.args):
        if not _mentions(arg, carried):
            continue
        if isinstance(arg, ast.Starred) or i >= len(positional):
            if a.vararg:
                out.add(a.vararg.arg)
            if isinstance(arg, ast.Starred):
                out.update(positional[i:])
        else:
            out.add(positional[i])
    names = set(positional) | {p.arg for p in a.kwonlyargs}
    for kw in call.keywords:
        if kw.arg is None:  # `**kw` passed on: the keys of it that carry (``"kw:key"``)
            keys = [c.split(":", 1)[1] for c in carried
                    if isinstance(kw.value, ast.Name) and c.startswith(kw.value.id + ":")]
        elif _mentions(kw.value, carried):
            keys = [kw.arg]
        else:
            keys = []
        for key in keys:
            if key in names:
                out.add(key)
            elif a.kwarg:
                out.add(f"{a.kwarg.arg}:{key}")
    return out


def _calls_in_order(fn: Function):
    """The calls of a function body in source order (nested functions included)."""
    calls = [n for n in ast.walk(fn.node) if isinstance(n, ast.Call)]
    return sorted(calls, key=lambda c: (c.lineno, c.col_offset))


def trip(mods: dict[str, Module], entry: Function, param: str) -> list[tuple[int, Function]]:
    """The stays ``(depth, function)`` of ``param`` from ``entry``, depth first."""
    stays: list[tuple[int, Function]] = []
    walked: set[tuple[str, frozenset]] = set()

    def visit(fn: Function, params: set[str], depth: int) -> None:
        stays.append((depth, fn))
        key = (fn.key, frozenset(params))
        if key in walked:
            return
        walked.add(key)
        carried = carried_names(fn, params)
        for call in _calls_in_order(fn):
            spread = {c.split(":", 1)[0] for c in carried if ":" in c}
            if not (any(_mentions(a, carried) for a in [*call.args, *(k.value for k in call.keywords)])
                    or any(k.arg is None and isinstance(k.value, ast.Name) and k.value.id in spread
                           for k in call.keywords)):
                continue
            method = isinstance(call.func, ast.Attribute) and isinstance(call.func.value, ast.Name) \
                and call.func.value.id == "self"
            for callee in resolve(mods, fn, call):
                got = bound(callee, call, carried, method)
                if got:
                    visit(callee, got, depth + 1)

    visit(entry, {param}, 0)
    return stays


def summary(stays, layers) -> dict:
    climbs, returns, shown = 0, 0, []
    for i, (depth, fn) in enumerate(stays):
        here = layer_of(fn.module, layers)
        mark = ""
        if i:
            prev_depth, prev = stays[i - 1]
            returns += max(0, prev_depth + 1 - depth)
            if here < layer_of(prev.module, layers):
                climbs += 1
                mark = "  <- climb"
        shown.append(f"{'  ' * depth}{fn.key} [{'|'.join(layers[here]) if here < len(layers) else 'core'}]{mark}")
    return {"stays": len(stays), "rooms": len({fn.module for _, fn in stays}), "climbs": climbs,
            "returns": returns, "lines": shown}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("entry", help="module:function, e.g. lungdeform.evaluate.pipeline:run_fit")
    ap.add_argument("param", help="the parameter to follow, e.g. config")
    ap.add_argument("--root", type=Path, default=ROOT, help="repository root (src/ and pyproject.toml)")
    ap.add_argument("--show", action="store_true", help="print the trip")
    args = ap.parse_args(argv)
    mods = load(args.root / "src")
    module, name = args.entry.split(":")
    entry = mods[module].functions.get(name) if module in mods else None
    if entry is None:
        print(f"{args.entry}: no such function", file=sys.stderr)
        return 2
    s = summary(trip(mods, entry, args.param), layer_order(args.root / "pyproject.toml"))
    if args.show:
        print("\n".join(s["lines"]))
    print(f"{args.entry} {args.param}: {s['stays']} stays in {s['rooms']} modules, "
          f"{s['climbs']} climbs, {s['returns']} returns")
    return 0


if __name__ == "__main__":
    sys.exit(main())
