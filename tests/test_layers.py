"""Dependencies point one way (docs/design.md, "Data flow"): scene -> transport -> photonmap -> render ->
replay -> fit -> maps, with io and cli on top. A package imports only packages below it, at module
level or inside a function."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "tissuefit"
ORDER = ["scene", "transport", "photonmap", "render", "replay", "fit", "maps", "io", "cli"]


def _imported_packages(package: str) -> dict[str, set[str]]:
    """{tissuefit sub-package imported by `package`: the files that import it}."""
    found: dict[str, set[str]] = {}
    for path in (PACKAGE / package).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level >= 2 and node.module:
                found.setdefault(node.module.split(".")[0], set()).add(path.name)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("tissuefit."):
                found.setdefault(node.module.split(".")[1], set()).add(path.name)
    return found


@pytest.mark.parametrize("package", ORDER)
def test_a_package_imports_only_the_layers_below_it(package):
    above = set(ORDER[ORDER.index(package) + 1:])
    wrong = {dep: sorted(files) for dep, files in _imported_packages(package).items() if dep in above}
    assert not wrong, f"tissuefit.{package} imports packages above it: {wrong}"
