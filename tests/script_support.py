"""Load a script of ``scripts/`` as a module, for the tests of that script."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def loaded_script(name: str):
    """Yield ``scripts/<name>.py`` as the module ``name`` (registered in ``sys.modules`` while it is used:
    dataclasses look their module up while the class is made), then unregister it; for a fixture."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(name, None)
