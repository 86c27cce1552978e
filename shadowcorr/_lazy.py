"""Lazy package exports (PEP 562): ``from package import Name`` imports only the module that defines it.

Used by the package ``__init__`` files whose submodules pull in heavy dependencies
(torch, MuJoCo, PIL), so that a command line can register its subcommands and answer
``--help`` / ``--version`` without importing them.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, exports: Mapping[str, str], namespace: dict[str, Any]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package`` whose public ``exports`` map name -> submodule.

    A resolved name is cached in the package ``namespace`` (its ``globals()``), so the
    lookup runs once per name.
    """

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{module}", package), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
