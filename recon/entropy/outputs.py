"""Files that show why the estimator did what it did (written next to ``disparity.pfm``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.entropy.estimate import EntropyResult
from recon.entropy.regions import REGION_COLOURS
from recon.entropy.windows import N_SHAPES
from recon.errors import ReconError
from recon.lf.imageio import write_png
from recon.lf.pfm import write_pfm

#: One colour per window shape (RGB): grey square, then W1..W8 and the two strips.
SHAPE_COLOURS = np.array([
    (128, 128, 128), (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200),
    (245, 130, 48), (145, 30, 180), (70, 240, 240), (240, 50, 230), (255, 255, 255), (0, 0, 0),
], np.uint8)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    try:
        write_png(path, np.ascontiguousarray(rgb))
    except OSError as error:
        raise ReconError(f"{path}: cannot write the image ({error.strerror}); check that the folder is writable") from None


def region_image(labels: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB in the paper's colours: occluding red, occluded blue, texture yellow,
    smooth green."""
    return REGION_COLOURS[np.asarray(labels, np.intp)]


def write_outputs(result: EntropyResult, out_dir: str | Path) -> list[Path]:
    """Write the intermediate maps of ``result`` into ``out_dir`` (created if needed).

    Files: ``regions.png`` (paper colours) and ``regions.npy`` (labels 0..3); ``window_size.png``
    (grey level = size / 15 * 255) and ``window_size.npy``; ``window_shape.png`` (one colour per shape,
    ``SHAPE_COLOURS``) and ``window_shape.npy`` (0 square, 1..8 = W1..W8, 9/10 strips);
    ``view_set.npy``; ``initial_disparity.pfm``, ``matched_disparity.pfm`` (before TV) and
    ``refined_disparity.pfm``; ``holes.png`` (white: black holes, filled from their surroundings
    by the TV refinement). Returns the paths written.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ReconError(f"{out}: cannot create the output folder ({error.strerror})") from None
    written: list[Path] = []

    def npy(name: str, array: np.ndarray) -> None:
        np.save(out / name, array)
        written.append(out / name)

    def png(name: str, rgb: np.ndarray) -> None:
        _write_png(out / name, rgb)
        written.append(out / name)

    def pfm(name: str, array: np.ndarray) -> None:
        write_pfm(out / name, array.astype(np.float32))
        written.append(out / name)

    png("regions.png", region_image(result.labels))
    npy("regions.npy", result.labels.astype(np.uint8))
    biggest = max(int(result.window_size.max()), 1)
    png("window_size.png", (result.window_size.astype(np.float32) / biggest * 255).astype(np.uint8))
    npy("window_size.npy", result.window_size.astype(np.uint8))
    png("window_shape.png", SHAPE_COLOURS[np.clip(result.window_shape, 0, N_SHAPES - 1)])
    npy("window_shape.npy", result.window_shape.astype(np.uint8))
    npy("view_set.npy", result.view_set.astype(np.uint8))
    pfm("initial_disparity.pfm", result.initial_disparity)
    pfm("matched_disparity.pfm", result.matched_disparity)
    pfm("refined_disparity.pfm", result.disparity)
    holes = result.info.get("holes") if result.info else None
    if holes is not None:  # black holes: filled by the TV refinement without a data term
        png("holes.png", (np.asarray(holes, bool) * 255).astype(np.uint8))
    return written
