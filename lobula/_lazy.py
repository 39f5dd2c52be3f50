"""A package's public names loaded on first use (PEP 562), so that importing the package stays light."""
from __future__ import annotations

import importlib


def lazy_api(package: str, api: dict[str, str], names: list[str]):
    """``(__getattr__, __dir__)`` for ``package``'s ``__init__``.

    package: the package's ``__name__``; api: public name -> the submodule (relative to ``package``)
    that defines it, imported when the name is first asked for (with torch, SciPy or OpenCV behind it);
    names: what ``dir(package)`` lists (its ``__all__``).
    """

    def __getattr__(name: str):
        if name in api:
            return getattr(importlib.import_module(f".{api[name]}", package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return names

    return __getattr__, __dir__
