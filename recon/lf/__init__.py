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

from typing import TYPE_CHECKING

from recon.lazy import lazy_names

if TYPE_CHECKING:
    from recon.lf.benchmark import read_ground_truth
    from recon.lf.capture import write_lightfield
    from recon.lf.io import read_lightfield
    from recon.lf.lightfield import LightField

__all__ = ["LightField", "read_ground_truth", "read_lightfield", "write_lightfield"]

__getattr__ = lazy_names(__name__, {"LightField": "recon.lf.lightfield", "read_ground_truth": "recon.lf.benchmark",
                                    "read_lightfield": "recon.lf.io", "write_lightfield": "recon.lf.capture"})
