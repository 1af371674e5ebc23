"""recon: light-field I/O, disparity estimation, depth and export."""

import os

# numba would pick its TBB threading layer when it finds a TBB (open3d's wheels bring one that is
# too old, and numba then warns and falls back). Prefer OpenMP, then numba's own work queue; a user's
# explicit NUMBA_THREADING_LAYER(_PRIORITY) still wins. numba reads this when it is first imported.
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp workqueue tbb")
# OpenMP threads that wait for work sleep instead of spinning (libgomp's default spins first): on a
# shared machine a spinning thread holds a core the other thread of the same parallel region needs,
# and every region then waits for a time slice. Backgammon, 2 threads, load 2-3: the estimate took
# 12.6 s with spinning and 5.7 s without (docs/entropy-results.md, "Speed and memory"). Read by
# libgomp when numba first loads it; a user's explicit OMP_WAIT_POLICY still wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# numpy asks the kernel for transparent huge pages for every large array (madvise); where THP
# defragmentation is "madvise" (this lab's machines), the first touch of such an array waits for the
# kernel to compact memory: 80 MB took 180 ms of CPU instead of 41, and a fresh backgammon estimate
# ~0.7 s more CPU, with no kernel faster for the huge pages (docs/entropy-results.md, "Speed and
# memory"). Read when numpy is first imported (so only if recon comes first); a user's explicit value wins.
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
# OpenCV refuses to decode an image of more pixels than this before allocating it (its own default is
# 1 Gpx, 3 GiB for 8-bit RGB): lfrig's limit, recon.lf.imageio.MAX_IMAGE_PIXELS (64 Mpx). PNGs are
# checked by lfrig from their header; this covers the other formats `lfrig import` reads. Read when
# OpenCV is loaded (so only if recon comes first); a user's explicit value wins.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(1 << 26))
