"""Dependencies point one way (docs/design.md, "Data flow"): scene -> transport -> photonmap -> render ->
replay -> fit -> maps, with io and cli on top. A package imports only packages below it, at module
level or inside a function, and only through their public `__init__` (no other package's `_module`)."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "tissuefit"
ORDER = ["scene", "transport", "photonmap", "render", "replay", "fit", "maps", "io", "cli"]
ROOT_PRIVATE = {p.stem for p in PACKAGE.glob("_*.py")}  # _checks, _setup, ...: shared by every layer


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


def _private_imports(package: str) -> list[str]:
    """Imports in `package` of another tissuefit sub-package's private module (`..transport._spectral`,
    `from ..fit import _names`), as "file:line: module"; the package root's own private modules
    (`.._checks`, `.._setup`, ...) are shared by every layer and allowed."""
    found = []
    for path in (PACKAGE / package).rglob("*.py"):
        here = path.relative_to(PACKAGE).parts[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level == 0:
                    if not (node.module or "").startswith("tissuefit."):
                        continue
                    parts = node.module.split(".")[1:]
                else:
                    parts = list(here[:len(here) - node.level + 1]) + (node.module.split(".") if node.module else [])
                modules = [parts + [alias.name] for alias in node.names]
            elif isinstance(node, ast.Import):
                modules = [a.name.split(".")[1:] for a in node.names if a.name.startswith("tissuefit.")]
            else:
                continue
            for module in modules:
                if module[0] not in (package, *ROOT_PRIVATE) and any(p.startswith("_") for p in module[1:]):
                    found.append(f"{path.name}:{node.lineno}: {'.'.join(module)}")
    return found


@pytest.mark.parametrize("package", ORDER)
def test_a_package_uses_only_the_public_names_of_another(package):
    wrong = _private_imports(package)
    assert not wrong, f"tissuefit.{package} imports private modules or names of other packages: {wrong}"
