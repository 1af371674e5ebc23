"""Reading a light field from disk, in either layout lfrig knows.

- The **benchmark layout** of the 4D Light Field Benchmark (:mod:`recon.lf.benchmark`):
  ``input_Cam000.png`` ... row-major, optional ``parameters.cfg`` and ``gt_disp_lowres.pfm``.
- lfrig's **capture layout** (:mod:`recon.lf.capture`): ``manifest.jsonl``, ``views/uUU_vVV.png``,
  ``parameters.cfg``.

:func:`read_lightfield` tells them apart and returns a :class:`recon.lf.lightfield.LightField`;
:func:`recon.lf.capture.write_lightfield` writes one as a complete capture.
"""

from __future__ import annotations

import os
from pathlib import Path

from recon.errors import LightFieldFormatError
from recon.lf import capture
from recon.lf.benchmark import BENCHMARK_VIEW, read_benchmark
from recon.lf.lightfield import LightField


def read_lightfield(path: str | os.PathLike, *, verify: bool = True, grey: bool = False,
                    decode: bool = True) -> LightField:
    """Read a light-field folder in the benchmark layout or lfrig's capture layout.

    ``verify``: check each view of a capture against its journalled SHA-256
    (:func:`recon.lf.capture.read_capture`); the benchmark layout has no checksums.

    ``grey``: the views as the estimators read them, ``(U, V, H, W)`` ``float32`` luminance
    (:func:`recon.lf.lightfield.to_gray` of the stored views, bit for bit, each view converted as
    it is decoded, so the stored views are never held all at once), with the centre view as stored
    in :attr:`~recon.lf.lightfield.LightField.stored_centre`: for one estimate
    (:func:`recon.pipeline.reconstruct_to_folder`). An 8-bit RGB light field then takes 4 bytes a
    pixel instead of 3 plus the 4 of its grey views.

    ``decode=False``: everything but the pixels, for what needs only the shapes, dtype and metadata
    (``lfrig info``): the files are read and checked as for decoding (a capture's checksums with
    ``verify``, each PNG's chunks and header), but only the first view is decoded, and any other
    whose PNG header says another size, colour or bit depth; :attr:`~recon.lf.lightfield.LightField.views`
    then holds no pixels (zeros, read-only, :func:`recon.lf.imageio.read_images`).

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
    if capture.is_capture(path):
        return capture.read_capture(path, verify=verify, grey=grey, decode=decode)
    if any(BENCHMARK_VIEW.match(p.name) for p in path.iterdir()):
        return read_benchmark(path, grey=grey, decode=decode)
    raise LightFieldFormatError(
        f"{path}: no light field here (expected input_Cam000.png ... of the benchmark layout, "
        "or manifest.jsonl of an lfrig capture)"
    )
