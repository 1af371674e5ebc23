"""The baseline's plane sweep: for each candidate disparity every view shifted onto the centre view,
its mean absolute difference box-filtered, and per pixel the least so far kept, without a cost volume.

:func:`sweep_least_cost` runs one of two kernels that give the same bits: the C one of
:mod:`recon.native` (``sweep.c``), which loads in milliseconds and needs no numba in the process, and
numba's :func:`recon.costvolume._sweep_kernel`, used where the C one cannot be built and kept as its
twin. This module imports neither numba nor :mod:`recon.costvolume` unless the numba kernel runs.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from recon.native import call, library, thread_count
from recon.shifts import shift_parts, view_offsets  # noqa: F401  view_offsets: the views to match

#: Which kernel :func:`sweep_least_cost` runs: ``"auto"`` the C one where it loads, else numba's.
Kernel = Literal["auto", "native", "numba"]


def native_library():
    """The C sweep's library (:func:`recon.native.library`), or ``None`` where it cannot be had."""
    return library("sweep")


def sweep_least_cost(gray: np.ndarray, candidates: np.ndarray, *, offsets: np.ndarray, indices: np.ndarray,
                     window: int, state: dict[str, np.ndarray] | None = None, first: int = 0,
                     bands: int | None = None, kernel: Kernel = "auto") -> dict[str, np.ndarray]:
    """The plane sweep over ``candidates`` (the ones numbered ``first ..`` of a longer sweep when
    ``state`` holds the earlier ones' result): per pixel of the centre view, the least
    ``box_mean(pixel_cost(gray, d, ...), window)`` over ``d`` and its two neighbours' means
    (:mod:`recon.costvolume`'s functions).

    Returns (and updates) ``state``: ``best`` ``(H, W)`` float32 least mean, ``best_index`` int64
    its candidate's number (the first least, as ``np.argmin``), ``c_minus``, ``c_plus`` float32 the
    means at the candidates before and after it (where they exist), ``previous`` the last
    candidate's means. The same numbers as those functions give, bit for bit, without holding a
    cost volume; rows are dealt to the threads in bands, so no thread waits for another between
    candidates (``bands``: how many; default one per thread, :func:`recon.native.thread_count`; the
    result is the same). ``kernel``: ``"native"`` the C kernel (``RuntimeError`` saying why where it
    cannot be had), ``"numba"`` numba's, ``"auto"`` (default) the C one where it loads, else numba's.
    """
    H, W = gray.shape[2:]
    if window < 1 or window % 2 == 0 or window // 2 >= min(H, W):
        raise ValueError(f"window must be odd, >= 1 and smaller than the {W}x{H} image; got {window}")
    if kernel not in ("auto", "native", "numba"):
        raise ValueError(f"kernel must be 'auto', 'native' or 'numba'; got {kernel!r}")
    if state is None:
        state = {"best": np.empty((H, W), np.float32), "best_index": np.full((H, W), -2, np.int64),
                 "c_minus": np.zeros((H, W), np.float32), "c_plus": np.zeros((H, W), np.float32),
                 "previous": np.zeros((H, W), np.float32)}
    indices = np.ascontiguousarray(indices, dtype=np.int64).reshape(-1, 2)
    if len(indices) == 0 or len(indices) != len(np.asarray(offsets).reshape(-1, 2)):
        raise ValueError(f"offsets and indices must name the same views, at least one; got {len(indices)} indices")
    if len(candidates) == 0:  # nothing to sweep
        return state
    threads = thread_count()
    bands = max(1, min(threads if bands is None else int(bands), H))
    edges = np.linspace(0, H, bands + 1).astype(np.int64)
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    vu, vv = indices[:, 0].copy(), indices[:, 1].copy()
    oy, fy, ox, fx = shift_parts(offsets, candidates)
    lib = native_library() if kernel != "numba" else None
    if lib is None and kernel == "native":
        from recon.native import unavailable

        raise RuntimeError(f"the C sweep is not available: {unavailable('sweep')}")
    if lib is None:
        from recon.costvolume import _sweep_kernel

        _sweep_kernel(gray, vu, vv, oy, fy, ox, fx, int(first), int(window), edges, state["previous"],
                      state["best"], state["best_index"], state["c_minus"], state["c_plus"])
        return state
    for name, dtype in (("previous", np.float32), ("best", np.float32), ("best_index", np.int64),
                        ("c_minus", np.float32), ("c_plus", np.float32)):
        array = state[name]
        if array.dtype != dtype or array.shape != (H, W) or not array.flags.c_contiguous or not array.flags.writeable:
            raise ValueError(f"state[{name!r}] must be a writable C-contiguous ({H}, {W}) {np.dtype(dtype)} array")
    U, V = gray.shape[:2]
    if not (0 <= vu.min() and vu.max() < U and 0 <= vv.min() and vv.max() < V):
        raise ValueError(f"view indices must lie within the {U}x{V} grid")
    call("sweep", "lfrig_sweep", gray, U, V, H, W, vu, vv, len(vu), oy, fy, ox, fx, len(oy), int(first), int(window),
         edges, bands, min(threads, bands), state["previous"], state["best"], state["best_index"], state["c_minus"],
         state["c_plus"])
    return state
