"""Names a package exports without importing their modules until first use."""

from __future__ import annotations

import importlib


def lazy_exports(package: str, exports: dict, namespace: dict):
    """The module-level ``__getattr__`` and ``__dir__`` of ``package``: ``name``
    is imported from the submodule ``exports[name]`` on first access and kept in
    the package's ``namespace`` (its ``globals()``)."""

    def __getattr__(name):
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{module}", package), name)
        namespace[name] = value
        return value

    def __dir__():
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
