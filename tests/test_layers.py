"""The layers depend only downwards: schema <- model <- build <- studies, the service on
schema alone, and nothing inside the package on the public facade ``pipeline.api``."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAY_IMPORT = {
    "schema": {"schema"},
    "clutter": {"schema", "clutter"},
    "pipeline.model": {"schema", "pipeline.model"},
    "pipeline.build": {"schema", "pipeline.model", "pipeline.build"},
    "pipeline.heaps": {"schema", "clutter", "pipeline.model", "pipeline.build", "pipeline.heaps"},
    "service": {"schema", "clutter", "service"},
}
"""Of the project's own packages, what each layer may import; and every layer of ``pipeline`` may import
``pipeline.numerics``, which imports nothing (``import pipeline`` runs it before anything else)."""
OWN = ("schema", "clutter", "pipeline", "service")


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the project modules a source file imports (relative imports resolved)."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join([*base, node.module] if node.module else base)
            names.add(module)
            names |= {f"{module}.{alias.name}" for alias in node.names}
    return {n for n in names if n.split(".")[0] in OWN}


def layer_files(layer: str) -> list[Path]:
    return sorted((ROOT / layer.replace(".", "/")).rglob("*.py"))


@pytest.mark.parametrize("layer", sorted(MAY_IMPORT))
def test_each_layer_imports_only_what_is_below_it(layer):
    allowed = MAY_IMPORT[layer] | ({"pipeline.numerics"} if layer.startswith("pipeline") else set())
    wrong = {
        f"{path.relative_to(ROOT)}: {name}"
        for path in layer_files(layer)
        for name in imported_modules(path)
        if not any(name == a or name.startswith(a + ".") for a in allowed)
    }
    assert not wrong, sorted(wrong)


def test_nothing_inside_the_package_imports_the_public_facade():
    users = {
        str(path.relative_to(ROOT))
        for layer in ("pipeline", "service", "schema")
        for path in layer_files(layer)
        if path.name != "__init__.py" and any(n.startswith("pipeline.api") for n in imported_modules(path))
    }
    assert users == set(), sorted(users)
