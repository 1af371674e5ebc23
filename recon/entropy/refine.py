"""TV refinement of Eq. 13 in smooth regions only.

    mu = argmin_mu  sum_{smooth} (mu - d*)^2 + gamma * sum |grad mu|

with ``mu = d*`` held fixed outside the smooth region (so edges, which the paper keeps out of the
refinement, stay sharp, and the smooth region is tied to its surroundings through the TV term).
``|grad mu|`` is the isotropic TV with forward differences (pixel units). Solved with the first-order
primal-dual algorithm of Chambolle and Pock (2011); the pixel-wise prox of the data term is exact,
and the fixed pixels are a projection, so the iteration converges to the constrained minimum.
"""

from __future__ import annotations

import numpy as np


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


def tv_refine(disparity: np.ndarray, mask: np.ndarray, *, gamma: float,
              iterations: int) -> np.ndarray:
    """Minimise Eq. 13 over the pixels of ``mask``; the others keep their value.

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

    Returns
    -------
    ``(H, W)`` float32 refined disparity ``mu``.
    """
    f = disparity.astype(np.float64)
    mask = np.asarray(mask, bool)
    if gamma <= 0 or not mask.any() or iterations <= 0:
        return disparity.astype(np.float32)
    tau = sigma = 1.0 / np.sqrt(8.0)
    mu = f.copy()
    bar = f.copy()
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
        new = np.where(mask, (v + 2 * tau * f) / (1 + 2 * tau), f)
        bar = 2 * new - mu
        mu = new
    return mu.astype(np.float32)
