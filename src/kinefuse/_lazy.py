"""Lazy re-exports for a package's ``__init__`` (PEP 562): a name is imported from its submodule
when first used, so importing the package (or a light submodule of it) stays cheap."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping

__all__ = ["lazy_exports"]


def lazy_exports(package: str, table: Mapping[str, str]) -> tuple[Callable, Callable]:
    """The module ``__getattr__`` and ``__dir__`` of ``package``, re-exporting lazily.

    Parameters
    ----------
    package : str
        The package's dotted name (its ``__name__``).
    table : mapping name -> submodule
        Where each re-exported name lives (``"write_report": "report"`` reads
        ``package.report.write_report``); a name is cached in the package once imported.

    Returns
    -------
    (__getattr__, __dir__)
        To assign at module level in the package's ``__init__``.
    """

    def __getattr__(name: str):
        mod = table.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{mod}"), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__():
        return sorted(set(vars(sys.modules[package])) | set(table))

    return __getattr__, __dir__
