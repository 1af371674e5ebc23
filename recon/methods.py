"""The reconstruction methods by name, with one calling convention for the CLI, benchmark and batch.

A runner takes the light field, an optional ``progress(fraction, message)`` callback
(:mod:`recon.progress`) and the method's keyword options, and returns a
:class:`MethodResult`: the disparity of the centre view and, where the method has them, the maps
that explain it, written next to ``disparity.pfm`` by :meth:`MethodResult.write_extras`. A runner
reads the views only as grey (:meth:`recon.lf.lightfield.LightField.gray`), so
:func:`recon.pipeline.reconstruct_to_folder` reads them as grey (``read_lightfield(grey=True)``).
"""

from __future__ import annotations

import dataclasses
import gc
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # annotations only: the method registry loads without numpy or OpenCV
    import numpy as np

    from recon.lf.lightfield import LightField


@dataclass
class MethodResult:
    """``disparity`` ``(H, W)`` float32 of the centre view, plus whatever the method explains itself with."""

    disparity: np.ndarray
    extras: Any = None
    options: dict[str, Any] = field(default_factory=dict)
    #: Writes the method's own maps into a result folder; returns the paths written.
    write_extras: Callable[[Path], list[Path]] | None = None


def _baseline(lf: LightField, progress: Any, **options: Any) -> MethodResult:
    from recon.baseline import estimate_baseline

    result = estimate_baseline(lf, progress=progress, **options)
    return MethodResult(disparity=result.disparity, extras=result, options=options)


def _entropy(lf: LightField, progress: Any, **options: Any) -> MethodResult:
    from recon.entropy import estimate_disparity, write_outputs

    result = estimate_disparity(lf, progress=progress, **options)
    used = dataclasses.asdict(result.options) if dataclasses.is_dataclass(getattr(result, "options", None)) else options
    used["disparity_range"] = [float(v) for v in result.disparity_range]  # the range searched, found or given
    return MethodResult(disparity=result.disparity, extras=result, options=used,
                        write_extras=lambda folder: write_outputs(result, folder))


def _warm_baseline() -> None:
    import numba.np.linalg

    from recon.baseline import load_kernels

    # numba's start-up asks whether BLAS is there by importing scipy.linalg (0.17 s of the 0.39 s
    # CPU of start-up and kernel; the baseline uses no scipy). scipy is a dependency, so the answer
    # is yes: the check is skipped during the start-up and kept for any later compilation.
    check = numba.np.linalg.ensure_blas
    numba.np.linalg.ensure_blas = lambda: None
    try:
        load_kernels()
    finally:
        numba.np.linalg.ensure_blas = check


def _warm_entropy() -> None:
    import recon.entropy.estimate  # noqa: F401  numba, scipy and the estimator's modules
    import recon.entropy.outputs  # noqa: F401
    from recon.costvolume import start_numba
    from recon.entropy.preload import load_kernels

    start_numba()
    load_kernels()  # each kernel the estimate calls, with its argument types


def _check_baseline(options: dict[str, Any]) -> None:
    from recon.baseline import check_options

    check_options(**options)


def _check_entropy(options: dict[str, Any]) -> None:
    from recon.entropy.options import make_options

    make_options(**options)  # every group checks its values


@dataclass(frozen=True)
class Method:
    """A reconstruction method: ``run(lf, progress, **options)``, ``check(options)`` (raises
    ``ValueError`` for an option value it cannot use, before any work), a one-line description and
    ``warm()``, which loads what the method's first call would load (imports, compiled kernels) and
    changes no result (:func:`warm_in_background`)."""

    run: Callable[..., MethodResult]
    check: Callable[[dict[str, Any]], None]
    description: str
    warm: Callable[[], None] | None = None


#: name -> :class:`Method`. The first is the default.
METHODS: dict[str, Method] = {
    "entropy": Method(_entropy, _check_entropy,
                      "matching entropy (Shi et al.): adaptive windows, visible views, TV in smooth regions",
                      _warm_entropy),
    "baseline": Method(_baseline, _check_baseline,
                       "fixed square window, SAD over all views, parabolic sub-pixel refinement",
                       _warm_baseline),
}
DEFAULT_METHOD = next(iter(METHODS))


def _method(name: str) -> Method:
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(sorted(METHODS))}") from None


def check_method_options(name: str, options: dict[str, Any]) -> None:
    """Raise ``ValueError`` naming the method or option value that cannot be used."""
    _method(name).check(dict(options))


_FROZE: list[str] = []  # the first warm-up of this process (it freezes: see below)


def warm_in_background(name: str) -> threading.Thread | None:
    """Start method ``name``'s ``warm()`` in a daemon thread and return it (``None`` for an unknown
    name or a method without one).

    numba's start-up (importing it, its first load of a cached kernel: ~0.5 s of Python that holds
    the interpreter lock) then overlaps work that releases the lock, such as decoding the views.
    The method's own first call waits for it where it must (the import lock, numba's compiler
    lock); join the thread before the work to keep the two apart. A failure here is dropped: the
    method's own call meets the same problem and reports it.

    The imports make some 10^5 objects that live as long as the process (numba's types and
    templates, scipy's functions): the garbage collector is off while the first warm-up of a
    process runs, and what is alive after it is frozen (``gc.freeze``), left out of later
    collections. Without that, a reconstruction's ~265 collections (two of them full) walked those
    objects again and again. Frozen objects are still freed when their last reference goes; only a
    reference cycle that is already garbage at that moment stays.
    """
    method = METHODS.get(name)
    if method is None or method.warm is None:
        return None

    first = not _FROZE
    if first:
        _FROZE.append(name)

    def warm() -> None:
        collecting = gc.isenabled()
        if first:
            gc.disable()
        try:
            method.warm()
        except Exception:  # noqa: BLE001  reported by the method's own call (see above)
            pass
        finally:
            if first:
                gc.freeze()
                if collecting:
                    gc.enable()

    thread = threading.Thread(target=warm, name=f"lfrig-warm-{name}", daemon=True)
    thread.start()
    return thread


def run_method(name: str, lf: LightField, *, progress: Any = None, **options: Any) -> MethodResult:
    """Run the method ``name`` on ``lf`` with keyword ``options`` (the method's own defaults otherwise)."""
    return _method(name).run(lf, progress, **options)
