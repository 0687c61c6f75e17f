"""The house: dependencies point one way, and no private name crosses a module.

commands -> application (lightflow.app) -> core (lightflow.app.core); the
drivers and the simulator depend on the core's small types only.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = {"app": "lightflow.app", "drivers": "lightflow.drivers",
            "calibration": "lightflow.calibration"}  # fmt: skip


def _modules():
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            yield ".".join([package, *parts]), path


def _imports(name: str, path: Path):
    """``(module, imported names)`` of every import in a file, relative ones resolved."""
    tree = ast.parse(path.read_text())
    is_package = path.name == "__init__.py"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, []
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            yield module, [alias.name for alias in node.names]


MODULES = list(_modules())


@pytest.mark.parametrize("name, path", MODULES, ids=[m for m, _ in MODULES])
def test_dependencies_point_one_way(name, path):
    if name.startswith("lightflow.app.core"):
        allowed = ("lightflow.app.core",)
    elif name.startswith("lightflow.drivers.sim"):
        allowed = ("lightflow.app.core", "lightflow.drivers.base", "lightflow.drivers.sim")
    elif name.startswith("lightflow.drivers"):
        allowed = ("lightflow.app.core", "lightflow.drivers")
    else:
        return  # the application, its commands and calibration may use everything below
    for module, _names in _imports(name, path):
        if module.startswith("lightflow"):
            assert module.startswith(allowed), f"{name} imports {module}"


@pytest.mark.parametrize("name, path", MODULES, ids=[m for m, _ in MODULES])
def test_no_private_name_crosses_a_module(name, path):
    for module, names in _imports(name, path):
        if module.startswith("lightflow") and module != name:
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            assert not private, f"{name} imports {private} from {module}"


@pytest.mark.parametrize("name, path", MODULES, ids=[m for m, _ in MODULES])
def test_commands_do_not_import_each_other(name, path):
    """Shared command-line helpers live in lightflow.app.options."""
    if not name.startswith("lightflow.app.commands."):
        return
    for module, _names in _imports(name, path):
        assert not module.startswith("lightflow.app.commands."), f"{name} imports {module}"
