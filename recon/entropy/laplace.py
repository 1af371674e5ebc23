"""The 4-neighbour Laplace equations of a hole mask, and their solution by scipy's SuperLU without
the import of ``scipy.sparse``.

:func:`recon.entropy.refine.harmonic_fill` solves ``A x = b`` for the pixels of the holes of a map
(three times in an estimate: the initial disparity's holes, the TV refinement's start and the
confidence's support). Its solver is SuperLU, as ``scipy.sparse.linalg.spsolve`` calls it. That
function needs ``scipy.sparse`` and ``scipy.sparse.linalg``, whose imports take ~0.15 s of Python
(scipy's array-API layer clones numpy's namespace, which loads ``numpy.f2py``, ``numpy.testing``
and ``scipy.linalg``) for a solve of ~15 ms; in ``lfrig reconstruct`` that is CPU the estimate's
threads lose. :func:`solve` calls the same SuperLU routine (``gssv`` of scipy's extension module
``_superlu``, loaded from its file by itself, 2 ms) with the same arrays that ``spsolve`` gives it,
so its bits are ``spsolve``'s (``tests/test_laplace.py`` compares them). Where that module cannot
be loaded or called so (another scipy), :func:`solve` falls back to ``spsolve`` itself.

:func:`laplace_system` builds the matrix as compressed columns straight away. It is symmetric, so
its columns are its rows; within a column the rows are in increasing order (the neighbour above,
the one to the left, the pixel itself, the one to the right, the one below: the pixels are numbered
row by row), which is the canonical form ``scipy.sparse.csr_matrix(...).tocsc()`` gives.
"""

from __future__ import annotations

import functools
import importlib.machinery
import importlib.util
from pathlib import Path
from typing import Any

import numpy as np

#: The weight on the diagonal that ties a hole component without a known neighbour weakly to 0.
TIE = 1e-9


def laplace_system(values: np.ndarray, holes: np.ndarray, ys: np.ndarray, xs: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(data, indices, indptr, b)``: the 4-neighbour Laplace equations ``A x = b`` of the hole
    pixels ``(ys, xs)`` (row by row, ``np.nonzero(holes)``) as the compressed columns of ``A``
    (float64 ``data``, int32 ``indices`` and ``indptr``; the diagonal is the pixel's neighbours
    inside the image plus :data:`TIE`, every hole neighbour -1) and the known neighbours' ``values``
    summed in ``b`` (float64). A hole component without a known neighbour has no boundary value: the
    tie keeps the system regular (it cannot happen unless a component is cut off from every known
    pixel)."""
    H, W = holes.shape
    n = len(ys)
    if 5 * n >= 2 ** 31:
        raise ValueError(f"laplace_system: {n} hole pixels are too many for 32-bit indices")
    index = np.full((H, W), -1, np.int32)
    index[ys, xs] = np.arange(n, dtype=np.int32)
    b = np.zeros(n)
    diag = np.zeros(n)
    rows = np.full((n, 5), -1, np.int32)  # per column: the unknown above, left, itself, right, below
    rows[:, 2] = np.arange(n, dtype=np.int32)
    for j, (dy, dx) in zip((0, 1, 3, 4), ((-1, 0), (0, -1), (0, 1), (1, 0))):
        ny, nx = ys + dy, xs + dx
        ok = (ny >= 0) & (ny < H) & (nx >= 0) & (nx < W)
        diag[ok] += 1
        k = np.nonzero(ok)[0]
        rows[k, j] = nb = index[ny[k], nx[k]]
        known = k[nb < 0]
        b[known] += values[ny[known], nx[known]]
    del index
    data = np.full((n, 5), -1.0)
    data[:, 2] = diag + TIE
    present = rows >= 0
    indptr = np.zeros(n + 1, np.int32)
    np.cumsum(present.sum(axis=1), out=indptr[1:])
    return data[present], rows[present], indptr, b


def solve(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` of ``A x = b`` for the ``(n, n)`` matrix ``A`` of compressed columns ``(data, indices,
    indptr)`` (float64, int32, int32; canonical: rows increasing within a column, no duplicates),
    by SuperLU with its default column order (COLAMD): the bits of
    ``scipy.sparse.linalg.spsolve(scipy.sparse.csc_matrix((data, indices, indptr)), b)``. A singular
    matrix gives NaN everywhere (as ``spsolve``, without its warning)."""
    n = len(indptr) - 1
    gssv = _gssv()
    if gssv is not None:
        try:
            x, info = gssv(n, len(data), data, indices, indptr, b, 1, options={"ColPerm": None})
        except TypeError:  # a scipy whose gssv takes other arguments
            gssv = None
    if gssv is None:
        import scipy.sparse
        import scipy.sparse.linalg

        return scipy.sparse.linalg.spsolve(scipy.sparse.csc_matrix((data, indices, indptr), shape=(n, n)), b)
    if info > n:
        raise MemoryError(f"SuperLU ran out of memory factoring {n} equations")
    if info != 0:
        x.fill(np.nan)
    return x.ravel()


def solver_loads() -> bool:
    """Whether :func:`solve` calls SuperLU without importing ``scipy.sparse`` here."""
    return _gssv() is not None


@functools.cache
def _gssv() -> Any | None:
    """SuperLU's ``gssv`` from scipy's extension module ``scipy.sparse.linalg._dsolve._superlu``,
    loaded from its file without importing the packages around it (it needs only numpy); ``None``
    where scipy has no such module (then :func:`solve` calls ``spsolve``)."""
    try:
        found = importlib.util.find_spec("scipy")
        if found is None or not found.submodule_search_locations:
            return None
        folder = Path(next(iter(found.submodule_search_locations))) / "sparse" / "linalg" / "_dsolve"
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = folder / f"_superlu{suffix}"
            if path.is_file():
                spec = importlib.util.spec_from_file_location("scipy.sparse.linalg._dsolve._superlu", path)
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
                return getattr(module, "gssv", None)
    except (ImportError, OSError):
        return None
    return None
