"""Reading light fields from disk, in either layout lfrig knows.

- The **benchmark layout** of the 4D Light Field Benchmark: ``input_Cam000.png`` ...
  ``input_CamNNN.png`` row-major (``NNN = u * V + v``), optional ``parameters.cfg`` and
  ``gt_disp_lowres.pfm``.
- lfrig's **capture layout** (``rig.layout``): ``manifest.jsonl``, ``views/uUU_vVV.png``,
  ``parameters.cfg``.

:func:`read_lightfield` tells them apart and returns a :class:`recon.lightfield.LightField`.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from recon.errors import LightFieldFormatError
from recon.imageio import read_images
from recon.lightfield import LightField
from recon.params import camera_from_parameters, read_parameters
from recon.pfm import read_pfm

_BENCHMARK_VIEW = re.compile(r"^input_Cam(\d{3})\.png$")
GROUND_TRUTH = "gt_disp_lowres.pfm"


def read_lightfield(path: str | os.PathLike) -> LightField:
    """Read a light-field folder in the benchmark layout or lfrig's capture layout.

    Raises
    ------
    LightFieldFormatError
        Naming the folder or file and what is wrong: not a folder, no views, missing or extra views,
        views of mixed sizes, an unreadable image, a broken ``parameters.cfg``.
    """
    path = Path(path)
    if not path.exists():
        raise LightFieldFormatError(f"{path}: no such folder")
    if not path.is_dir():
        raise LightFieldFormatError(f"{path}: not a folder; pass the folder that holds the views")
    from rig import layout  # the capture layout belongs to rig, which writes it

    if layout.is_capture(path):
        return layout.read_capture(path)
    if any(_BENCHMARK_VIEW.match(p.name) for p in path.iterdir()):
        return read_benchmark(path)
    raise LightFieldFormatError(
        f"{path}: no light field here (expected input_Cam000.png ... of the benchmark layout, "
        "or manifest.jsonl of an lfrig capture)"
    )


def read_benchmark(path: str | os.PathLike) -> LightField:
    """Read a folder in the 4D Light Field Benchmark layout.

    The grid size comes from ``parameters.cfg`` (``num_cams_x``, ``num_cams_y``) when present, else
    the number of views must be a square. ``metadata["ground_truth"]`` names ``gt_disp_lowres.pfm``
    when the folder has one.
    """
    path = Path(path)
    numbered: dict[int, Path] = {}
    for p in path.iterdir():
        m = _BENCHMARK_VIEW.match(p.name)
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
    images = read_images([numbered[i] for i in range(count)])
    views = images.reshape((rows, cols) + images.shape[1:])
    if (path / GROUND_TRUTH).is_file():
        metadata["ground_truth"] = str(path / GROUND_TRUTH)
    return LightField(views=views, metadata=metadata, source=path, **camera)


def ground_truth_path(lf: LightField) -> Path | None:
    """The ground-truth disparity file recorded for a light field, if any."""
    name = lf.metadata.get("ground_truth")
    return Path(name) if name else None


def read_ground_truth(lf: LightField) -> np.ndarray | None:
    """The ground-truth disparity of the centre view, ``(H, W)`` float32, or ``None``."""
    p = ground_truth_path(lf)
    return read_pfm(p) if p is not None else None


def write_lightfield(path: str | os.PathLike, lf: LightField, *, header_extra: dict | None = None) -> None:
    """Write a light field in lfrig's capture layout (see :func:`rig.layout.write_lightfield`)."""
    from rig import layout

    layout.write_lightfield(path, lf, header_extra=header_extra)
