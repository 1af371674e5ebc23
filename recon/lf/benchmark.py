"""The 4D Light Field Benchmark's folder layout, read.

``input_Cam000.png`` ... ``input_CamNNN.png`` row-major (``NNN = u * V + v``), optional
``parameters.cfg`` (:mod:`recon.lf.params`) and ``gt_disp_lowres.pfm`` (the centre view's ground-truth
disparity). :func:`recon.lf.read_lightfield` tells this layout from lfrig's capture layout.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from recon.errors import LightFieldFormatError
from recon.lf.imageio import read_view_grid
from recon.lf.lightfield import LightField
from recon.lf.params import camera_from_parameters, check_camera_fits, read_parameters
from recon.lf.pfm import read_pfm

BENCHMARK_VIEW = re.compile(r"^input_Cam(\d{3})\.png$")
GROUND_TRUTH = "gt_disp_lowres.pfm"


def read_benchmark(path: str | os.PathLike, *, grey: bool = False, decode: bool = True) -> LightField:
    """Read a folder in the 4D Light Field Benchmark layout (``grey``: the views as ``float32``
    luminance; ``decode=False``: no pixels, :func:`recon.lf.read_lightfield`).

    The grid size comes from ``parameters.cfg`` (``num_cams_x``, ``num_cams_y``) when present, else
    the number of views must be a square. ``metadata["ground_truth"]`` names ``gt_disp_lowres.pfm``
    when the folder has one; ``metadata["views_sha256"]`` maps each view's file name to the SHA-256 of
    the bytes read (:func:`recon.provenance.input_identity` takes them instead of reading the views again).
    """
    path = Path(path)
    numbered: dict[int, Path] = {}
    for p in path.iterdir():
        m = BENCHMARK_VIEW.match(p.name)
        if m:
            numbered[int(m[1])] = p
    if not numbered:
        raise LightFieldFormatError(f"{path}: no input_CamNNN.png views")
    num_cams, camera = None, {}
    metadata: dict = {"layout": "benchmark"}
    cfg = path / "parameters.cfg"
    if cfg.is_file():
        parameters = read_parameters(cfg)
        metadata["parameters"] = parameters
        num_cams, camera = camera_from_parameters(parameters, path=cfg)
    if num_cams is not None:
        rows, cols = num_cams
    else:
        side = math.isqrt(max(numbered) + 1)
        if side * side != max(numbered) + 1:
            side = math.isqrt(len(numbered))
        rows = cols = side
    count = rows * cols
    extra = sorted(i for i in numbered if i >= count)
    if extra:
        raise LightFieldFormatError(
            f"{numbered[extra[0]]}: extra view, a {rows}x{cols} grid has input_Cam000 .. input_Cam{count - 1:03d}; remove it"
        )
    missing = [i for i in range(count) if i not in numbered]
    if missing:
        names = ", ".join(f"input_Cam{i:03d}.png" for i in missing[:3]) + (" ..." if len(missing) > 3 else "")
        raise LightFieldFormatError(f"{path}: {len(missing)} of {count} views missing ({names})")
    digests: dict[Path, str] = {}
    views, centre = read_view_grid([numbered[i] for i in range(count)], (rows, cols), grey=grey, digests=digests,
                                   decode=decode)
    if cfg.is_file():
        check_camera_fits(camera, metadata["parameters"], grid=(rows, cols), image_shape=views.shape[2:4], path=cfg)
    if (path / GROUND_TRUTH).is_file():
        metadata["ground_truth"] = str(path / GROUND_TRUTH)
    metadata["views_sha256"] = {p.name: digest for p, digest in digests.items()}  # for the input's identity
    return LightField(views=views, metadata=metadata, source=path, stored_centre=centre, **camera)


def ground_truth_path(lf: LightField) -> Path | None:
    """The ground-truth disparity file recorded for a light field, if any."""
    name = lf.metadata.get("ground_truth")
    return Path(name) if name else None


def read_ground_truth(lf: LightField) -> np.ndarray | None:
    """The ground-truth disparity of the centre view, ``(H, W)`` float32, or ``None``."""
    p = ground_truth_path(lf)
    return read_pfm(p) if p is not None else None
