"""Names of a package that load their module on first use (PEP 562), so that importing the package
stays cheap: ``recon.lf`` and ``recon.entropy`` keep numpy, OpenCV and numba out of ``lfrig --help``."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_names(package: str, names: Mapping[str, str]) -> Callable[[str], Any]:
    """A module-level ``__getattr__`` for ``package``: ``names`` maps each name to the module that
    defines it, imported when the name is first looked up; the value is then kept in the package."""

    def __getattr__(name: str) -> Any:
        module = names.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
