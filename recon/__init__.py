"""recon: light-field I/O, disparity estimation, depth and export."""

import os

# numba would pick its TBB threading layer when it finds a TBB (open3d's wheels bring one that is
# too old, and numba then warns and falls back). Prefer OpenMP, then numba's own work queue; a user's
# explicit NUMBA_THREADING_LAYER(_PRIORITY) still wins. numba reads this when it is first imported.
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp workqueue tbb")
