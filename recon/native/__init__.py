"""Kernels compiled ahead of time with the system's C compiler, loaded without numba.

A process that loads a numba kernel pays numba's start first: its import and its typing and target
registries, 0.7-0.8 s of one core, held under the interpreter lock, on the 2-core machines lfrig is
measured on (``docs/entropy-results.md``, "Speed and memory"). A kernel here is C source beside this
file, built once into a shared library and called through :mod:`ctypes`: loading it takes
milliseconds. Each one mirrors a numba kernel operation for operation, on the same types in the same
order (no fused multiply-add, no fast math), so it gives the same bits; the numba kernel stays as
its fallback and its twin in the tests.

:func:`library` builds a library the first time it is asked for (``./setup.sh`` asks, through the
methods' warm-ups) into ``build/`` beside the sources, named by a digest of its source, the
compiler flags and this CPU's model and features (it is built for this CPU: ``-march=native``), and
loads it. Where no compiler is found, or the build fails, it returns ``None`` and says why once
(:func:`unavailable`); callers then use the numba kernel, which gives the same result. A build
writes the library to a temporary name and renames it, so that two processes building at once leave
one whole file, and removes the library of an earlier source. A kernel starts its threads and joins
them within each call (pthreads, no pool): a process may fork after it, as the fault tests' runner
does. ``LFRIG_NATIVE=0`` turns the compiled kernels off (the numba ones run instead).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: Where the built libraries go (ignored by git; one file per source digest).
BUILD = HERE / "build"
#: The compiler's flags. ``-ffp-contract=off``: C allows ``a * b + c`` to become one fused
#: multiply-add, rounded once; numba's kernels round twice, and so must these.
#: ``-fno-trapping-math``: no value changes, but loops with a floating-point test vectorise, as
#: LLVM (numba) assumes by default (the nine-view search's kernel 0.47 -> 0.43 s on one thread).
CFLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-fno-trapping-math", "-fno-math-errno", "-pthread",
          "-fPIC", "-shared", "-std=c11", "-Wall", "-Werror")

#: Each library's functions and their C argument types (``p``: a pointer, an array's data; ``i``:
#: int64; ``d``: double; ``f``: float), as :func:`library` declares them to :mod:`ctypes`. Every
#: function returns an int status: 0, -1 out of memory, -2 a thread could not be started.
SIGNATURES: dict[str, dict[str, str]] = {
    "sweep": {"lfrig_sweep": "p i i i i p p i p p p p i i i p i i p p p p p"},
    "initial": {
        "lfrig_min_window_costs": "p i i i i p p p p p i p i p p p i p p i p p i i i i p",
        "lfrig_subpixel_argmin": "p i i i p d p p i",
        "lfrig_cost_ambiguity": "p i i i f p i",
        "lfrig_downsample": "p i i i i i p i i i",
    },
    "joint": {
        "lfrig_joint_group": "p i i i i p p p p p i p i p p p i p p p i p p p p d i p p p i",
        "lfrig_offer_counts": "p i i i p p i p i",
        "lfrig_offer_runs": "p i i i p p i p p i",
    },
    "refine": {
        "lfrig_centroid": "p i i p d d p i",
        "lfrig_tv_wavefront": "p p p i i d i p p p p i i i p p p",
        "lfrig_tv_blocks": "p p p i i d i p p p p p i i p p p i",
    },
    "select": {"lfrig_select": "p i p i i p i i p d d d i i p i p p d p p i i p i p p p p p p i p i p p i"},
    "volume": {"lfrig_take": "p i p p p i i i f p i", "lfrig_window_major": "p i p p i i i i f p i"},
    "median": {"lfrig_median": "p i i i p p i p i i p i"},
    "views": {"lfrig_warp_mask": "p p p i p p i i i i i i p i", "lfrig_blend": "p p p i p"},
    "regions": {
        "lfrig_occlusion": "p i i p i f p i p p p p i",
        "lfrig_snap": "p i i i i p p p i p p p i p i d i d p p p p p i",
    },
    "filters": {"lfrig_uniform": "p p i i i i i i"},
    "confidence": {"lfrig_jump_distance": "p i i d i i i p", "lfrig_neighbours": "p i i i i d p p p"},
}
_CTYPES = {"p": ctypes.c_void_p, "i": ctypes.c_int64, "d": ctypes.c_double, "f": ctypes.c_float}

_lock = threading.Lock()
_loaded: dict[str, ctypes.CDLL | None] = {}
_why: dict[str, str] = {}


@functools.cache
def _cpu() -> str:
    """This CPU's model and instruction-set features (the library is built for them)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            lines = [line for line in info if line.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor() or platform.machine()


def compiler() -> str | None:
    """The C compiler to build with: ``$CC``, else ``cc`` or ``gcc`` on the PATH (``None``: none)."""
    named = os.environ.get("CC")
    if named:
        return shutil.which(named)
    return shutil.which("cc") or shutil.which("gcc")


def library_path(name: str, cc: str) -> Path:
    """Where the library of ``name.c`` (with the headers beside it) built by ``cc`` for this CPU goes."""
    source = b"".join([(HERE / f"{name}.c").read_bytes(), *(h.read_bytes() for h in sorted(HERE.glob("*.h")))])
    digest = hashlib.sha256(b"\0".join([source, " ".join(CFLAGS).encode(), cc.encode(), _cpu().encode(),
                                        platform.machine().encode()])).hexdigest()[:16]
    return BUILD / f"{name}-{digest}.so"


def _build(name: str, cc: str, target: Path) -> None:
    if BUILD.is_symlink():  # lfrig makes a folder here, never a link: build nowhere else
        raise RuntimeError(f"{BUILD} is a symbolic link, not the folder lfrig builds into; remove it")
    BUILD.mkdir(exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=BUILD, prefix=f".{name}-", suffix=".so")
    os.close(fd)
    try:
        run = subprocess.run([cc, *CFLAGS, "-o", tmp, str(HERE / f"{name}.c")], capture_output=True, text=True,
                             timeout=120)
        if run.returncode != 0:
            raise RuntimeError(f"{cc} failed: {(run.stderr or run.stdout).strip()[:400]}")
        os.replace(tmp, target)
        for old in BUILD.glob(f"{name}-*.so"):  # earlier builds of the same kernels (another source)
            if old.name != target.name:
                old.unlink(missing_ok=True)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def library(name: str) -> ctypes.CDLL | None:
    """The loaded library of ``name.c`` (built first if needed), or ``None`` where it cannot be had:
    ``LFRIG_NATIVE=0``, no compiler, a failed build or load (:func:`unavailable` says which)."""
    with _lock:
        if name in _loaded:
            return _loaded[name]
        lib = None
        if os.environ.get("LFRIG_NATIVE", "1") == "0":
            _why[name] = "LFRIG_NATIVE=0"
        else:
            cc = compiler()
            if cc is None:
                _why[name] = (f"no C compiler: CC={os.environ['CC']} is not on the PATH" if os.environ.get("CC")
                              else "no C compiler (cc or gcc) on the PATH")
            else:
                try:
                    path = library_path(name, cc)
                    if not path.exists():
                        _build(name, cc, path)
                    lib = ctypes.CDLL(str(path))
                    for function, types in SIGNATURES.get(name, {}).items():
                        getattr(lib, function).argtypes = [_CTYPES[t] for t in types.split()]
                        getattr(lib, function).restype = ctypes.c_int
                except (OSError, RuntimeError, subprocess.SubprocessError) as error:
                    _why[name] = f"{name}.c could not be built or loaded: {error}"
        _loaded[name] = lib
        return lib


def chosen(name: str, kernel: str = "auto") -> bool:
    """Whether to run the C kernels of ``name.c`` (``True``) or their numba twins: ``kernel``
    ``"numba"`` the twins, ``"native"`` the C ones (``RuntimeError`` saying why where they cannot be
    had), ``"auto"`` the C ones where they load."""
    if kernel not in ("auto", "native", "numba"):
        raise ValueError(f"kernel must be 'auto', 'native' or 'numba'; got {kernel!r}")
    if kernel == "auto" and _preferred:
        kernel = _preferred[-1]
    if kernel == "numba":
        return False
    if library(name) is not None:
        return True
    if kernel == "native":
        raise RuntimeError(f"the C kernels of {name}.c are not available: {unavailable(name)}")
    return False


_preferred: list[str] = []


@contextlib.contextmanager
def preferring(kernel: str) -> Iterator[None]:
    """Within, every :func:`chosen` asked with ``kernel="auto"`` answers as if asked with ``kernel``
    (``"native"`` or ``"numba"``): a whole estimate runs with all its C kernels or all their numba
    twins, for tests and benchmarks that compare the two (``bench/native_kernels.py``). It holds for
    the whole process, every thread, while the block runs."""
    if kernel not in ("native", "numba"):
        raise ValueError(f"kernel must be 'native' or 'numba'; got {kernel!r}")
    _preferred.append(kernel)
    try:
        yield
    finally:
        _preferred.pop()


def call(name: str, function: str, *args) -> None:
    """Call ``function`` of the loaded library ``name`` (:func:`library` must have given it) with
    ``args``: numpy arrays, passed as their data (each must be C-contiguous, the kernel's dtype, and
    alive for the call), and numbers. Raises ``MemoryError`` or ``RuntimeError`` for a status
    other than 0. The call releases the interpreter's lock (:mod:`ctypes`)."""
    lib = _loaded.get(name)
    if lib is None:
        raise RuntimeError(f"the C kernels of {name}.c are not loaded: {unavailable(name)}")
    values = []
    for arg in args:
        if hasattr(arg, "ctypes"):
            if not arg.flags.c_contiguous:
                raise ValueError(f"{function}: an array argument is not C-contiguous")
            values.append(arg.ctypes.data)
        else:
            values.append(arg)
    status = getattr(lib, function)(*values)
    if status == -1:
        raise MemoryError(f"{function} could not allocate its scratch memory")
    if status != 0:
        raise RuntimeError(f"{function} could not start its threads")


def thread_count() -> int:
    """The threads a kernel runs on: numba's setting where numba is loaded, else what numba would
    take (``NUMBA_NUM_THREADS``, else the CPUs this process may run on)."""
    numba_threads = getattr(sys.modules.get("numba"), "get_num_threads", None)  # None: numba not (yet) loaded
    if numba_threads is not None:
        return int(numba_threads())
    named = os.environ.get("NUMBA_NUM_THREADS", "").strip()
    if named.isdigit() and int(named) > 0:
        return int(named)
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def status() -> dict[str, str]:
    """How each C kernel asked for in this process runs: ``"C"`` (its library loaded), else
    ``"numba: WHY"`` (its numba twin, and why, :func:`unavailable`). Results record it
    (:func:`recon.provenance.machine`)."""
    with _lock:
        return {name: "C" if lib is not None else f"numba: {_why.get(name, 'not loaded')}"
                for name, lib in sorted(_loaded.items())}


def unavailable(name: str) -> str | None:
    """Why :func:`library` gave ``None`` for ``name`` (``None``: it was not asked, or it loaded)."""
    return _why.get(name)
