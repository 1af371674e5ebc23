"""Scale-out on a Dask cluster (``docs/scale-out.md``).

- :mod:`recon.scale.cluster`: a local cluster sized to the machine, or a scheduler by address.
- :mod:`recon.scale.batch`: many captures, one task each (reconstruct + export), skip what is done.
- :mod:`recon.scale.tiles`: one large light field as tiles of the centre view with a halo, stitched.

Importing this package does not import dask; the modules do, when they are used.
"""

from __future__ import annotations

from recon.errors import ReconError


class ScaleError(ReconError):
    """A cluster cannot be reached or used, or a batch/tile request is inconsistent."""
