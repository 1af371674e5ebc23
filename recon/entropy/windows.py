"""The window shapes W1..W8 (Fig. 6), the sizes 3x3..15x15 and the visible-viewpoint sets (Fig. 9).

Reading (``/work/shared/paper/README.md``, ``docs/entropy-method.md``): the eight shapes are the side
windows of the ``size x size`` square that contain the centre pixel on their border: the left, right,
upper and lower half-windows and the four quadrant windows. Shape 0 is the full square, used in
textured and smooth regions where only the size is chosen.

``shape  extends to   rows        cols        visible views (du = u - u0, dv = v - v0)``

====== ============= =========== =========== ==========================================
0      everywhere    [-r, r]     [-r, r]     all
1 W1   left  (-x)    [-r, r]     [-r, 0]     dv <= 0
2 W2   right (+x)    [-r, r]     [0, r]      dv >= 0
3 W3   up    (-y)    [-r, 0]     [-r, r]     du <= 0
4 W4   down  (+y)    [0, r]      [-r, r]     du >= 0
5 W5   up-left       [-r, 0]     [-r, 0]     du <= 0 and dv <= 0
6 W6   up-right      [-r, 0]     [0, r]      du <= 0 and dv >= 0
7 W7   down-left     [0, r]      [-r, 0]     du >= 0 and dv <= 0
8 W8   down-right    [0, r]      [0, r]      du >= 0 and dv >= 0
====== ============= =========== =========== ==========================================

9      row strip  [0, 0]      [-r, r]     du == 0       (lfrig's extension)
10     col strip  [-r, r]     [0, 0]      dv == 0       (lfrig's extension)

with ``r = (size - 1) // 2``. The strips are not in the paper: a pixel seen through a gap between
two closer surfaces (above and below, or left and right) is hidden in both halves of the grid, and
only the views in line with the gap see it; its window must then lie along the gap.
Why these views: a window that extends to the left is chosen when the
occluder (closer, larger ``d``) sits to the right. In view ``(u, v)`` a point of disparity ``d``
moves by ``-dv * d`` in x (``docs/conventions.md``), so the occluder moves relative to the
background by ``-dv * (d_front - d_back)``: away from the pixel (to +x) exactly when ``dv < 0``, not
at all when ``dv == 0``. So the views that see the pixel are ``dv <= 0``: the views on the side the
window extends to. The same argument per axis gives every row; ``tests/test_entropy_windows.py``
checks it on a rendered occluder.
"""

from __future__ import annotations

import numpy as np

from recon.native import thread_count

#: Number of shapes: the full square (0), the paper's W1..W8 (1..8) and two strips (9, 10).
N_SHAPES = 11
#: The paper's shapes W1..W8.
PAPER_SHAPES = tuple(range(1, 9))
#: lfrig's extension: one-pixel-high horizontal (9) and one-pixel-wide vertical (10) strips.
STRIP_SHAPES = (9, 10)
#: Window sizes the paper searches (side of the square, pixels).
DEFAULT_SIZES = (3, 5, 7, 9, 11, 13, 15)
#: ``(dy, dx)`` direction each shape extends to; (0, 0) for the full square.
SHAPE_DIRECTIONS = np.array(
    [(0, 0), (0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1), (0, 0), (0, 0)],
    np.int64,
)
#: Names used in docs and output legends.
SHAPE_NAMES = ("square", "W1 left", "W2 right", "W3 up", "W4 down",
               "W5 up-left", "W6 up-right", "W7 down-left", "W8 down-right",
               "horizontal strip", "vertical strip")


def window_rect(shape: int, size: int) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` inclusive offsets of window ``shape`` (0..8) of side ``size`` (odd)."""
    if not 0 <= shape < N_SHAPES:
        raise ValueError(f"window shape must be 0..{N_SHAPES - 1}, got {shape}")
    if size < 1 or size % 2 == 0:
        raise ValueError(f"window size must be odd and positive, got {size}")
    r = (size - 1) // 2
    if shape == 9:
        return 0, 0, -r, r
    if shape == 10:
        return -r, r, 0, 0
    dy, dx = SHAPE_DIRECTIONS[shape]
    y0, y1 = (-r, 0) if dy < 0 else (0, r) if dy > 0 else (-r, r)
    x0, x1 = (-r, 0) if dx < 0 else (0, r) if dx > 0 else (-r, r)
    return y0, y1, x0, x1


def window_mask(shape: int, size: int) -> np.ndarray:
    """``(size, size)`` bool footprint of the window inside its square (centre at ``[r, r]``)."""
    r = (size - 1) // 2
    y0, y1, x0, x1 = window_rect(shape, size)
    mask = np.zeros((size, size), bool)
    mask[r + y0:r + y1 + 1, r + x0:r + x1 + 1] = True
    return mask


def visible_view_mask(shape: int, grid_shape: tuple[int, int]) -> np.ndarray:
    """``(U, V)`` bool: the visible-viewpoint set of ``shape`` (all views for shape 0)."""
    U, V = grid_shape
    du, dv = np.meshgrid(np.arange(U) - U // 2, np.arange(V) - V // 2, indexing="ij")
    if shape in STRIP_SHAPES:
        return du == 0 if shape == 9 else dv == 0
    sy, sx = SHAPE_DIRECTIONS[shape]
    return (du * sy >= 0) & (dv * sx >= 0)


def _set_blocks() -> np.ndarray:
    # Block b = 3 * (sign(du) + 1) + (sign(dv) + 1); a set holds a block when the block's signs pass.
    table = np.zeros((N_SHAPES, 9), bool)
    for shape in range(N_SHAPES):
        sy, sx = SHAPE_DIRECTIONS[shape]
        for su in (-1, 0, 1):
            for sv in (-1, 0, 1):
                if shape == 9:
                    ok = su == 0
                elif shape == 10:
                    ok = sv == 0
                else:
                    ok = (su * sy >= 0) and (sv * sx >= 0)
                table[shape, 3 * (su + 1) + (sv + 1)] = ok
    return table


#: ``(N_SHAPES sets, 9 blocks)`` bool: which view blocks make up the visible set of each shape.
SET_BLOCKS = _set_blocks()


def curvature_size_cap(layers: np.ndarray, sizes: tuple[int, ...], *, tolerance: float,
                       measured: np.ndarray | None = None, initial: np.ndarray | None = None,
                       noise_factor: float = 0.0, threads: int | None = None) -> np.ndarray:
    """``(H, W)`` int64: the largest of ``sizes`` up to which every square window centred on the
    pixel sees a mean layer value within ``tolerance`` (px/view) of the smallest square's mean.

    Why: a square window matched with one disparity finds about the mean disparity of the surface
    under it. On a plane that is the centre pixel's (the square is symmetric), so a slant alone does
    not bias it; where the slope changes (a ridge, a pit, a crease, a curved surface) the mean moves
    off the pixel's value by ~ slope change x radius / 4. The layer map (median of ``d0``) shows that
    change; comparing with the smallest square's mean (not the pixel's own value) keeps ``d0``'s
    per-pixel noise out. The smallest size is always allowed. ``measured`` (``(H, W)`` bool): a
    square more than a quarter of which is unmeasured is not capped (``d0`` filled into a black hole
    is an interpolation, not a measured surface: its bend says nothing about a crease, and a mean
    over the measured part alone would be off the pixel on any slant).

    ``noise_factor`` > 0 with ``initial`` (the ``d0`` the layers were made from): the tolerance is
    raised to that many times the local noise of ``d0``, ``1.4826 x`` the median of
    ``|d0 - median3(d0)|`` over the largest window (every third pixel: 25 samples; a median, so that
    edges and creases do not count as noise). Where ``d0`` is noisy (render noise on a realistic
    surface) its layer means wander without a crease, and capping there only makes the windows, and
    the matching, noisier.

    ``threads``: how many run the box filters, a size each (default
    :func:`recon.native.thread_count`; the cap is the same for any number)."""
    from recon.entropy.filters import uniform_filter
    from recon.entropy.median import median_filter_nearest

    sizes = tuple(sorted(int(s) for s in sizes))
    m = np.asarray(layers, np.float64)
    # None: every pixel measured, no square blind (the filters of a map of zeros would give zeros)
    unmeasured = (None if measured is None or np.all(measured)
                  else (~np.asarray(measured, bool)).astype(np.float64))

    def tolerance_map() -> np.ndarray:
        tol = np.full(m.shape, float(tolerance))
        if noise_factor > 0 and initial is not None:
            d0 = np.asarray(initial, np.float32)
            wander = np.abs(d0 - median_filter_nearest(d0, size=3))
            footprint = np.zeros((sizes[-1], sizes[-1]), bool)
            footprint[::3, ::3] = True
            local = 1.4826 * median_filter_nearest(wander, footprint=footprint)
            tol = np.maximum(tol, noise_factor * local)
        return tol

    def reference() -> np.ndarray:
        return uniform_filter(m, sizes[0], mode="nearest")

    def within(size: int, ref, tol) -> np.ndarray:
        """Where the ``size`` square's mean is within the tolerance of the smallest's, or blind."""
        ok = np.abs(uniform_filter(m, size, mode="nearest") - ref) <= tol
        if unmeasured is not None:
            ok |= uniform_filter(unmeasured, size, mode="nearest") > 0.25  # blind
        return ok

    threads = min(thread_count(), len(sizes)) if threads is None else int(threads)
    if threads <= 1:
        ref, tol = reference(), tolerance_map()
        oks = (within(size, ref, tol) for size in sizes[1:])
        return _cap_of(oks, sizes, m.shape)
    # the filters (scipy's and the C medians let the interpreter's lock go) a size to a thread; each
    # size's test is one map whatever the thread that makes it
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=threads) as pool:
        ref, tol = pool.submit(reference), pool.submit(tolerance_map)
        ref, tol = ref.result(), tol.result()
        oks = [pool.submit(within, size, ref, tol) for size in sizes[1:]]
        return _cap_of((ok.result() for ok in oks), sizes, m.shape)


def _cap_of(oks, sizes: tuple[int, ...], shape: tuple[int, int]) -> np.ndarray:
    """The cap of :func:`curvature_size_cap` from the tests of ``sizes[1:]`` (``oks``, in order)."""
    cap = np.full(shape, sizes[0], np.int64)
    allowed = np.ones(shape, bool)
    for size, ok in zip(sizes[1:], oks):
        allowed &= ok
        cap[allowed] = size
    return cap
