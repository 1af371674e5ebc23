"""Scoring a disparity map against ground truth as the 4D Light Field Benchmark does.

On the low-resolution ground truth, a border of 15 pixels is left out on every side and pixels where
either map is not finite are skipped:

- ``mse_x100 = 100 * mean((estimate - gt)^2)``
- ``badpix_t = 100 * share of pixels with |estimate - gt| > t`` for t = 0.07, 0.03, 0.01
"""

from __future__ import annotations

import numpy as np

from recon.errors import ReconError

BORDER = 15
THRESHOLDS = (0.07, 0.03, 0.01)


def score(
    estimate: np.ndarray, gt: np.ndarray, *, border: int = BORDER, mask: np.ndarray | None = None
) -> dict[str, float]:
    """MSE x100 and BadPix(0.07 / 0.03 / 0.01) in percent.

    Parameters
    ----------
    estimate, gt
        ``(H, W)`` disparity maps in pixels per view step, same sign convention.
    border
        Pixels left out on every side.
    mask
        Optional ``(H, W)`` bool: score only where True (e.g. one region type).

    Returns
    -------
    ``{"mse_x100", "badpix_0.07", "badpix_0.03", "badpix_0.01", "pixels"}``; the scores are NaN when
    no pixel is left to score.
    """
    estimate, gt = np.asarray(estimate), np.asarray(gt)
    for name, array in (("estimate", estimate), ("ground truth", gt)):
        if array.ndim != 2:
            raise ReconError(f"{name} is {describe_map(array)}; a disparity map has one channel (H, W)")
    if estimate.shape != gt.shape:
        raise ReconError(
            f"estimate is {describe_map(estimate)} but ground truth is {describe_map(gt)}; "
            "score an estimate of the same scene at the same resolution"
        )
    if isinstance(border, bool) or not isinstance(border, (int, np.integer)) or border < 0:
        raise ReconError(f"border = {border!r}: give a whole number of pixels >= 0")
    if mask is not None and np.shape(mask) != gt.shape:
        raise ReconError(f"mask is {np.shape(mask)} but the maps are {gt.shape}")
    if 2 * border >= min(gt.shape):
        raise ReconError(f"border of {border} pixels leaves nothing of a {gt.shape[1]}x{gt.shape[0]} map")
    keep = np.zeros(gt.shape, dtype=bool)
    keep[border : gt.shape[0] - border, border : gt.shape[1] - border] = True
    keep &= np.isfinite(estimate) & np.isfinite(gt)
    if mask is not None:
        keep &= mask
    error = (estimate[keep].astype(np.float64) - gt[keep].astype(np.float64))
    result: dict[str, float] = {"pixels": int(keep.sum())}
    if error.size == 0:
        result["mse_x100"] = float("nan")
        result.update({f"badpix_{t}": float("nan") for t in THRESHOLDS})
        return result
    result["mse_x100"] = float(100.0 * np.mean(error**2))
    for t in THRESHOLDS:
        result[f"badpix_{t}"] = float(100.0 * np.mean(np.abs(error) > t))
    return result


def describe_map(array: np.ndarray) -> str:
    """``"64x48"`` for a one-channel map, ``"64x48 with 3 channels"`` otherwise (width first)."""
    if array.ndim < 2:
        return f"an array of shape {array.shape}"
    text = f"{array.shape[1]}x{array.shape[0]}"
    if array.ndim == 3:
        text += f" with {array.shape[2]} channels"
    elif array.ndim > 3:
        text += f" (shape {array.shape})"
    return text


def score_files(estimate_path, gt_path, *, border: int = BORDER) -> dict[str, float]:
    """:func:`score` of two PFM files, for ``lfrig evaluate``.

    Raises
    ------
    ReconError
        Naming the file: unreadable, not one channel, sizes differ, or no pixel has a finite value in
        both maps (the scores would be NaN: nothing was compared).
    """
    from recon.lf.pfm import read_pfm

    estimate, gt = read_pfm(estimate_path), read_pfm(gt_path)
    for path, array in ((estimate_path, estimate), (gt_path, gt)):
        if array.ndim != 2:
            raise ReconError(f"{path}: is {describe_map(array)}; a disparity map has one channel")
    if estimate.shape != gt.shape:
        raise ReconError(f"{estimate_path} is {describe_map(estimate)} but {gt_path} is {describe_map(gt)}; "
                         "score an estimate of the same scene at the same resolution")
    result = score(estimate, gt, border=border)
    if result["pixels"] == 0:
        empty = [str(p) for p, a in ((estimate_path, estimate), (gt_path, gt)) if not np.isfinite(a).any()]
        why = (f"{' and '.join(empty)} has no finite value" if empty
               else f"no pixel inside the {border}-pixel border is finite in both maps")
        raise ReconError(f"nothing to score: {why}; check that the files are a disparity estimate and its truth")
    return result
