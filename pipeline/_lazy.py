"""Lazy public names of a package (PEP 562, as scipy does): ``__getattr__`` and
``__dir__`` that import a name's module on first use, so importing one core module does
not load every layer."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping


def lazy_names(package: str, public: Mapping[str, str]
               ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for `package` whose public names live in other modules.

    Parameters
    ----------
    package : str
        The package's dotted name (for the error message).
    public : mapping of str -> str
        Public name -> the module that defines it.
    """
    def __getattr__(name: str) -> object:
        if name in public:
            return getattr(importlib.import_module(public[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(public)

    return __getattr__, __dir__
