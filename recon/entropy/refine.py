"""TV refinement of Eq. 13 in smooth regions only.

    mu = argmin_mu  sum_{smooth} w (mu - d*)^2 + gamma * sum |grad mu|

with ``mu = d*`` held fixed outside the smooth region (so edges, which the paper keeps out of the
refinement, stay sharp, and the smooth region is tied to its surroundings through the TV term).
``|grad mu|`` is the isotropic TV with forward differences (pixel units). Solved with the first-order
primal-dual algorithm of Chambolle and Pock (2011); the pixel-wise prox of the data term is exact,
and the fixed pixels are a projection, so the iteration converges to the constrained minimum.

``w`` is 1 (the paper) except on *black holes* (lfrig): smooth pixels where the matching had no
information (its cost curve is flat), whose ``d*`` is noise. There ``w = 0``: the hole is filled by the
TV term alone from its surroundings, which is what the paper uses the refinement for ("the
refinement can repair these black holes"). Holes wider than the largest window need a good start to
converge in a few hundred iterations; :func:`harmonic_fill` gives it (exact on a plane).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from recon.jit import numba
from recon.native import call, chosen, thread_count
import numpy as np

if TYPE_CHECKING:  # scipy loads at the first multigrid solve (holes of over LU_MAX_PIXELS)
    import scipy.sparse


#: Holes of up to this many pixels (every hole of a 512x512 image) are filled by a sparse LU of their
#: Laplacian, larger ones by conjugate gradients preconditioned with multigrid (:func:`harmonic_fill`).
#: The LU's memory grows faster than the hole (a square of 2^18 pixels: 508 MiB, the multigrid's 107;
#: the 1.24 M pixels of a 2000x1500 capture's wall: 2.8 GB and 19 s CPU, the multigrid's 377 MiB and 4 s).
LU_MAX_PIXELS = 2 ** 18

#: Relative residual ``|A x - b| / |b|`` at which the multigrid-preconditioned solve stops.
MULTIGRID_RTOL = 1e-12


def harmonic_fill(values: np.ndarray, holes: np.ndarray, *, solver: str = "auto") -> np.ndarray:
    """``values`` with the ``holes`` pixels replaced by the solution of Laplace's equation whose
    boundary values are the known neighbours (4-neighbourhood, image edges free). Linear functions
    are reproduced where the hole keeps off the image's edges (to rounding by the LU, to the
    tolerance by multigrid). ``(H, W)`` float32; returned unchanged when nothing is known.

    ``solver``: ``"lu"`` (SuperLU, scipy's sparse LU, exact to rounding, called without importing
    ``scipy.sparse``: :mod:`recon.entropy.laplace`; its memory grows faster than the hole), ``"multigrid"`` (conjugate gradients preconditioned with a multigrid V-cycle to a
    relative residual of :data:`MULTIGRID_RTOL`; memory in proportion to the hole; ``ValueError``
    when a known neighbour is not finite, where the LU gives NaN) or ``"auto"`` (the LU up to
    :data:`LU_MAX_PIXELS` hole pixels, else multigrid)."""
    if solver not in ("auto", "lu", "multigrid"):
        raise ValueError(f"solver must be 'auto', 'lu' or 'multigrid', got {solver!r}")
    holes = np.asarray(holes, bool)
    out = np.array(values, np.float64)
    if not holes.any() or holes.all():
        return out.astype(np.float32)
    ys, xs = np.nonzero(holes)
    if solver == "lu" or (solver == "auto" and len(ys) <= LU_MAX_PIXELS):
        from recon.entropy.laplace import laplace_system, solve

        out[ys, xs] = solve(*laplace_system(out, holes, ys, xs))
        return out.astype(np.float32)
    A, rhs = _laplace_system(out, holes, ys, xs)
    if not np.isfinite(rhs).all():
        raise ValueError(f"harmonic_fill: {np.count_nonzero(~np.isfinite(rhs))} hole pixels have a non-finite known "
                         "neighbour; pass finite values around the holes (or mark those pixels as holes too)")
    else:
        out[ys, xs] = _multigrid_cg(A, rhs, ys, xs)
    return out.astype(np.float32)


def _laplace_system(values: np.ndarray, holes: np.ndarray, ys: np.ndarray, xs: np.ndarray):
    """``(A, b)``: the 4-neighbour Laplace equations ``A x = b`` of the hole pixels ``(ys, xs)``
    (``A`` CSR ``(n, n)``, the known neighbours' ``values`` in ``b``). A hole component without a
    known neighbour has no boundary value: ``1e-9`` on the diagonal ties it weakly to 0 so that the
    system stays regular (cannot happen unless a component is cut off from every known pixel)."""
    H, W = holes.shape
    n = len(ys)
    index = np.full((H, W), -1, np.int32 if n < 2 ** 31 else np.int64)
    index[ys, xs] = np.arange(n)
    rhs = np.zeros(n)
    diag = np.zeros(n)
    columns = np.full((n, 5), -1, index.dtype)  # per row: its unknown neighbours (-1: none), itself
    for j, (dy, dx) in enumerate(((-1, 0), (1, 0), (0, -1), (0, 1))):
        ny, nx = ys + dy, xs + dx
        ok = (ny >= 0) & (ny < H) & (nx >= 0) & (nx < W)
        diag[ok] += 1
        k = np.nonzero(ok)[0]
        columns[k, j] = nb = index[ny[k], nx[k]]
        known = k[nb < 0]
        rhs[known] += values[ny[known], nx[known]]
    del index
    columns[:, 4] = np.arange(n)
    data = np.full((n, 5), -1.0)
    data[:, 4] = diag + 1e-9
    return _rows_to_csr(columns, data, n), rhs


def _rows_to_csr(columns: np.ndarray, data: np.ndarray, n_columns: int) -> scipy.sparse.csr_matrix:
    """The CSR matrix whose row ``i`` holds ``data[i, j]`` at column ``columns[i, j]`` for every
    ``j`` with ``columns[i, j] >= 0`` (``(n, k)`` arrays; -1: no entry)."""
    import scipy.sparse

    present = columns >= 0
    indptr = np.concatenate([[0], np.cumsum(present.sum(axis=1))])
    return scipy.sparse.csr_matrix((data[present], columns[present], indptr), shape=(len(columns), n_columns))


#: The multigrid's coarsest level: solved by a sparse LU once it has at most this many unknowns.
MULTIGRID_COARSEST = 4096


def _coarser(ys: np.ndarray, xs: np.ndarray):
    """``(P, cys, cxs)``: the next level's nodes, the points ``(ys, xs)`` (given row by row) on
    even rows and columns, at ``(cys, cxs) = (ys, xs) // 2``, and the bilinear interpolation ``P``
    (CSR ``(n, m)``) from them to the points, its weights normalised over the nodes present (a
    point with none gets none)."""
    even = (ys % 2 == 0) & (xs % 2 == 0)
    width = int(xs.max()) // 2 + 2
    nodes = ys[even] // 2 * width + xs[even] // 2  # sorted, as the points come row by row
    n = len(ys)
    columns = np.full((n, 4), -1, np.int32 if len(nodes) < 2 ** 31 else np.int64)
    weights = np.zeros((n, 4))
    if len(nodes):
        for j, (a, b) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            key = (ys // 2 + a) * width + xs // 2 + b
            at = np.minimum(np.searchsorted(nodes, key), len(nodes) - 1)
            w = np.where(ys % 2, 0.5, 1.0 - a) * np.where(xs % 2, 0.5, 1.0 - b)  # odd: two nodes, half each
            hit = (w > 0) & (nodes[at] == key)
            columns[hit, j] = at[hit]
            weights[hit, j] = w[hit]
    total = weights.sum(axis=1, keepdims=True)
    np.divide(weights, total, out=weights, where=total > 0)
    return _rows_to_csr(columns, weights, len(nodes)), nodes // width, nodes % width


def _multigrid_cg(A: scipy.sparse.csr_matrix, b: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Solve ``A x = b`` (:func:`_laplace_system` of the pixels ``(ys, xs)``) by conjugate gradients
    preconditioned with one V-cycle: Galerkin coarse levels ``P^T A P`` on grids of every other row and
    column (:func:`_coarser`), two damped-Jacobi sweeps before and after each coarse correction
    (damping ``4 / 3`` over the Gershgorin bound of ``D^-1 A``), a sparse LU on the coarsest level."""
    import scipy.sparse.linalg

    system = A
    ys, xs = ys.astype(np.int32), xs.astype(np.int32)  # (H * W < 2 ** 31)
    levels = []  # (A, omega / diagonal, P to the next level)
    while A.shape[0] > MULTIGRID_COARSEST:
        P, cys, cxs = _coarser(ys, xs)
        if P.shape[1] > A.shape[0] // 2:  # too few points to drop: solve this level
            break
        ys, xs = cys, cxs
        diagonal = A.diagonal()
        omega = 4.0 / 3.0 / np.max(np.add.reduceat(np.abs(A.data), A.indptr[:-1]) / diagonal)
        levels.append((A, omega / diagonal, P))
        A = (P.T @ A @ P).tocsr()
    coarsest = scipy.sparse.linalg.splu(A.tocsc())

    n = len(b)
    M = scipy.sparse.linalg.LinearOperator((n, n), matvec=lambda r: _vcycle(levels, coarsest, r),
                                           dtype=np.float64)
    x, info = scipy.sparse.linalg.cg(system, b, rtol=MULTIGRID_RTOL, atol=0.0,
                                     M=M, maxiter=500)
    if info != 0:
        raise RuntimeError(f"the hole fill's multigrid solve did not converge in {info} iterations")
    return x


def _vcycle(levels: list, coarsest, r: np.ndarray, level: int = 0) -> np.ndarray:
    """One V-cycle of :func:`_multigrid_cg` from ``level`` on the residual ``r``."""
    if level == len(levels):
        return coarsest.solve(r)
    A, scale, P = levels[level]
    x = scale * r
    x += scale * (r - A @ x)
    x += P @ _vcycle(levels, coarsest, P.T @ (r - A @ x), level + 1)
    for _ in range(2):
        x += scale * (r - A @ x)
    return x


def _grad(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gy = np.zeros_like(u)
    gx = np.zeros_like(u)
    gy[:-1] = u[1:] - u[:-1]
    gx[:, :-1] = u[:, 1:] - u[:, :-1]
    return gy, gx


def _div(py: np.ndarray, px: np.ndarray) -> np.ndarray:
    # Negative adjoint of _grad.
    d = np.zeros_like(py)
    d[0] += py[0]
    d[1:-1] += py[1:-1] - py[:-2]
    d[-1] -= py[-2]
    d[:, 0] += px[:, 0]
    d[:, 1:-1] += px[:, 1:-1] - px[:, :-2]
    d[:, -1] -= px[:, -2]
    return d


def tv_energy(mu: np.ndarray, data: np.ndarray, mask: np.ndarray, gamma: float) -> float:
    """Value of Eq. 13 (data term over ``mask`` plus ``gamma`` times the TV of the whole map)."""
    gy, gx = _grad(mu.astype(np.float64))
    return float(np.sum(((mu - data) ** 2)[mask]) + gamma * np.sum(np.sqrt(gy ** 2 + gx ** 2)))


def _tv_problem(disparity: np.ndarray, mask: np.ndarray, holes: np.ndarray | None,
                hole_weight: np.ndarray | None = None):
    """Eq. 13's inputs with black holes: ``(start, data, mask, data weight)``; holes join the mask
    with weight 0 (or ``hole_weight`` there) and start from :func:`harmonic_fill`; a hole with a
    positive weight keeps its own value as data."""
    mask = np.asarray(mask, bool)
    weight = np.ones(mask.shape)
    start = disparity
    if holes is not None and np.any(holes):
        holes = np.asarray(holes, bool)
        start = harmonic_fill(disparity, holes)
        mask = mask | holes
        weight[holes] = 0.0 if hole_weight is None else np.asarray(hole_weight, np.float64)[holes]
        if hole_weight is not None:
            disparity = np.where(holes & (weight > 0), disparity, start).astype(np.float32)
        else:
            disparity = start
    return start, disparity, mask, weight


def valley_weights(width: np.ndarray, *, flat: np.ndarray, no_data: np.ndarray | None,
                   hole_width: float, unsure_width: float, plateau_width: float = np.inf
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels join the refinement with a reduced data weight, and that weight.

    Eq. 13's data term ``w (mu - d*)^2`` is a quadratic model of the matching cost around its
    minimum ``d*``; a cost valley of width ``width`` (the disparity span within the hole tolerance
    of the least cost) has a curvature ``~ 1 / width^2``. So a pixel whose valley is wider than
    ``hole_width`` keeps its matched value with the weight ``(hole_width / width)^2`` instead of
    none (a black hole) or a fixed value (outside the smooth region):

    - the black holes (``flat`` and ``width > hole_width``) and the textured pixels whose valley is
      wider than ``unsure_width`` join;
    - a pixel without data (``no_data``: noise-limited, or nothing but noise in its window) keeps
      weight 0 as before: its matched value is the noise's, not the surface's
      (``docs/entropy-method.md``); a pixel whose every candidate lies in the valley
      (``width >= plateau_width``, the span of all candidates) joins with weight 0: a plateau
      has no minimum, so it is filled from its surroundings.

    ``(H, W)`` maps in (``width`` px/view); ``(joined bool, weight float64 in [0, 1])`` out.
    """
    width = np.asarray(width, np.float64)
    holes = np.asarray(flat, bool) & (width > hole_width)
    wide = holes | (width > unsure_width)
    if no_data is not None:
        wide &= ~np.asarray(no_data, bool)
    joined = holes | wide  # a plateau joins with weight 0: filled from its surroundings
    weight = np.where(wide & (width < plateau_width - 1e-9),
                      np.minimum(1.0, (hole_width / np.maximum(width, 1e-9)) ** 2), 0.0)
    return joined, weight


def tv_refine_reference(disparity: np.ndarray, mask: np.ndarray, *, gamma: float,
              iterations: int, holes: np.ndarray | None = None,
              hole_weight: np.ndarray | None = None) -> np.ndarray:
    """Minimise Eq. 13 over the pixels of ``mask``; the others keep their value (readable numpy
    reference of :func:`tv_refine`, the compiled twin).

    Parameters
    ----------
    disparity
        ``(H, W)`` disparity ``d*`` from the matching, pixels per view step.
    mask
        ``(H, W)`` bool, the smooth region.
    gamma
        TV weight (the paper's 0.2).
    iterations
        Primal-dual iterations.
    holes
        ``(H, W)`` bool, optional: pixels (inside or outside ``mask``) whose data term is dropped,
        filled from their surroundings; started from :func:`harmonic_fill`.
    hole_weight
        ``(H, W)`` float, optional: the data weight of the ``holes`` pixels instead of 0 (where it
        is positive the pixel's own value stays the data; :func:`valley_weights`).

    Returns
    -------
    ``(H, W)`` float32 refined disparity ``mu``.
    """
    start, disparity, mask, weight = _tv_problem(disparity, mask, holes, hole_weight)
    f = disparity.astype(np.float64)
    if gamma <= 0 or not mask.any() or iterations <= 0:
        return start.astype(np.float32)
    tau = sigma = 1.0 / np.sqrt(8.0)
    mu = start.astype(np.float64)
    bar = mu.copy()
    py = np.zeros_like(f)
    px = np.zeros_like(f)
    for _ in range(iterations):
        gy, gx = _grad(bar)
        py += sigma * gy
        px += sigma * gx
        norm = np.maximum(1.0, np.sqrt(py ** 2 + px ** 2) / gamma)
        py /= norm
        px /= norm
        v = mu + tau * _div(py, px)
        new = np.where(mask, (v + 2 * tau * weight * f) / (1 + 2 * tau * weight), f)
        bar = 2 * new - mu
        mu = new
    return mu.astype(np.float32)


@numba.njit(cache=True)
def _tv_kernel(f, mask, weight, gamma, iterations, mu, bar, py, px, top, H):
    # The iterations of tv_refine_reference, the same float64 operations in the same order (so the
    # same values), two sweeps per iteration (the plain twin of _tv_wavefront, which runs): dual
    # ascent and projection, then the primal step with
    # the divergence. Needs H, W >= 2. The arrays hold the rows top .. top + n - 1 of an image of H
    # rows; a row whose neighbour lies outside them (not outside the image) gets a wrong value, and
    # after k iterations so do the k rows nearest each such side (_tv_blocks keeps them out).
    n, W = f.shape
    tau = 1.0 / np.sqrt(8.0)
    sigma = tau
    for _ in range(iterations):
        for i in range(n):
            y = top + i
            for x in range(W):
                gy = bar[i + 1, x] - bar[i, x] if y < H - 1 and i < n - 1 else 0.0
                gx = bar[i, x + 1] - bar[i, x] if x < W - 1 else 0.0
                qy = py[i, x] + sigma * gy
                qx = px[i, x] + sigma * gx
                norm = max(1.0, np.sqrt(qy ** 2 + qx ** 2) / gamma)
                py[i, x] = qy / norm
                px[i, x] = qx / norm
        for i in range(n):
            y = top + i
            for x in range(W):
                if y == 0 or i == 0:
                    dy = py[i, x]
                elif y < H - 1:
                    dy = py[i, x] - py[i - 1, x]
                else:
                    dy = -py[i - 1, x]
                if x == 0:
                    dx = px[i, 0]
                elif x < W - 1:
                    dx = px[i, x] - px[i, x - 1]
                else:
                    dx = -px[i, W - 2]
                if mask[i, x]:
                    v = mu[i, x] + tau * (dy + dx)
                    w = 2 * tau * weight[i, x]
                    new = (v + w * f[i, x]) / (1 + w)
                else:
                    new = f[i, x]
                bar[i, x] = 2 * new - mu[i, x]
                mu[i, x] = new


@numba.njit(cache=True, inline="always")
def _tv_dual(py, px, gy, gx, sigma, gamma):
    # _tv_kernel's dual step at one pixel, given its forward differences: the new (py, px), without
    # a branch (inside the ball the norm is 1 and the divisions leave the values as they are).
    qy = py + sigma * gy
    qx = px + sigma * gx
    norm = max(1.0, np.sqrt(qy ** 2 + qx ** 2) / gamma)
    return qy / norm, qx / norm


@numba.njit(cache=True, inline="always")
def _tv_primal(f, mask, weight, mu, div, tau):
    # _tv_kernel's primal step at one pixel, given its divergence (dy + dx, in that order): the new
    # mu; the masked value is computed everywhere and chosen (no branch).
    v = mu + tau * div
    w = 2 * tau * weight
    return (v + w * f) / (1 + w) if mask else f


# A row's loops over x (_tv_row), in two functions of their own: LLVM vectorises them so (sqrt
# and division packed, which round exactly as the scalar ones: the same values), not inlined into
# the sweep. The numpy error model leaves out the test for a zero divisor, which would keep the
# loops scalar (there is none: the norm is at least 1, and so is 1 + w). Each runs over the runs
# ``r0 .. r1 - 1`` of the row's columns (tv_runs) with unsigned indices: a signed one, which numba
# cannot prove to be >= 0, gets a test for wrapping around and keeps the loop scalar.

@numba.njit(cache=True, error_model="numpy")
def _tv_dual_row(qy, qx, b0, b1, below, sigma, gamma, run_x0, run_x1, r0, r1):
    # The dual step along the runs of a row, in place on its dual values qy, qx, from its primal
    # values b0 and, if ``below``, the next row's b1 (else the y difference is 0).
    one = np.uint64(1)
    m = np.uint64(b0.shape[0] - 1)
    for r in range(r0, r1):
        x0, x1 = run_x0[r], run_x1[r]
        for x in range(x0, min(x1, m)):
            qy[x], qx[x] = _tv_dual(qy[x], qx[x], b1[x] - b0[x] if below else 0.0, b0[x + one] - b0[x], sigma, gamma)
        if x1 > m:
            qy[m], qx[m] = _tv_dual(qy[m], qx[m], b1[m] - b0[m] if below else 0.0, 0.0, sigma, gamma)


@numba.njit(cache=True, error_model="numpy")
def _tv_divergence_primal_row(f, mask, weight, mu, bar, div, qy, qx, above, edge, tau, run_x0, run_x1, r0, r1):
    # Along the runs of a row: the divergence into div from its dual values qy, qx and the row
    # above's y part ``above`` (``edge`` 0 on the first row, no row above, 1 inside, 2 on the last
    # row), then the primal step, in place on its mu and bar.
    one = np.uint64(1)
    m = np.uint64(qy.shape[0] - 1)
    for r in range(r0, r1):
        x0, x1 = run_x0[r], run_x1[r]
        if edge == 0:
            for x in range(x0, x1):
                div[x] = qy[x]
        elif edge == 1:
            for x in range(x0, x1):
                div[x] = qy[x] - above[x]
        else:
            for x in range(x0, x1):
                div[x] = -above[x]
        if x0 == 0:
            div[0] += qx[0]
        for x in range(max(x0, one), min(x1, m)):
            div[x] += qx[x] - qx[x - one]
        if x1 > m:
            div[m] += -qx[m - one]
        for x in range(x0, x1):
            new = _tv_primal(f[x], mask[x], weight[x], mu[x], div[x], tau)
            bar[x] = 2 * new - mu[x]
            mu[x] = new


@numba.njit(cache=True, inline="always")
def _tv_row(f, mask, weight, gamma, mu, bar, py, px, i, top, H, tau, sigma, div, runs, run_x0, run_x1):
    # One iteration of _tv_kernel at row i over its runs (image row top + i): their dual step
    # (reads bar's rows i and i + 1), then their primal step (reads py's rows i - 1 and i, writes
    # bar's and mu's row i), with the tests of the image's edges taken out of the loops over x.
    # ``div``: (W,) scratch for the divergence.
    n = f.shape[0]
    y = top + i
    if runs[y] == runs[y + 1]:
        return
    below = y < H - 1 and i < n - 1
    _tv_dual_row(py[i], px[i], bar[i], bar[i + 1] if below else bar[i], below, sigma, gamma, run_x0, run_x1,
                 runs[y], runs[y + 1])
    edge = 0 if y == 0 or i == 0 else 1 if y < H - 1 else 2
    _tv_divergence_primal_row(f[i], mask[i], weight[i], mu[i], bar[i], div, py[i], px[i], py[i - 1] if i > 0 else py[i],
                              edge, tau, run_x0, run_x1, runs[y], runs[y + 1])


#: Iterations the TV kernel carries through the rows in one sweep (:func:`_tv_wavefront`).
TV_WAVE_ITERATIONS = 8


@numba.njit(cache=True)
def _tv_wavefront(f, mask, weight, gamma, iterations, mu, bar, py, px, top, H, depth, runs, run_x0, run_x1):
    # _tv_kernel with the same operations on the values of the runs (tv_runs: where they can
    # change) in an order that keeps the rows it works on in cache: `depth` iterations at a time in
    # one sweep down the rows, iteration t + 1 one row behind iteration t (row i of iteration t + 1
    # needs rows i and i + 1 of iteration t, and overwrites row i's dual values only after
    # iteration t's row i + 1 has read them). Each row's two steps follow each other (the dual step
    # of row i reads no primal value of this iteration). ``runs``: per image row, where its runs
    # begin in run_x0, run_x1 (the arrays hold the rows top .. top + n - 1).
    n, W = f.shape
    tau = 1.0 / np.sqrt(8.0)
    sigma = tau
    div = np.empty(W)
    done = 0
    while done < iterations:
        k = min(depth, iterations - done)
        for front in range(n + k - 1):
            for j in range(k):
                i = front - j
                if 0 <= i < n:
                    _tv_row(f, mask, weight, gamma, mu, bar, py, px, i, top, H, tau, sigma, div, runs, run_x0, run_x1)
        done += k


@numba.njit(cache=True)
def _copy_runs(source, target, source_top, target_top, y0, y1, runs, run_x0, run_x1):
    # The values of the runs of image rows [y0, y1) from the maps of `source` (rows from
    # source_top) into those of `target` (rows from target_top).
    for y in range(y0, y1):
        for r in range(runs[y], runs[y + 1]):
            a, b = run_x0[r], run_x1[r]
            for s, t in zip(source, target):
                t[y - target_top, a:b] = s[y - source_top, a:b]


@numba.njit(cache=True, parallel=True)
def _tv_blocks(f, mask, weight, gamma, iterations, mu, bar, py, px, edges, halo, runs, run_x0, run_x1):
    # The image in bands of rows [edges[b], edges[b + 1]), one per thread, each iterated on a copy
    # of its own of its band and `halo` rows around it for up to `halo` iterations at a time (the
    # wrong rows at a copy's cut edges advance one row per iteration, so they never reach the
    # band); between those rounds each band's runs go into the next maps and each copy takes its
    # halo rows' runs from them (the values outside the runs never change). The values are those
    # of one thread over the whole image; one barrier per `halo` iterations instead of two per
    # iteration.
    H, W = f.shape
    n_blocks = edges.shape[0] - 1
    depth = 0
    for b in range(n_blocks):
        depth = max(depth, min(edges[b + 1] + halo, H) - max(edges[b] - halo, 0))
    copies = (np.empty((n_blocks, depth, W)), np.empty((n_blocks, depth, W)), np.empty((n_blocks, depth, W)),
              np.empty((n_blocks, depth, W)))
    state = (mu, bar, py, px)
    nxt = (mu.copy(), bar.copy(), py.copy(), px.copy())
    done = 0
    while done < iterations:
        k = min(halo, iterations - done)
        for b in numba.prange(n_blocks):
            lo, hi = edges[b], edges[b + 1]
            a = max(lo - halo, 0)
            z = min(hi + halo, H)
            own = (copies[0][b][:z - a], copies[1][b][:z - a], copies[2][b][:z - a], copies[3][b][:z - a])
            if done == 0:
                for s, t in zip(state, own):
                    t[:] = s[a:z]
            else:
                _copy_runs(state, own, 0, a, a, lo, runs, run_x0, run_x1)
                _copy_runs(state, own, 0, a, hi, z, runs, run_x0, run_x1)
            _tv_wavefront(f[a:z], mask[a:z], weight[a:z], gamma, k, own[0], own[1], own[2], own[3], a, H,
                          TV_WAVE_ITERATIONS, runs, run_x0, run_x1)
            _copy_runs(own, nxt, a, 0, lo, hi, runs, run_x0, run_x1)
        state, nxt = nxt, state
        done += k
    return state[0]


#: Iterations of the TV refinement between two exchanges of the threads' bands (and the rows each
#: band's copy reaches beyond it): 300 iterations are 19 parallel regions.
TV_HALO_ROWS = 16

#: Fewest pixels in the TV kernel's runs (:func:`tv_runs`) for which it runs in bands on every
#: thread: below, the copies and the halo rows cost more CPU than the second thread saves wall
#: (backgammon's 131 k: 0.21 s CPU on one thread, 0.26 s in two bands, and 0.43 against 0.55 s
#: wall at load 6).
TV_PARALLEL_PIXELS = 2 ** 18

#: :data:`TV_PARALLEL_PIXELS` of the C kernels (``recon/native/refine.c``: the bands' threads start
#: once per call, each band's copy takes the rows beyond it from the others' between two barriers a
#: round). Backgammon's 131 k run in two bands there: ``tv_refine`` 0.12 s wall (0.20 s CPU) against
#: one thread's 0.17 s at load 1; where the second core is another process's the bands cost a tenth
#: more than one thread (0.14 against 0.13 s wall at load 3).
TV_NATIVE_PARALLEL_PIXELS = 2 ** 16

#: Columns between two runs of the TV kernel's pixels (:func:`tv_runs`) up to which they are
#: worked as one: a loop over x stays long enough to run several pixels at once.
TV_RUN_GAP = 8


def tv_runs(mask: np.ndarray, start: np.ndarray, data: np.ndarray, *, gap: int = TV_RUN_GAP
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where Eq. 13's iteration (:func:`tv_refine`) can change a value: the pixels of ``mask``,
    those whose dual value a pixel of ``mask`` reads (the one above and the one to the left of it),
    and those outside ``mask`` that start away from their ``data`` (the first iteration sets them
    to it). Every other pixel keeps its primal value (its data) and its dual value, which no
    pixel of ``mask`` reads, so the iteration leaves them out. ``(H, W)`` maps in; out ``(runs,
    x0, x1)``: row ``y``'s runs of such columns are ``[x0[r], x1[r])`` for ``r`` in
    ``range(runs[y], runs[y + 1])``, runs at most ``gap`` columns apart joined (int64 each)."""
    mask = np.asarray(mask, bool)
    active = mask | (start != data)
    active[:-1] |= mask[1:]
    active[:, :-1] |= mask[:, 1:]
    H, W = active.shape
    padded = np.zeros((H, W + 2), np.int8)
    padded[:, 1:-1] = active
    change = np.diff(padded, axis=1)
    ys, x0 = np.nonzero(change == 1)  # row by row, left to right
    x1 = np.nonzero(change == -1)[1]
    first = np.ones(ys.size, bool)  # a run that does not continue the one before
    first[1:] = (ys[1:] != ys[:-1]) | (x0[1:] - x1[:-1] > gap)
    begin = np.flatnonzero(first)
    end = np.append(begin[1:], ys.size) - 1
    runs = np.zeros(H + 1, np.int64)
    np.cumsum(np.bincount(ys[begin], minlength=H), out=runs[1:])
    return runs, x0[begin].astype(np.uint64), x1[end].astype(np.uint64)


def tv_bands(runs: np.ndarray, run_x0: np.ndarray, run_x1: np.ndarray, n_bands: int) -> np.ndarray:
    """``(n_bands + 1,)`` int64 row edges of ``n_bands`` bands of rows (at least one row each) with
    about the same share of the runs' columns (:func:`tv_runs`), a column more for every row."""
    H = runs.shape[0] - 1
    rows = np.repeat(np.arange(H), np.diff(runs))
    total = np.cumsum(np.bincount(rows, weights=run_x1 - run_x0, minlength=H) + 1)
    edges = [0]
    for share in total[-1] * np.arange(1, n_bands) / n_bands:
        cut = int(np.searchsorted(total, share)) + 1
        edges.append(min(max(cut, edges[-1] + 1), H - n_bands + len(edges)))
    return np.array(edges + [H], np.int64)


def tv_refine(disparity: np.ndarray, mask: np.ndarray, *, gamma: float,
              iterations: int, holes: np.ndarray | None = None,
              hole_weight: np.ndarray | None = None, kernel: str = "auto") -> np.ndarray:
    """Minimise Eq. 13 over the pixels of ``mask``; the others keep their value.

    Compiled twin of :func:`tv_refine_reference`: the same parameters and result (Chambolle-Pock in
    two sweeps per iteration instead of 300 rounds of whole-array numpy operations, over the
    pixels whose values can change, :func:`tv_runs`). ``kernel``: :func:`recon.native.chosen`: by
    default the C twin of :func:`_tv_wavefront` and :func:`_tv_blocks` (``recon/native/refine.c``)
    where it loads, else numba's; the same map. The C kernels run in bands from
    :data:`TV_NATIVE_PARALLEL_PIXELS` pixels in the runs, numba's from :data:`TV_PARALLEL_PIXELS`
    (the bands give the one thread's values: only the time differs).
    """
    if min(np.shape(disparity)) < 2:
        return tv_refine_reference(disparity, mask, gamma=gamma, iterations=iterations, holes=holes,
                                   hole_weight=hole_weight)
    start, disparity, mask, weight = _tv_problem(disparity, mask, holes, hole_weight)
    f = np.ascontiguousarray(disparity, dtype=np.float64)
    if gamma <= 0 or not mask.any() or iterations <= 0:
        return start.astype(np.float32)
    mu = np.ascontiguousarray(start, dtype=np.float64)
    runs = tv_runs(mask, mu, f)
    bar = mu.copy()
    py = np.zeros_like(f)
    px = np.zeros_like(f)
    mask = np.ascontiguousarray(mask)
    weight = np.ascontiguousarray(weight, dtype=np.float64)
    H = f.shape[0]
    if chosen("refine", kernel):
        if f.ndim != 2 or mask.shape != f.shape or weight.shape != f.shape or mask.dtype != np.bool_:
            raise ValueError(f"mask and hole_weight must be {f.shape} as the disparity (H, W); got {mask.shape} "
                             f"and {weight.shape}")
        W = f.shape[1]
        threads = thread_count()
        n_blocks = min(threads, H // (4 * TV_HALO_ROWS))
        if n_blocks < 2 or np.sum(runs[2] - runs[1]) < TV_NATIVE_PARALLEL_PIXELS:
            call("refine", "lfrig_tv_wavefront", f, mask, weight, H, W, float(gamma), int(iterations), mu, bar, py,
                 px, 0, H, TV_WAVE_ITERATIONS, *runs)
        else:
            call("refine", "lfrig_tv_blocks", f, mask, weight, H, W, float(gamma), int(iterations), mu, bar, py, px,
                 tv_bands(*runs, n_blocks), n_blocks, TV_HALO_ROWS, *runs, threads)
        return mu.astype(np.float32)
    n_blocks = min(numba.get_num_threads(), H // (4 * TV_HALO_ROWS))
    if n_blocks < 2 or np.sum(runs[2] - runs[1]) < TV_PARALLEL_PIXELS:
        _tv_wavefront(f, mask, weight, float(gamma), int(iterations), mu, bar, py, px, 0, H, TV_WAVE_ITERATIONS,
                      *runs)
        return mu.astype(np.float32)
    return _tv_blocks(f, mask, weight, float(gamma), int(iterations), mu, bar, py, px, tv_bands(*runs, n_blocks),
                      TV_HALO_ROWS, *runs).astype(np.float32)


def _box_sums(table: np.ndarray, ya, yb, xa, xb) -> np.ndarray:
    # Sum over rows ya..yb-1 and columns xa..xb-1 from a (H + 1, W + 1) summed-area table.
    return table[yb, xb] - table[ya, xb] - table[yb, xa] + table[ya, xa]


def _sat(image: np.ndarray) -> np.ndarray:
    out = np.zeros((image.shape[0] + 1, image.shape[1] + 1), np.float64)
    np.cumsum(np.cumsum(image, axis=0, dtype=np.float64), axis=1, out=out[1:, 1:])
    return out


def centroid_correction_reference(disparity: np.ndarray, rects: np.ndarray, *,
                                  max_residual: float, max_shift: float) -> np.ndarray:
    """Move each pixel's disparity from its window's centroid back to the pixel (readable
    reference with summed-area tables; :func:`centroid_correction` is the fast twin whose sums do
    not depend on the image's origin).

    A window matched with one disparity on a slanted surface finds (about) the disparity at the
    window's centroid. A side window's centroid is ``r / 2`` off the pixel, so on a slant of ``g``
    px/view per pixel its estimate is off by ``g r / 2``. Here the plane ``d(q) = a + g . (q - c)`` is
    fitted by least squares to ``disparity`` over the pixel's own window ``R`` (clipped to the
    image), and the pixel gets ``disparity(p) - g . (c - p)``. On a plane every pixel using the same
    window is shifted alike, so the fitted slope is the true one and the correction exact.

    Parameters
    ----------
    disparity
        ``(H, W)`` matched disparity.
    rects
        ``(H, W, 4)`` int window offsets ``(y0, y1, x0, x1)`` (inclusive, ``windows.window_rect``).
    max_residual
        No correction where the plane fits worse than this RMS (px/view): not one surface.
    max_shift
        Corrections are clipped to ``+-max_shift``.

    Returns
    -------
    ``(H, W)`` float32 corrected disparity.
    """
    d = disparity.astype(np.float64)
    H, W = d.shape
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    ya = np.clip(yy + rects[..., 0], 0, H - 1).astype(np.int64)
    yb = np.clip(yy + rects[..., 1], 0, H - 1).astype(np.int64) + 1
    xa = np.clip(xx + rects[..., 2], 0, W - 1).astype(np.int64)
    xb = np.clip(xx + rects[..., 3], 0, W - 1).astype(np.int64) + 1
    n = (yb - ya) * (xb - xa)
    cy = (ya + yb - 1) / 2.0  # centroid of the clipped rectangle
    cx = (xa + xb - 1) / 2.0
    ny, nx = yb - ya, xb - xa
    var_y = (ny ** 2 - 1) / 12.0  # variance of consecutive integers
    var_x = (nx ** 2 - 1) / 12.0
    s1 = _box_sums(_sat(d), ya, yb, xa, xb)
    sy = _box_sums(_sat(d * yy), ya, yb, xa, xb)
    sx = _box_sums(_sat(d * xx), ya, yb, xa, xb)
    s2 = _box_sums(_sat(d * d), ya, yb, xa, xb)
    mean = s1 / n
    with np.errstate(invalid="ignore", divide="ignore"):
        gy = np.where(var_y > 0, (sy / n - cy * mean) / var_y, 0.0)
        gx = np.where(var_x > 0, (sx / n - cx * mean) / var_x, 0.0)
    residual = s2 / n - mean ** 2 - gy ** 2 * var_y - gx ** 2 * var_x
    shift = gy * (cy - yy) + gx * (cx - xx)
    ok = (residual <= max_residual ** 2) & ((cy != yy) | (cx != xx))
    out = np.where(ok, d - np.clip(shift, -max_shift, max_shift), d)
    return out.astype(np.float32)


@numba.njit(cache=True, parallel=True)
def _centroid_kernel(d, rects, max_residual, max_shift, out):
    H, W = d.shape
    for y in numba.prange(H):
        for x in range(W):
            ya = max(y + rects[y, x, 0], 0)
            yb = min(y + rects[y, x, 1], H - 1) + 1
            xa = max(x + rects[y, x, 2], 0)
            xb = min(x + rects[y, x, 3], W - 1) + 1
            if ya + yb - 1 == 2 * y and xa + xb - 1 == 2 * x:  # centred on the pixel: nothing to move
                out[y, x] = d[y, x]
                continue
            s1 = 0.0
            sy = 0.0
            sx = 0.0
            s2 = 0.0
            for qy in range(ya, yb):
                for qx in range(xa, xb):
                    v = d[qy, qx]
                    s1 += v
                    sy += v * (qy - y)
                    sx += v * (qx - x)
                    s2 += v * v
            ny = yb - ya
            nx = xb - xa
            n = ny * nx
            cy = (ya + yb - 1) / 2.0 - y  # centroid relative to the pixel
            cx = (xa + xb - 1) / 2.0 - x
            var_y = (ny * ny - 1) / 12.0
            var_x = (nx * nx - 1) / 12.0
            mean = s1 / n
            gy = (sy / n - cy * mean) / var_y if var_y > 0 else 0.0
            gx = (sx / n - cx * mean) / var_x if var_x > 0 else 0.0
            residual = s2 / n - mean * mean - gy * gy * var_y - gx * gx * var_x
            value = d[y, x]
            if residual <= max_residual * max_residual and (cy != 0.0 or cx != 0.0):
                shift = gy * cy + gx * cx
                value -= min(max(shift, -max_shift), max_shift)
            out[y, x] = value


def centroid_correction(disparity: np.ndarray, rects: np.ndarray, *,
                        max_residual: float, max_shift: float, kernel: str = "auto") -> np.ndarray:
    """Move each pixel's disparity from its window's centroid back to the pixel.

    As :func:`centroid_correction_reference` (same parameters and result up to rounding), with
    each window's sums taken directly in a fixed order in coordinates relative to the pixel, so a
    pixel's result depends only on the values in its window, not on where the image starts (a
    tile computes what the whole image computes). ``kernel``: :func:`recon.native.chosen`: by
    default the C twin of :func:`_centroid_kernel` (``recon/native/refine.c``) where it loads, else
    numba's; the same map.
    """
    d = np.ascontiguousarray(disparity, dtype=np.float64)
    rects = np.ascontiguousarray(rects, dtype=np.int64)
    out = np.empty(d.shape, np.float64)
    if chosen("refine", kernel):
        if d.ndim != 2 or rects.shape != d.shape + (4,):
            raise ValueError(f"rects must be {d.shape + (4,)} for a disparity of {d.shape}; got {rects.shape}")
        if rects[..., 0::2].max(initial=0) > 0 or rects[..., 1::2].min(initial=0) < 0:
            raise ValueError("every window must hold its pixel (rects y0, x0 <= 0 <= y1, x1)")
        call("refine", "lfrig_centroid", d, d.shape[0], d.shape[1], rects, float(max_residual), float(max_shift),
             out, thread_count())
    else:
        _centroid_kernel(d, rects, float(max_residual), float(max_shift), out)
    return out.astype(np.float32)
