"""The compiled kernels an estimate calls, each with the argument types it is called with, so that a
caller can load them from numba's cache before the estimate needs them.

In a fresh process numba loads a cached kernel at its first call: the index lookup, unpickling and
LLVM's materialising of the object code, 5-50 ms of CPU per kernel and signature (the first one of
a process also sets up numba's typing and target registries, ~0.35 s: :func:`recon.costvolume.start_numba`).
:func:`load_kernels` does that for every kernel of a default estimate, in the order the estimate
first calls them; ``lfrig reconstruct`` runs it in a thread (:func:`recon.methods.warm_in_background`):
the first phase's kernels (:data:`FIRST_PHASE_KERNELS`) while the views are decoded, the others
while that phase runs, each only where its C twin (``recon/native``, :data:`C_TWINS`) does not load
(:func:`without_c_twins`): the estimate then calls the C kernel, and where every kernel has its
C twin, the process never imports numba (:mod:`recon.jit`). ``./setup.sh`` loads them all once,
to fill the cache (:func:`recon.methods.warm_every_method`). It computes nothing and changes no result.

A signature is written as one token per argument: a scalar type by its numba name (``int64``,
``float32``, ``bool``) and a C-contiguous array as ``dtype:ndim``, with ``:ro`` for a read-only
one. A kernel called with other types than listed is still correct: numba then loads (or compiles)
that signature at its call, as without this module. ``tests/test_entropy_preload.py`` runs an
estimate in a fresh process after :func:`load_kernels` and checks that it adds no signature.
"""

from __future__ import annotations

import importlib
import threading

#: (module, kernel, argument types), in the order of the estimate's first calls.
KERNELS: tuple[tuple[str, str, str], ...] = (
    # the coarse search for a range nobody gave (a lab capture's) downsamples the views first
    ("recon.entropy.initial", "_downsample_kernel", "float32:4 int64 float32:4"),
    ("recon.entropy.cost", "_min_window_costs_kernel",
     "float32:4 int64:1 int64:1 float32:1 float32:1 int64:1 float32:1 int64:2 int64:1 int64:1 int64:1 int64:2 "
     "float64:1 bool:3 int64 float32:3"),
    ("recon.entropy.matching", "_subpixel_argmin_kernel", "float32:3 float64:1 float64 float32:2 float32:2"),
    ("recon.entropy.cost", "_cost_ambiguity_kernel", "float32:3 float32 int32:2"),
    # the first phase (the nine-view search) calls the kernels above, the later phases those below
    ("recon.entropy.median", "_median_kernel", "float32:2 int64:1 int64:1 int64:2 int64 float32:2"),
    ("recon.entropy.regions", "_occlusion_kernel",
     "float32:2 float64:2 float32 int64:2 int64 int64:1 int64:2 float32:2 float32:2"),
    ("recon.entropy.entropy", "_select_kernel",
     "uint16:1 uint8:2 int64:3 int64:1 float64 float64 float64 int64 int64 float64:1 int64:2:ro float32:2 "
     "float64 int64:2:ro int64:1 int64 uint64:2 int64:2 bool:1 int64:2 int64:2 float32:2 float32:3 bool float32:1 int64 "
     "int64:1 uint8:3"),
    ("recon.entropy.volume", "_window_major_kernel", "uint8:3 int64:1 float32:1 int64 int64 float32 float32:3"),
    ("recon.entropy.layout", "_offer_runs_kernel", "float32:3 bool:2 int64:1"),
    ("recon.entropy.matching", "_joint_group_kernel",
     "float32:4 int64:1 int64:1 float32:1 float32:1 int64:1 float32:1 int64:2 int64:1 int64:1 bool:2 int64:2 int64:1 "
     "float64:1 float32:3 int64:1 int32:2 float64 int64 float32:3 float32:2 int64:2"),
    ("recon.entropy.volume", "_take_kernel", "uint8:3 int64:1 float32:1 int64:2 int64 float32 float32:2"),
    ("recon.entropy.refine", "_centroid_kernel", "float64:2 int64:3 float64 float64 float64:2"),
    ("recon.entropy.boundary", "_snap_kernel",
     "float32:4 float32:2 float32:2 float32:2 int64 int64:1 int64:1 float64:1 float64:1 float64 int64 float64 "
     "float64:1 float64:1 int64:1 float64:1 float64:1"),
    ("recon.entropy.refine", "_tv_wavefront",
     "float64:2 bool:2 float64:2 float64 int64 float64:2 float64:2 float64:2 float64:2 int64 int64 int64 int64:1 "
     "uint64:1 uint64:1"),
    ("recon.entropy.refine", "_tv_blocks",
     "float64:2 bool:2 float64:2 float64 int64 float64:2 float64:2 float64:2 float64:2 int64:1 int64 int64:1 "
     "uint64:1 uint64:1"),
)
#: How many of :data:`KERNELS` the estimate's first phase calls (the first ones).
FIRST_PHASE_KERNELS = 4
#: The library of ``recon/native`` that holds each kernel's C twin (``module.kernel`` -> name):
#: where it loads, the estimate calls the C kernel and never this one (:func:`without_c_twins`).
C_TWINS: dict[str, str] = {
    "recon.entropy.initial._downsample_kernel": "initial",
    "recon.entropy.cost._min_window_costs_kernel": "initial",
    "recon.entropy.matching._subpixel_argmin_kernel": "initial",
    "recon.entropy.cost._cost_ambiguity_kernel": "initial",
    "recon.entropy.entropy._select_kernel": "select",
    "recon.entropy.layout._offer_runs_kernel": "joint",  # the joint search's offer runs
    "recon.entropy.matching._joint_group_kernel": "joint",
    "recon.entropy.volume._take_kernel": "volume",
    "recon.entropy.volume._window_major_kernel": "volume",
    "recon.entropy.median._median_kernel": "median",
    "recon.entropy.refine._centroid_kernel": "refine",
    "recon.entropy.refine._tv_wavefront": "refine",
    "recon.entropy.refine._tv_blocks": "refine",
    "recon.entropy.regions._occlusion_kernel": "regions",
    "recon.entropy.boundary._snap_kernel": "regions",
    "recon.entropy.noise.warp_landings": "views",  # the view filters' steps: numpy and OpenCV twins, no numba
    "recon.entropy.noise._blend_filtered": "views",
    "recon.entropy.calibration.jump_distance_reference": "confidence",  # its twin is scipy's, not numba's
    "recon.entropy.filters.uniform_filter": "filters",  # scipy's too
    "recon.entropy.filters.uniform_filter1d": "filters",
}


def without_c_twins(kernels: tuple[tuple[str, str, str], ...]) -> tuple[tuple[str, str, str], ...]:
    """The entries of ``kernels`` whose C twin (:data:`C_TWINS`) does not load here: the numba
    kernels an estimate will call. Loads (and, the first time, builds) the C libraries it asks
    about (:func:`recon.native.library`, milliseconds once built)."""
    from recon.native import library

    return tuple(entry for entry in kernels
                 if (twin := C_TWINS.get(f"{entry[0]}.{entry[1]}")) is None or library(twin) is None)


def argument_types(tokens: str) -> tuple:
    """The numba types of a signature written as in :data:`KERNELS` (``"float32:2 int64"``)."""
    from numba.core import types

    def one(token: str):
        name, *array = token.split(":")
        dtype = types.boolean if name == "bool" else getattr(types, name)
        if not array:
            return dtype
        return types.Array(dtype, int(array[0]), "C", readonly=array[1:] == ["ro"])

    return tuple(one(token) for token in tokens.split())


def load_kernels(kernels: tuple[tuple[str, str, str], ...] = KERNELS, *, stop: threading.Event | None = None) -> int:
    """Load every kernel of ``kernels`` (default :data:`KERNELS`) with its signature (from numba's
    cache, or compile it where the cache has none), or only those before ``stop`` is set (checked
    before each kernel); return how many were not loaded yet."""
    loaded = 0
    for module, name, tokens in kernels:
        if stop is not None and stop.is_set():
            break
        kernel = getattr(importlib.import_module(module), name)
        signature = argument_types(tokens)
        if signature not in kernel.overloads:
            kernel.compile(signature)
            loaded += 1
    return loaded
