"""Lazy subpackage exports (PEP 562): ``from metadesign.sensing import AsFabricated`` imports
``metadesign.sensing.model`` on first use, so ``metadesign --help`` and the stage-1 commands import only
what they run (no torch, no scipy.optimize, no zarr)."""

from __future__ import annotations

import importlib

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: dict[str, str]):
    """``(__getattr__, __dir__)`` for a package whose names ``exports`` maps to the submodule defining them."""

    def __getattr__(name: str):
        mod = exports.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{mod}"), name)
        return value

    def __dir__():
        return sorted(exports)

    return __getattr__, __dir__
