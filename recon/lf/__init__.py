"""The light-field vocabulary every lfrig package shares: the ground floor.

- :class:`LightField` (:mod:`recon.lf.lightfield`): views on a regular grid with what is known
  about the camera;
- the two folder layouts: the 4D Light Field Benchmark's (:mod:`recon.lf.benchmark`) and lfrig's
  capture layout (:mod:`recon.lf.capture`), read by :func:`read_lightfield`;
- ``parameters.cfg`` read and written as one inverse pair (:mod:`recon.lf.params`);
- PFM (:mod:`recon.lf.pfm`) and image files (:mod:`recon.lf.imageio`).

``rig`` and ``calib`` import from here (and from :mod:`recon.errors`, :mod:`recon.progress`), never
the other way round: see ``docs/architecture.md``.

The names above load their modules (numpy, OpenCV) on first use, not with the package: a command
that needs only :mod:`recon.lf.params`' bounds to build its flags does not pay for image decoding.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from recon.lf.benchmark import read_ground_truth
    from recon.lf.capture import write_lightfield
    from recon.lf.io import read_lightfield
    from recon.lf.lightfield import LightField

__all__ = ["LightField", "read_ground_truth", "read_lightfield", "write_lightfield"]

#: name -> the module that defines it, loaded on first use (:func:`__getattr__`).
_LAZY = {"LightField": "recon.lf.lightfield", "read_ground_truth": "recon.lf.benchmark",
         "read_lightfield": "recon.lf.io", "write_lightfield": "recon.lf.capture"}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
