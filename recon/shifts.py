"""The views a plane sweep matches and the shifts at which it samples them, split into whole pixels
and fractions (plain numpy; :mod:`recon.costvolume` and :mod:`recon.sweep` share them)."""

from __future__ import annotations

import numpy as np


def view_offsets(grid_shape: tuple[int, int], views: np.ndarray | None = None) -> np.ndarray:
    """``(N, 2)`` float64 ``(u - u0, v - v0)`` of the views to match (all but the centre by default).

    ``views`` is an optional ``(N, 2)`` integer array of ``(u, v)`` grid positions to use instead.
    """
    rows, cols = grid_shape
    u0, v0 = rows // 2, cols // 2
    if views is None:
        views = np.array([(u, v) for u in range(rows) for v in range(cols) if (u, v) != (u0, v0)])
    views = np.asarray(views, dtype=np.int64).reshape(-1, 2)
    return (views - np.array([u0, v0])).astype(np.float64)


def split_shift(shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A shift in pixels as its integer part (floor, int64) and its fraction in ``[0, 1)`` (float32)."""
    whole = np.floor(shift)
    return whole.astype(np.int64), (shift - whole).astype(np.float32)


def shift_parts(offsets: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, ...]:
    """``(oy, fy, ox, fx)``, each ``(D, N)``: the integer parts (int64) and fractions (float32) of
    the shifts ``-(u - u0) d``, ``-(v - v0) d`` at which the ``N`` views of ``offsets`` are sampled
    for each of the ``D`` candidate disparities ``d``."""
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(candidates, dtype=np.float64).reshape(-1, 1)
    oy, fy = split_shift(-offsets[:, 0] * d)
    ox, fx = split_shift(-offsets[:, 1] * d)
    return oy, fy, ox, fx
