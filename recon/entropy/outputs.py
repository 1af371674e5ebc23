"""Files that show why the estimator did what it did (written next to ``disparity.pfm``; their names
are :mod:`recon.result`'s)."""

from __future__ import annotations

import io
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
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
#: Threads that make and write the maps of :func:`write_outputs` at once.
WRITERS = 4


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
    :mod:`recon.entropy.confidence`). Returns the paths, in the order above.

    The files are made and written by :data:`WRITERS` threads at once: OpenCV's PNG encoder and the
    disk's syncs (each file is synced, :func:`recon.lf.imageio.write_bytes_atomic`) run without the
    GIL. The first failure is raised once every write has ended.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ReconError(f"{out}: cannot create the output folder ({error.strerror})") from None

    def npy(array: np.ndarray) -> Callable[[Path], object]:
        def write(path: Path) -> None:
            buffer = io.BytesIO()
            np.save(buffer, array)
            write_bytes_atomic(path, buffer.getvalue())
        return write

    def png(draw: Callable[[], np.ndarray]) -> Callable[[Path], object]:
        return lambda path: write_bytes_atomic(path, encode_png(np.ascontiguousarray(draw())))

    def pfm(array: np.ndarray) -> Callable[[Path], object]:
        return lambda path: write_pfm(path, array.astype(np.float32))

    biggest = max(int(result.window_size.max()), 1)
    holes = result.info.get("holes") if result.info else None
    files = {
        REGIONS_PNG: png(lambda: region_image(result.labels)),
        REGIONS_NPY: npy(result.labels.astype(np.uint8)),
        WINDOW_SIZE_PNG: png(lambda: (result.window_size.astype(np.float32) / biggest * 255).astype(np.uint8)),
        WINDOW_SIZE_NPY: npy(result.window_size.astype(np.uint8)),
        WINDOW_SHAPE_PNG: png(lambda: SHAPE_COLOURS[np.clip(result.window_shape, 0, N_SHAPES - 1)]),
        WINDOW_SHAPE_NPY: npy(result.window_shape.astype(np.uint8)),
        VIEW_SET_NPY: npy(result.view_set.astype(np.uint8)),
        INITIAL_DISPARITY_PFM: pfm(result.initial_disparity),
        MATCHED_DISPARITY_PFM: pfm(result.matched_disparity),
        REFINED_DISPARITY_PFM: pfm(result.disparity),
    }
    if result.confidence is not None:  # 0..1, white = sure (recon.entropy.confidence)
        files[CONFIDENCE_PFM] = pfm(result.confidence)
        files[CONFIDENCE_PNG] = png(lambda: (np.clip(result.confidence, 0, 1) * 255).astype(np.uint8))
    if holes is not None:  # black holes: filled by the TV refinement without a data term
        files[HOLES_PNG] = png(lambda: (np.asarray(holes, bool) * 255).astype(np.uint8))
    with ThreadPoolExecutor(max_workers=WRITERS, thread_name_prefix="lfrig-maps") as pool:
        writes = [pool.submit(write, out / name) for name, write in files.items()]
    for write in writes:
        write.result()
    return [out / name for name in files]
