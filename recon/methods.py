"""The reconstruction methods by name, with one calling convention for the CLI, benchmark and batch.

A runner takes the light field, an optional ``progress(fraction, message)`` callback
(:mod:`recon.progress`) and the method's keyword options, and returns a
:class:`MethodResult`: the disparity of the centre view and, where the method has them, the maps
that explain it, written next to ``disparity.pfm`` by :meth:`MethodResult.write_extras`. A runner
reads the views only as grey (:meth:`recon.lf.lightfield.LightField.gray`), so
:func:`recon.pipeline.reconstruct_to_folder` reads them as grey (``read_lightfield(grey=True)``).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import gc
import sys
import threading
from collections.abc import Callable, Iterator
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


@contextlib.contextmanager
def _blas_check_skipped() -> Iterator[None]:
    """numba's start-up asks whether BLAS is there by importing scipy.linalg (0.17 s of the 0.39 s
    CPU of the baseline's start-up and kernel, with scipy's array-API layer). scipy is a
    dependency, so the answer is yes: the check is skipped within and kept for any later compilation."""
    import numba.np.linalg

    check = numba.np.linalg.ensure_blas
    numba.np.linalg.ensure_blas = lambda: None
    try:
        yield
    finally:
        numba.np.linalg.ensure_blas = check


def _warm_baseline() -> None:
    from recon.baseline import load_kernels
    from recon.sweep import native_library

    if native_library() is not None:  # the C sweep: no numba in the process
        load_kernels(kernel="native")
        return
    with _blas_check_skipped():  # the baseline uses no scipy
        load_kernels(kernel="numba")


def _warm_entropy() -> None:
    import recon.entropy.estimate  # noqa: F401  the estimator's modules (numba and scipy load later)
    import recon.entropy.outputs  # noqa: F401
    from recon.entropy.preload import FIRST_PHASE_KERNELS, KERNELS, load_kernels, without_c_twins

    # the nine-view search's kernels that have no C twin here, with their argument types
    numba_kernels = without_c_twins(KERNELS[:FIRST_PHASE_KERNELS])
    if not numba_kernels:  # the first phase's C kernels: numba (if any kernel needs it) starts beside it
        return
    from recon.costvolume import start_numba

    with _blas_check_skipped():  # the first phase uses no scipy
        start_numba()
        load_kernels(numba_kernels, stop=_EXITING)


def _warm_entropy_later() -> None:
    # (with the first phase's C kernels, numba's start-up comes with the first numba kernel loaded here)
    from recon.entropy.laplace import solver_loads
    from recon.entropy.preload import FIRST_PHASE_KERNELS, KERNELS, load_kernels, without_c_twins
    from recon.native import library

    if not solver_loads():
        import scipy.sparse.linalg  # noqa: F401  the hole fill's solver, the first step after the first phase
    load_kernels(without_c_twins(KERNELS[FIRST_PHASE_KERNELS:]), stop=_EXITING)  # the later steps' kernels
    # scipy's filters, where their C twins (recon.entropy.filters) do not load: first used by the windows
    if library("filters") is None and not _EXITING.is_set():
        import scipy.ndimage  # noqa: F401


def _check_baseline(options: dict[str, Any]) -> None:
    from recon.baseline import check_options

    check_options(**options)


def _check_entropy(options: dict[str, Any]) -> None:
    from recon.entropy.options import make_options

    make_options(**options)  # every group checks its values


@dataclass(frozen=True)
class Method:
    """A reconstruction method: ``run(lf, progress, **options)``, ``check(options)`` (raises
    ``ValueError`` for an option value it cannot use, before any work), a one-line description,
    ``warm()``, which loads what the method's first call would load before its first step (imports,
    compiled kernels), and ``warm_later()``, which loads what only its later steps use while the
    first ones run; neither changes any result (:func:`warm_in_background`)."""

    run: Callable[..., MethodResult]
    check: Callable[[dict[str, Any]], None]
    description: str
    warm: Callable[[], None] | None = None
    warm_later: Callable[[], None] | None = None


#: name -> :class:`Method`. The first is the default.
METHODS: dict[str, Method] = {
    "entropy": Method(_entropy, _check_entropy,
                      "matching entropy (Shi et al.): adaptive windows, visible views, TV in smooth regions",
                      _warm_entropy, _warm_entropy_later),
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
#: Set when the process exits: a warm-up loads no further kernel (:func:`_finish_warm_ups`).
_EXITING = threading.Event()
_WARM_UPS: list[threading.Thread] = []
#: The warm-ups' gates of ``warm_later()`` (:attr:`Warming.later`): the exit opens them, so that a
#: warm-up still waiting ends.
_LATER: list[threading.Event] = []


def _finish_warm_ups() -> None:
    """At the process's exit (``atexit``): let each running warm-up finish the kernel it is loading,
    start no other, and end. A kernel that numba compiles (the cache has none for it: a new
    machine, an edited module) spends seconds in LLVM without the interpreter lock; a process that
    exited meanwhile would tear LLVM down under it and end in a segmentation fault or one of LLVM's
    assertions instead of its own exit status, whatever the command had done. Exit then waits for
    at most that one kernel, which its next run then loads from the cache."""
    _EXITING.set()
    for later in _LATER:
        later.set()
    for thread in _WARM_UPS:
        thread.join(1.0)
        if thread.is_alive():  # a compile: say why the exit waits
            with contextlib.suppress(Exception):
                print("lfrig: waiting for numba to finish compiling a kernel into its cache before exiting "
                      "(seconds; once)", file=sys.stderr, flush=True)
            thread.join()


#: What a wait for the warm-up longer than :data:`SLOW_WARM_UP_S` says (:meth:`Warming.wait`): where
#: numba's cache lacks the entropy method's kernels (``./setup.sh`` fills it; a module edited since,
#: a cache that could not be written) a run compiles them (~15 s before its first step, ~70 s for
#: backgammon in all on 2 cores), and until then its bar would stand at 0 %.
SLOW_WARM_UP = "compiling the estimator's kernels into numba's cache (a minute or two, once)"
SLOW_WARM_UP_S = 3.0


@dataclass(frozen=True)
class Warming:
    """A method's warm-up running in a thread (:func:`warm_in_background`)."""

    thread: threading.Thread
    #: Set when ``warm()`` has ended (or failed): the method's call may start.
    ready: threading.Event
    #: Set when ``warm_later()`` may begin (:meth:`begin_later`; :meth:`wait` and :meth:`join` set it too).
    later: threading.Event = field(default_factory=threading.Event)

    def begin_later(self) -> None:
        """Let ``warm_later()`` begin once ``warm()`` has ended: the caller's own work that needs
        the interpreter lock is done (the views are read). scipy's import (~0.2 s of Python) took
        the lock from the decoding threads between their images, which slowed the reading by
        half again as much as the import itself (backgammon: views read 0.29 -> 0.50 s); beside
        the first phase, whose C kernels run without the lock, it costs less than that."""
        self.later.set()

    def wait(self, progress: Any = None, *, note_after_s: float = SLOW_WARM_UP_S) -> None:
        """Block until the method's call may start (and let ``warm_later()`` begin; it may still
        run). With a ``progress(fraction, message)`` callback, a wait longer than ``note_after_s``
        (default :data:`SLOW_WARM_UP_S`) says what it waits for (:data:`SLOW_WARM_UP`): on a warm
        cache the warm-up is ready within a second of the views being read; past that it is most
        likely compiling."""
        self.later.set()
        if progress is not None and not self.ready.wait(note_after_s):
            progress(0.0, SLOW_WARM_UP)
        self.ready.wait()

    def join(self) -> None:
        """Block until the whole warm-up has ended (``warm_later()`` too)."""
        self.later.set()
        self.thread.join()


def warm_in_background(name: str) -> Warming | None:
    """Start method ``name``'s ``warm()`` in a daemon thread, and its ``warm_later()`` after it once
    the caller lets it begin (:meth:`Warming.begin_later`, :meth:`Warming.wait`); ``None`` for an
    unknown name or a method without a warm-up.

    numba's start-up (importing it, its first load of a cached kernel: ~0.5 s of Python that holds
    the interpreter lock) then overlaps work that releases the lock, such as decoding the views.
    Wait for it (:meth:`Warming.wait`) before the method's call, which then starts with what its first
    steps need loaded; ``warm_later()`` (scipy for the entropy method, ~0.3 s of CPU) runs beside
    those steps, whose compiled kernels release the lock. A later step that needs what is still
    loading waits for it where it must (the import lock, numba's compiler lock). A failure here is
    dropped: the method's own call meets the same problem and reports it.

    The imports make some 10^5 objects that live as long as the process (numba's types and
    templates): the garbage collector is off while the first ``warm()`` of a process runs, and what
    is alive after it is frozen (``gc.freeze``), left out of later collections. Without that, a
    reconstruction's ~265 collections (two of them full) walked those objects again and again.
    Frozen objects are still freed when their last reference goes; only a reference cycle that is
    already garbage at that moment stays. ``warm_later()`` runs with the collector as it was (the
    method's call runs meanwhile), so scipy's ~3x10^4 objects are not frozen.

    The process's exit waits for a running warm-up to finish the kernel it is loading; it loads no
    other (:func:`_finish_warm_ups`).
    """
    method = METHODS.get(name)
    if method is None or method.warm is None:
        return None

    first = not _FROZE
    if first:
        _FROZE.append(name)
        atexit.register(_finish_warm_ups)
    ready, later = threading.Event(), threading.Event()
    _LATER[:] = [*(gate for gate in _LATER if not gate.is_set()), later]

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
            ready.set()
        later.wait()  # set by the caller, or at the exit (_finish_warm_ups)
        if method.warm_later is not None and not _EXITING.is_set():
            with contextlib.suppress(Exception):  # as above
                method.warm_later()

    thread = threading.Thread(target=warm, name=f"lfrig-warm-{name}", daemon=True)
    _WARM_UPS[:] = [*(t for t in _WARM_UPS if t.is_alive()), thread]
    thread.start()
    return Warming(thread, ready, later)


def warm_every_method() -> None:
    """Every method's ``warm()`` and ``warm_later()`` in this thread, one after the other, and the
    numba twins of the C kernels (the baseline's sweep, the entropy method's kernels), which the
    warm-ups skip where the C ones load: numba's cache then holds every kernel they load
    (``./setup.sh`` runs it, so that no reconstruction compiles them, with ``LFRIG_NATIVE=0``
    neither; with the cache current it takes ~1.4 s)."""
    for method in METHODS.values():
        for warm in (method.warm, method.warm_later):
            if warm is not None:
                warm()
    from recon.baseline import load_kernels
    from recon.entropy.preload import load_kernels as load_entropy_kernels

    load_kernels(kernel="numba")
    load_entropy_kernels()


def run_method(name: str, lf: LightField, *, progress: Any = None, **options: Any) -> MethodResult:
    """Run the method ``name`` on ``lf`` with keyword ``options`` (the method's own defaults otherwise)."""
    return _method(name).run(lf, progress, **options)
