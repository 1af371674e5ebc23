"""Files that show why the estimator did what it did (written next to ``disparity.pfm``; their names
are :mod:`recon.result`'s)."""

from __future__ import annotations

import io
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from recon.entropy.estimate import EntropyResult
from recon.entropy.labels import REGION_COLOURS
from recon.entropy.windows import N_SHAPES
from recon.errors import ReconError
from recon.lf.imageio import encode_png, write_bytes_atomic
from recon.lf.pfm import write_pfm
from recon.result import (CONFIDENCE_PFM, CONFIDENCE_PNG, HOLES_PNG, INITIAL_DISPARITY_PFM, MATCHED_DISPARITY_PFM, REFINED_DISPARITY_PFM, REGIONS_NPY,
                          REGIONS_PNG, VIEW_SET_NPY, WINDOW_SHAPE_NPY, WINDOW_SHAPE_PNG, WINDOW_SIZE_NPY, WINDOW_SIZE_PNG)

#: One colour per window shape (RGB): grey square, then W1..W8 and the two strips.
SHAPE_COLOURS = np.array([
    (128, 128, 128), (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200),
    (245, 130, 48), (145, 30, 180), (70, 240, 240), (240, 50, 230), (255, 255, 255), (0, 0, 0),
], np.uint8)


def _write_png(path: Path, encoded: Future[bytes]) -> None:
    try:
        write_bytes_atomic(path, encoded.result())
    except OSError as error:
        raise ReconError(f"{path}: cannot write the image ({error.strerror}); check that the folder is writable") from None


def region_image(labels: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB in the paper's colours: occluding red, occluded blue, texture yellow,
    smooth green."""
    return REGION_COLOURS[np.asarray(labels, np.intp)]


def write_outputs(result: EntropyResult, out_dir: str | Path) -> list[Path]:
    """Write the intermediate maps of ``result`` into ``out_dir`` (created if needed).

    Files: ``regions.png`` (paper colours) and ``regions.npy`` (labels 0..3); ``window_size.png``
    (grey level = size / largest size * 255) and ``window_size.npy``; ``window_shape.png`` (one colour per shape,
    ``SHAPE_COLOURS``) and ``window_shape.npy`` (0 square, 1..8 = W1..W8, 9/10 strips);
    ``view_set.npy``; ``initial_disparity.pfm``, ``matched_disparity.pfm`` (before TV) and
    ``refined_disparity.pfm``; ``holes.png`` (white: black holes, filled from their surroundings
    by the TV refinement); ``confidence.pfm`` and ``confidence.png`` (0..1, white = sure; see
    :mod:`recon.entropy.confidence`). Returns the paths written, in the order written.

    The PNGs are encoded in two threads while the other files are written (OpenCV's encoder runs
    without the GIL); the files are written one by one in the order above.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ReconError(f"{out}: cannot create the output folder ({error.strerror})") from None
    written: list[Path] = []

    def npy(name: str, array: np.ndarray) -> None:
        buffer = io.BytesIO()
        np.save(buffer, array)
        write_bytes_atomic(out / name, buffer.getvalue())
        written.append(out / name)

    def png(name: str) -> None:
        _write_png(out / name, encoded[name])
        written.append(out / name)

    def pfm(name: str, array: np.ndarray) -> None:
        write_pfm(out / name, array.astype(np.float32))
        written.append(out / name)

    biggest = max(int(result.window_size.max()), 1)
    figures = {
        REGIONS_PNG: lambda: region_image(result.labels),
        WINDOW_SIZE_PNG: lambda: (result.window_size.astype(np.float32) / biggest * 255).astype(np.uint8),
        WINDOW_SHAPE_PNG: lambda: SHAPE_COLOURS[np.clip(result.window_shape, 0, N_SHAPES - 1)],
    }
    if result.confidence is not None:  # 0..1, white = sure (recon.entropy.confidence)
        figures[CONFIDENCE_PNG] = lambda: (np.clip(result.confidence, 0, 1) * 255).astype(np.uint8)
    holes = result.info.get("holes") if result.info else None
    if holes is not None:  # black holes: filled by the TV refinement without a data term
        figures[HOLES_PNG] = lambda: (np.asarray(holes, bool) * 255).astype(np.uint8)
    with ThreadPoolExecutor(max_workers=2) as pool:
        encoded = {name: pool.submit(lambda draw: encode_png(np.ascontiguousarray(draw())), draw)
                   for name, draw in figures.items()}
        png(REGIONS_PNG)
        npy(REGIONS_NPY, result.labels.astype(np.uint8))
        png(WINDOW_SIZE_PNG)
        npy(WINDOW_SIZE_NPY, result.window_size.astype(np.uint8))
        png(WINDOW_SHAPE_PNG)
        npy(WINDOW_SHAPE_NPY, result.window_shape.astype(np.uint8))
        npy(VIEW_SET_NPY, result.view_set.astype(np.uint8))
        pfm(INITIAL_DISPARITY_PFM, result.initial_disparity)
        pfm(MATCHED_DISPARITY_PFM, result.matched_disparity)
        pfm(REFINED_DISPARITY_PFM, result.disparity)
        if result.confidence is not None:
            pfm(CONFIDENCE_PFM, result.confidence)
            png(CONFIDENCE_PNG)
        if holes is not None:
            png(HOLES_PNG)
    return written
