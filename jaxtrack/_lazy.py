"""PEP 562 lazy attributes: host-side modules (OpenCV, trimesh, embree) load on first access."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_exports(package: str, namespace: dict, exports: dict) -> tuple[Callable, Callable]:
    """`__getattr__` and `__dir__` for `package` that import `exports[name]` (a relative module) on
    first access of `name` and cache it in the package's `namespace` (later look-ups skip them)."""

    def __getattr__(name: str):
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        target = importlib.import_module(f".{exports[name]}", package)
        value = target if exports[name] == name else getattr(target, name)
        namespace[name] = value
        return value

    def __dir__() -> list:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
