"""The ``scipy.ndimage`` filters the estimator calls that :mod:`recon.entropy.regions`
(``box_extreme``: the minimum and maximum filters) and ``recon/native/confidence.c`` (the distance
to the nearest jump) do not cover, without importing ``scipy.ndimage`` (~0.1 s of Python, with
scipy's array-API layer ~0.2 s, which in ``lfrig reconstruct`` is CPU the estimate's threads lose),
each giving ``scipy.ndimage``'s bits:

- :func:`uniform_filter`, :func:`uniform_filter1d`: the C kernel of ``recon/native/filters.c``,
  scipy's own arithmetic (a float64 running sum) in its order, for images of finite values;
- :func:`chessboard_distance` (``distance_transform_cdt(..., metric="chessboard")``): OpenCV's
  distance transform, exact for this metric (an integer).

Every function takes ``kernel``: ``"auto"`` (the way above where it can be had, scipy otherwise),
``"native"`` (the same, but ``RuntimeError`` where the C library of the uniform filters is not
built), ``"scipy"`` (scipy's function, the reference the tests compare with). Only the cases the
estimator uses are handled so: 2-D images, and the values, types and modes named above; any other
goes to scipy, which gives what scipy gives.
"""

from __future__ import annotations

import cv2
import numpy as np

from recon.native import call, chosen

#: ``mode`` -> the C kernel's code (``recon/native/filters.c``).
_MODES = {"nearest": 0, "reflect": 1}


def _check_kernel(kernel: str) -> None:
    if kernel not in ("auto", "native", "scipy"):
        raise ValueError(f"kernel must be 'auto', 'native' or 'scipy'; got {kernel!r}")


def _uniform_in_c(image: np.ndarray, mode: str, kernel: str) -> bool:
    """Whether the C kernel filters ``image``: a 2-D float32 or float64 image of finite values, a
    mode it knows, and the library loaded (``kernel="native"``: ``RuntimeError`` where it is not).
    Where two NaN meet in a sum (inf - inf is one), the sign of the NaN that comes out follows the
    order of the operands, which the compiler's vector loops need not keep: scipy then."""
    if kernel == "scipy" or not chosen("filters", "native" if kernel == "native" else "auto"):
        return False
    return (image.ndim == 2 and image.dtype in (np.float32, np.float64) and mode in _MODES and image.size > 0
            and bool(np.isfinite(image).all()))


def _uniform_axis(image: np.ndarray, out: np.ndarray, size: int, axis: int, mode: str) -> None:
    H, W = image.shape
    call("filters", "lfrig_uniform", image, out, int(image.dtype == np.float64), H, W, size, axis, _MODES[mode])


def uniform_filter1d(image: np.ndarray, size: int, *, axis: int = -1, mode: str = "reflect",
                     kernel: str = "auto") -> np.ndarray:
    """``scipy.ndimage.uniform_filter1d(image, size, axis=axis, mode=mode)``: the mean of ``size``
    samples along ``axis`` (the window's centre at ``size // 2``), in the image's dtype."""
    _check_kernel(kernel)
    image = np.asarray(image)
    if size < 1 or not _uniform_in_c(image, mode, kernel) or axis not in (-2, -1, 0, 1):
        from scipy import ndimage

        return ndimage.uniform_filter1d(image, size, axis=axis, mode=mode)
    image = np.ascontiguousarray(image)
    out = np.empty_like(image)
    _uniform_axis(image, out, int(size), axis % 2, mode)
    return out


def uniform_filter(image: np.ndarray, size: int | tuple[int, int], *, mode: str = "reflect",
                   kernel: str = "auto") -> np.ndarray:
    """``scipy.ndimage.uniform_filter(image, size, mode=mode)`` of a 2-D image: the mean of the
    ``size`` box (one size, or one per axis), along the columns and then the rows, each pass
    rounded to the image's dtype as scipy's is."""
    _check_kernel(kernel)
    image = np.asarray(image)
    sizes = (size, size) if np.ndim(size) == 0 else tuple(size)
    if len(sizes) != 2 or min(sizes) < 1 or not _uniform_in_c(image, mode, kernel):
        from scipy import ndimage

        return ndimage.uniform_filter(image, size, mode=mode)
    image = np.ascontiguousarray(image)
    out = np.empty_like(image)
    sy, sx = (int(s) for s in sizes)
    if sy > 1:
        _uniform_axis(image, out, sy, 0, mode)
    else:
        out[...] = image
    if sx > 1:
        _uniform_axis(out, out, sx, 1, mode)  # in place: the kernel copies each row first
    return out


def chessboard_distance(mask: np.ndarray, *, kernel: str = "auto") -> np.ndarray:
    """``scipy.ndimage.distance_transform_cdt(mask, metric="chessboard")`` of a 2-D mask with at least
    one ``False`` pixel: int32, each ``True`` pixel's chessboard distance to the nearest ``False``
    one within the image (0 on them)."""
    _check_kernel(kernel)
    mask = np.asarray(mask, bool)
    if kernel == "scipy" or mask.ndim != 2 or mask.all():
        from scipy import ndimage

        return ndimage.distance_transform_cdt(mask, metric="chessboard")
    distance = cv2.distanceTransform(mask.view(np.uint8), cv2.DIST_C, 3)
    return distance.astype(np.int32)
