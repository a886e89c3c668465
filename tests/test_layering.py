"""The package layering, checked on the source: the hardware drivers never depend on the
simulator (the simulator builds on them, and the daemon chooses between them in
`app.devices`), and perception and mapping depend on no device, simulator or server."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

APP = Path(__file__).resolve().parents[1] / "app"

UPPER_LAYERS = ("app.web", "app.runtime", "app.daemon", "app.devices", "app.cli")
"""What runs the daemon: nothing below it may import it."""

FORBIDDEN = {
    "hardware": ("app.sim", *UPPER_LAYERS),
    "perception": ("app.sim", "app.hardware", "app.mapping", *UPPER_LAYERS),
    "mapping": ("app.sim", "app.hardware", *UPPER_LAYERS),
}


def imported_modules(source: str, package: str) -> set[str]:
    """Every module ``source`` (a module of ``package``) imports anywhere, also inside
    functions and ``TYPE_CHECKING`` blocks, relative imports resolved; ``from a import
    b`` counts as both ``a`` and ``a.b``."""
    modules: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            modules.add(module)
            modules.update(f"{module}.{alias.name}" for alias in node.names)
    return modules


def package_of(path: Path) -> str:
    return ".".join(path.relative_to(APP.parent).with_suffix("").parts[:-1])


def is_within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_a_layer_imports_nothing_above_or_beside_it(layer: str) -> None:
    sources = sorted((APP / layer).rglob("*.py"))
    assert sources, f"no modules under app/{layer}"
    violations = [
        f"{path.relative_to(APP.parent)} imports {module}"
        for path in sources
        for module in sorted(imported_modules(path.read_text(encoding="utf-8"), package_of(path)))
        if any(is_within(module, banned) for banned in FORBIDDEN[layer])
    ]
    assert not violations, "\n".join(violations)


def test_the_check_sees_imports_inside_functions_and_relative_ones() -> None:
    source = "def f():\n    from app import sim\n    from ..sim.robot import SimRobot\n"
    modules = imported_modules(source, "app.hardware")
    assert {"app.sim", "app.sim.robot"} <= modules
