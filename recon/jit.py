"""numba for modules whose kernels may never run: ``from recon.jit import numba`` stands for
``import numba``, but numba itself is imported only when one of the module's kernels is first used.

Where the C kernels of :mod:`recon.native` load, a reconstruction calls none of the numba kernels
they mirror, and a process that imports numba pays for it all the same: its import and its typing
and target registries, ~1 s of one core's time under the interpreter's lock (``docs/entropy-
results.md``, "Speed and memory"). So the estimator's modules and :mod:`recon.costvolume` define
their kernels through :data:`numba` here: ``@numba.njit(...)`` keeps the function and its options
(:class:`Kernel`) and compiles nothing. At the kernel's first call or public attribute lookup (its
``overloads``, ``compile``: :func:`recon.entropy.preload.load_kernels` asks for them) numba is
imported and the dispatcher made, with the same options, from the same function (so numba's cache
finds the same entries); the names of the function's module that stand for kernels, and ``numba``
itself, are then bound to the real ones, for the compiler reads a kernel's callees and
``numba.prange`` from its module's globals. ``py_func`` is the Python function, as numba's, and
imports nothing; any other attribute (``numba.get_num_threads``) imports numba and is numba's. It
changes no result: the kernels are numba's, compiled and cached as before.
"""

from __future__ import annotations

import importlib
import sys
import threading
from collections.abc import Callable
from typing import Any

_lock = threading.RLock()


class Kernel:
    """A function decorated with ``numba.njit(**options)``, made a numba dispatcher at its first
    use (:meth:`dispatcher`); calling it or reading an attribute uses the dispatcher."""

    def __init__(self, function: Callable, options: dict[str, Any]):
        self.function = function
        self.options = options
        self._dispatcher = None
        self.__name__ = function.__name__
        self.__qualname__ = function.__qualname__
        self.__module__ = function.__module__
        self.__doc__ = function.__doc__
        self.__wrapped__ = function
        self.py_func = function  # numba's name for it: the Python function, run without numba

    def dispatcher(self):
        """numba's dispatcher of the function (importing numba the first time)."""
        if self._dispatcher is None:
            with _lock:
                if self._dispatcher is None:
                    real = importlib.import_module("numba")
                    self._dispatcher = real.njit(**self.options)(self.function)
                    _bind(self.function.__globals__, real)
        return self._dispatcher

    def __call__(self, *args, **kwargs):
        return self.dispatcher()(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):  # tools that probe objects (pytest, inspect, pickle) make no dispatcher
            raise AttributeError(name)
        return getattr(self.dispatcher(), name)

    def __repr__(self) -> str:
        state = "compiled on first use" if self._dispatcher is None else "numba's dispatcher made"
        return f"<kernel {self.__module__}.{self.__qualname__} ({state})>"


def _bind(names: dict[str, Any], real) -> None:
    # The module's names for kernels (its own, and those it imported from other modules) and for
    # numba become the real ones. A kernel's dispatcher is set before its module is bound, so the
    # kernels that refer to each other end the recursion.
    with _lock:
        for name, value in list(names.items()):
            if isinstance(value, Kernel):
                names[name] = value.dispatcher()
            elif value is numba:
                names[name] = real


class _Numba:
    """Stands for the ``numba`` module: :meth:`njit` defers, everything else is numba's own."""

    def njit(self, *args, **options):
        if args and callable(args[0]) and len(args) == 1 and not options:  # bare @numba.njit
            return Kernel(args[0], {})
        if args:
            raise TypeError("recon.jit.numba.njit takes keyword options only (as @numba.njit(cache=True))")
        return lambda function: Kernel(function, options)

    def __getattr__(self, name: str) -> Any:
        return getattr(importlib.import_module("numba"), name)

    @staticmethod
    def loaded() -> bool:
        """Whether numba has been imported in this process (by a kernel's first use or otherwise)."""
        return "numba" in sys.modules


#: ``from recon.jit import numba`` in place of ``import numba``.
numba = _Numba()
