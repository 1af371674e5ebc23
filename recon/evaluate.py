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
    if estimate.shape != gt.shape:
        raise ReconError(
            f"estimate is {estimate.shape[1]}x{estimate.shape[0]} but ground truth is {gt.shape[1]}x{gt.shape[0]}; "
            "score an estimate of the same scene at the same resolution"
        )
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
