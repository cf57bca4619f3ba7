"""Lazy package attributes (PEP 562): names imported from their module on first use.

`tissuefit` and `tissuefit.io` both use it, so that `import tissuefit` (and the command's `--help`)
loads neither JAX nor the file readers until something needs them.
"""

from __future__ import annotations

import importlib


def lazy_exports(namespace: dict, exports: dict[str, str], subpackages: tuple[str, ...] = ()):
    """(`__getattr__`, `__dir__`, `__all__`) for the package whose globals are `namespace`.

    `exports` maps a public name to the module (relative to the package) that defines it;
    `subpackages` are loaded as modules. A name once loaded is stored in `namespace`, so later
    look-ups do not come back here."""
    package = namespace["__name__"]
    public = sorted({*exports, *subpackages})

    def __getattr__(name: str):
        if name in subpackages:
            return importlib.import_module(f".{name}", package)
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module, package), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(public))

    return __getattr__, __dir__, public
