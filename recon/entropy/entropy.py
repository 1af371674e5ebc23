"""Matching entropy (Eq. 1) and the window choice of Section 4.2.

For a window ``w`` of ``N`` pixels (clipped to the image)::

    E(w) = -sum_k p_k log p_k  +  alpha1 * sum_k p'_k log p'_k  +  alpha2 * sum_k p''_k log p''_k

- ``p_k``: grey-level histogram of the centre view in ``w`` (``grey_bins`` levels over ``[0, 1]``;
  256 by default, the 8-bit levels a grey histogram of the paper's data has),
- ``p'_k``: histogram of the initial disparity in ``w``, bins ``disparity_bin`` wide,
- ``p''_k``: grey-level histogram of the *mismatched* pixels of ``w`` (occluded-region pixels when the
  centre pixel is occluding, occluding-region pixels when it is occluded), normalised by ``N``, the
  window's pixel count, so that the term is the mismatched pixels' share of the window's grey entropy:
  it is 0 without mismatched pixels and more negative the more of them there are. (Normalising by
  their own count would make one mismatched pixel, or any number of one grey level, cost nothing.)

Natural logarithms. ``alpha2`` is ``alpha2_occlusion`` (1) for occluding and occluded pixels and
``alpha2_other`` (0) elsewhere. The window is the arg-max over the candidates: in occlusion regions
the shapes W1..W8 (1..8) at every size, elsewhere the full square (0) at every size. Ties go to the
larger window and then to the lower shape index.

The entropies of all sizes of one shape are computed incrementally: the windows of one shape are
nested, so each size only adds the ring of new pixels to the histograms and ``sum c log c`` is
updated per added pixel (``E`` then follows from ``N`` and the running sums). With ``strips`` the two strip windows of
``recon.entropy.windows`` (lfrig's extension) are offered in occlusion regions as well.
"""

from __future__ import annotations

from recon.jit import numba
import numpy as np

from recon.entropy.labels import OCCLUDED, OCCLUDING
from recon.entropy.layout import row_order
from recon.entropy.volume import SparseVolume
from recon.entropy.windows import N_SHAPES, window_rect
from recon.native import call, chosen, thread_count


def quantise_grey(image: np.ndarray, bins: int) -> np.ndarray:
    """``(H, W)`` int64 bin index of grey values in ``[0, 1]`` (``bins`` equal bins)."""
    return np.clip((image * bins).astype(np.int64), 0, bins - 1)


def quantise_disparity(d0: np.ndarray, width: float, origin: float | None = None) -> np.ndarray:
    """``(H, W)`` int64 bin index ``floor((d0 - origin) / width)``; ``origin`` defaults to
    ``min(d0)`` (bins start at 0). A tile passes the whole map's minimum so its bins are the whole
    image's bins (only differences of indices matter to the entropy, so any origin at or below the
    minimum gives the same histograms up to relabelling). Values below ``origin`` take bin 0: a
    tile's layer map can dip below the whole image's minimum in the outer rows of its halo (its
    median sees other neighbours there), beyond the reach of the tile's core."""
    origin = float(np.nanmin(d0)) if origin is None else float(origin)
    q = np.floor((d0 - origin) / width).astype(np.int64)
    return np.maximum(q, 0, out=q)


def _plogp_sum(counts: np.ndarray, n: int) -> float:
    c = counts[counts > 0].astype(np.float64)
    return float(np.sum(c / n * np.log(c / n)))


def matching_entropy_reference(grey_q: np.ndarray, disp_q: np.ndarray, labels: np.ndarray,
                               y: int, x: int, shape: int, size: int, *, alpha1: float,
                               alpha2: float) -> float:
    """Eq. 1 for one window (readable reference); arguments as in :func:`select_windows`."""
    H, W = grey_q.shape
    y0, y1, x0, x1 = window_rect(shape, size)
    ys = slice(max(y + y0, 0), min(y + y1, H - 1) + 1)
    xs = slice(max(x + x0, 0), min(x + x1, W - 1) + 1)
    g = grey_q[ys, xs].ravel()
    d = disp_q[ys, xs].ravel()
    n = g.size
    e = -_plogp_sum(np.bincount(g), n) + alpha1 * _plogp_sum(np.bincount(d), n)
    if alpha2 != 0 and labels[y, x] in (OCCLUDED, OCCLUDING):
        opposite = OCCLUDING if labels[y, x] == OCCLUDED else OCCLUDED
        mism = g[labels[ys, xs].ravel() == opposite]
        if mism.size:
            e += alpha2 * _plogp_sum(np.bincount(mism), n)
    return e


def select_windows_reference(grey_q, disp_q, labels, *, sizes, alpha1, alpha2_occlusion,
                             alpha2_other, strips=True, side_radius=None, layers=None,
                             layer_gap=None, max_size=None):
    """Arg-max of Eq. 1 per pixel (readable reference of :func:`select_windows`)."""
    H, W = grey_q.shape
    shape_map = np.zeros((H, W), np.int64)
    size_map = np.zeros((H, W), np.int64)
    best_e = np.full((H, W), -np.inf)
    n_shapes = N_SHAPES if strips else 9
    for y in range(H):
        for x in range(W):
            occl = labels[y, x] in (OCCLUDED, OCCLUDING)
            shapes = range(1, n_shapes) if occl else range(n_shapes)
            a2 = alpha2_occlusion if occl else alpha2_other
            for shape in shapes:
                for size in sizes:
                    side_ok = side_radius is not None and (size - 1) // 2 >= side_radius[y, x]
                    if not occl and shape != 0 and not side_ok:
                        continue
                    if (not occl and shape == 0 and max_size is not None and size != min(sizes)
                            and size > max_size[y, x]):
                        continue
                    if not occl and layers is not None and layer_gap is not None and not (
                            shape == 0 and size == min(sizes)):
                        y0, y1, x0, x1 = window_rect(shape, size)
                        patch = layers[max(y + y0, 0):y + y1 + 1, max(x + x0, 0):x + x1 + 1]
                        if np.any(np.abs(patch - layers[y, x]) > layer_gap):
                            continue
                    e = matching_entropy_reference(grey_q, disp_q, labels, y, x, shape, size,
                                                   alpha1=alpha1, alpha2=a2)
                    better = e > best_e[y, x] + 1e-9
                    tie = abs(e - best_e[y, x]) <= 1e-9 and size > size_map[y, x]
                    if better or tie:
                        best_e[y, x], shape_map[y, x], size_map[y, x] = e, shape, size
    return shape_map, size_map, best_e.astype(np.float32)


@numba.njit(cache=True)
def _add(counts, k, s, xlogx):
    # counts uint32 and k unsigned (a uint16 or uint32 bin): no index below is negative, so numba
    # adds no wrap-around
    c = counts[k]
    counts[k] = c + np.uint32(1)
    return s + xlogx[c + np.uint32(1)] - xlogx[c]


def ring_order(rects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The order in which :func:`select_windows` adds the pixels of one shape's nested windows to
    the histograms, for a window that the image does not clip.

    ``rects``: ``(n_sizes, 4)`` ``(y0, y1, x0, x1)`` inclusive offsets of the shape's windows,
    ascending. Returns ``(offsets, ends)``: ``(n, 2)`` int64 ``(dy, dx)`` of every pixel of the
    largest window, each size's new pixels row by row (top to bottom; in a row of the previous
    window, those left of it and then those right of it, else the whole row, left to right), and
    ``(n_sizes,)`` int64: the pixels up to and including size ``k`` are ``offsets[:ends[k]]``."""
    offsets: list[tuple[int, int]] = []
    ends = np.zeros(len(rects), np.int64)
    py0, py1, px0, px1 = 0, -1, 0, -1
    for k, (y0, y1, x0, x1) in enumerate(np.asarray(rects, np.int64).tolist()):
        for yy in range(y0, y1 + 1):
            if py0 <= yy <= py1:
                runs = ((x0, min(px0, x1 + 1)), (max(px1 + 1, x0), x1 + 1))
            else:
                runs = ((x0, x1 + 1), (0, 0))
            for a, b in runs:
                offsets.extend((yy, xx) for xx in range(a, b))
        ends[k] = len(offsets)
        py0, py1, px0, px1 = y0, y1, x0, x1
    return np.array(offsets, np.int64).reshape(-1, 2), ends


#: Rows of the image whose windows :func:`select_windows` scores at a time, as many as this many MiB
#: hold at 4 bytes for each of the ``K`` windows of a pixel: their values are written each row from
#: its own offset of a buffer of that size, so that only the pages they fill are touched. One buffer
#: for the whole image (924 MB at 2000x1500) stayed small only on small pages: in transparent huge
#: pages (numpy's madvise when numpy is imported before :mod:`recon`, or a system's THP set to
#: "always") every row touched its own 2 MB page and the whole buffer became resident, the window
#: selection's peak at 2000x1500 then 0.8-1.0 GB higher whenever the kernel had huge pages to give.
SELECT_BAND_MIB = 64


@numba.njit(cache=True, inline="always")
def _add_pixel(q, bins, labels_f, layers_f, hist, sg, sd, sm, m, mixed, occl, opposite,
               gap, m_centre, xlogx):
    # Pixel q (flat index) into one window's histograms and sums: the grey and disparity terms;
    # in an occlusion region the mismatched term (a pixel of the opposite label), elsewhere, with
    # a layer gap, whether the window reaches another layer. bins[3 q:3 q + 3]: the pixel's bins
    # in hist, the window's three histograms one after the other (select_windows).
    b = np.uint64(3) * q
    sg = _add(hist, bins[b], sg, xlogx)
    sd = _add(hist, bins[b + np.uint64(1)], sd, xlogx)
    if occl:
        if labels_f[q] == opposite:
            sm = _add(hist, bins[b + np.uint64(2)], sm, xlogx)
            m += 1
    elif gap >= 0 and abs(layers_f[q] - m_centre) > gap:
        mixed = True
    return sg, sd, sm, m, mixed


@numba.njit(cache=True, inline="always")
def _window_entropy(n, logn, sg, sd, sm, m, alpha1, a2):
    # Eq. 1 from a window's pixel count n (logn: its log) and running sums of c log c (module
    # docstring).
    e = (logn - sg / n) + alpha1 * (sd / n - logn)
    if m > 0:
        e += a2 * (sm / n - m / n * logn)
    return e


@numba.njit(cache=True, inline="always")
def _verdict(occl, s, k, size, cap, side_r, mixed):
    # Whether a texture or smooth pixel is offered window (s, size k) once its pixels are added:
    # 2 offered, 1 not at this size (a side window opens with the size), 0 neither at this nor
    # at any larger size (the cap and the layers only shut more). Occlusion pixels: always.
    if occl:
        return 2
    if s == 0 and k > 0 and (size > cap or mixed):
        return 0  # the square's mean disparity is off the pixel's (a crease), or it reaches
        # another layer (the smallest square stays)
    if s > 0 and mixed:
        return 0  # the window reaches another layer
    if s > 0 and (size - 1) // 2 < side_r:
        return 1  # side window not offered at this size (no layer jump within r)
    return 2


@numba.njit(cache=True, inline="always")
def _ring_windows(two, s, ring_a, ring_b, ends, base_u, bins, labels_f, layers_f, hist_a, hist_b,
                  xlogx, log_n, occl, opposite, gap, m_centre, sizes_n, cap, side_r, alpha1, a2,
                  e_k, offered):
    # The windows of shape s (and, if two, of shape s + 1, whose rings are as long) of a pixel
    # that no window of which the image clips, size by size along the rings (ring_order's pixels
    # as flat offsets from base_u): e_k[j, k], offered[j, k] for shape s + j. The two shapes'
    # sums are independent chains of additions, each in its own shape's order, interleaved so
    # that the processor overlaps them. Then the histograms are cleared. hist_a, hist_b: each
    # shape's grey, disparity and mismatched-grey histograms, one after the other (bins: each
    # pixel's three bins in them, _add_pixel).
    n_sizes = ends.shape[0]
    sga = sda = sma = 0.0
    sgb = sdb = smb = 0.0
    ma = mb = 0
    mixa = mixb = False
    act_a = True
    act_b = two
    na = nb = 0
    n = 0
    for k in range(n_sizes):
        i0 = np.uint64(n)
        n = ends[k]
        i1 = np.uint64(n)
        if act_a and act_b:
            for i in range(i0, i1):
                sga, sda, sma, ma, mixa = _add_pixel(base_u + ring_a[i], bins, labels_f, layers_f,
                                                     hist_a, sga, sda, sma, ma, mixa, occl,
                                                     opposite, gap, m_centre, xlogx)
                sgb, sdb, smb, mb, mixb = _add_pixel(base_u + ring_b[i], bins, labels_f, layers_f,
                                                     hist_b, sgb, sdb, smb, mb, mixb, occl,
                                                     opposite, gap, m_centre, xlogx)
        elif act_a:
            for i in range(i0, i1):
                sga, sda, sma, ma, mixa = _add_pixel(base_u + ring_a[i], bins, labels_f, layers_f,
                                                     hist_a, sga, sda, sma, ma, mixa, occl,
                                                     opposite, gap, m_centre, xlogx)
        elif act_b:
            for i in range(i0, i1):
                sgb, sdb, smb, mb, mixb = _add_pixel(base_u + ring_b[i], bins, labels_f, layers_f,
                                                     hist_b, sgb, sdb, smb, mb, mixb, occl,
                                                     opposite, gap, m_centre, xlogx)
        offered[0, k] = offered[1, k] = False
        if act_a:
            na = n
            v = _verdict(occl, s, k, sizes_n[k], cap, side_r, mixa)
            act_a = v > 0
            if v == 2:
                offered[0, k] = True
                e_k[0, k] = _window_entropy(n, log_n[n], sga, sda, sma, ma, alpha1, a2)
        if act_b:
            nb = n
            v = _verdict(occl, s + 1, k, sizes_n[k], cap, side_r, mixb)
            act_b = v > 0
            if v == 2:
                offered[1, k] = True
                e_k[1, k] = _window_entropy(n, log_n[n], sgb, sdb, smb, mb, alpha1, a2)
    _clear_ring(hist_a, ring_a, na, base_u, bins)
    if two:
        _clear_ring(hist_b, ring_b, nb, base_u, bins)


@numba.njit(cache=True)
def _clear_ring(hist, ring, n, base_u, bins):
    # The histograms of a window of n ring pixels back to 0: whole where that is at most twice
    # the stores (contiguous counts), else at the bins of its pixels.
    if hist.shape[0] <= 6 * n:
        hist[:] = 0
    else:
        for i in range(np.uint64(n)):
            b = np.uint64(3) * (base_u + ring[i])
            hist[bins[b]] = 0
            hist[bins[b + np.uint64(1)]] = 0
            hist[bins[b + np.uint64(2)]] = 0


@numba.njit(cache=True, inline="always")
def _clipped_windows(y, x, rects_s, s, bins, labels_f, layers_f, hist, xlogx, log_n, occl,
                     opposite, gap, m_centre, sizes_n, cap, side_r, alpha1, a2, H, W, e_k, offered):
    # The windows of shape s of a pixel near the border, clipped to the image: each size's new
    # pixels row by row left to right (in a row of the previous window, those left of it and
    # those right of it), the order of ring_order, so the sums of _ring_windows bit for bit.
    n_sizes = rects_s.shape[0]
    sg = sd = sm = 0.0
    n = m = 0
    mixed = False
    py0 = px0 = 0
    py1 = px1 = -1
    for k in range(n_sizes):
        ya = max(y + rects_s[k, 0], 0)
        yb = min(y + rects_s[k, 1], H - 1)
        xa = max(x + rects_s[k, 2], 0)
        xb = min(x + rects_s[k, 3], W - 1)
        for yy in range(ya, yb + 1):
            if py0 <= yy <= py1:
                runs = ((xa, min(px0, xb + 1)), (max(px1 + 1, xa), xb + 1))
            else:
                runs = ((xa, xb + 1), (0, 0))
            for run in runs:
                for xx in range(run[0], run[1]):
                    sg, sd, sm, m, mixed = _add_pixel(np.uint64(yy * W + xx), bins, labels_f, layers_f, hist,
                                                      sg, sd, sm, m, mixed, occl, opposite, gap,
                                                      m_centre, xlogx)
                    n += 1
        py0, py1, px0, px1 = ya, yb, xa, xb
        offered[0, k] = False
        v = _verdict(occl, s, k, sizes_n[k], cap, side_r, mixed)
        if v == 0:
            for kk in range(k + 1, n_sizes):
                offered[0, kk] = False
            break
        if v == 2:
            offered[0, k] = True
            e_k[0, k] = _window_entropy(n, log_n[n], sg, sd, sm, m, alpha1, a2)
    for yy in range(py0, py1 + 1):
        for xx in range(px0, px1 + 1):
            b = 3 * (yy * W + xx)
            hist[bins[b]] = 0
            hist[bins[b + 1]] = 0
            hist[bins[b + 2]] = 0


@numba.njit(cache=True, parallel=True)
def _select_kernel(bins, labels, rects, sizes_n, alpha1, a2_occl, a2_other, n_grey,
                   n_disp, xlogx, side_radius, layers, gap, max_size, order, margin, ring, ring_end,
                   paired, shape_map, size_map, best_e, all_e, dense, row_values, row_first, counts, mask):
    # Rows in ``order`` (layout.row_order: dealt round-robin to the threads; pixels near depth
    # edges try 11 shapes, elsewhere 1). A pixel at least ``margin`` from the border (its largest
    # window not clipped by the image) adds each size's new pixels from ``ring`` (ring_order's, as
    # flat offsets), two shapes at a time where ``paired[s]`` (shapes s and s + 1 have rings of
    # the same lengths): the same pixels in the same order as the clipped windows' row runs, so
    # the same sums bit for bit. Each offered window's entropy goes to ``all_e`` if ``dense``, and
    # always to the sparse volume's parts: row y's values one after the other from
    # ``row_values[(y - row_first) * W * K]`` (the rows of ``order`` from ``row_first`` on, a band
    # of them), the count per pixel in ``counts``, the bit of window k in ``mask`` (np.packbits'
    # order), in the order of the windows. The per-pixel loops index with unsigned values only
    # (uint16 or uint32 bins, uint32 counts, the ring's offsets shifted by ring_shift to uint64), so numba adds
    # no wrap-around of negative indices to their loads (a sign test and an add per load, and the
    # registers they took: backgammon 1.37 -> 0.80 s on one thread). Each pixel's three bins sit
    # together in ``bins`` and a window's three histograms in one array, and a window's log n is
    # looked up (log_n): 0.67-0.73 -> 0.58-0.65 s (least of 12 runs).
    H, W = labels.shape
    n_shapes = rects.shape[0]
    n_sizes = rects.shape[1]
    r_max = (sizes_n[n_sizes - 1] - 1) // 2
    labels_f = labels.ravel()
    layers_f = layers.ravel()
    K = n_shapes * n_sizes
    ring_shift = r_max * W + r_max  # ring holds offsets + ring_shift (unsigned)
    log_n = np.zeros(xlogx.shape[0])  # log of a window's pixel count, as np.log(n) there
    for n in range(1, xlogx.shape[0]):
        log_n[n] = np.log(n)
    for jr in numba.prange(order.shape[0]):
        y = order[jr]
        row_n = (y - row_first) * W * K
        hist_a = np.zeros(2 * n_grey + n_disp, np.uint32)
        hist_b = np.zeros(2 * n_grey + n_disp, np.uint32)
        e_k = np.empty((2, n_sizes))
        offered = np.zeros((2, n_sizes), np.bool_)
        for x in range(W):
            lab = labels[y, x]
            occl = lab == 0 or lab == 1
            opposite = 1 if lab == 0 else 0
            a2 = a2_occl if occl else a2_other
            s_last = n_shapes if (occl or side_radius[y, x] <= r_max) else 1
            inside = margin <= y < H - margin and margin <= x < W - margin
            base_u = np.uint64(y * W + x - ring_shift)  # >= 0 where inside
            m_centre = layers[y, x]
            cap = max_size[y, x]
            side_r = side_radius[y, x]
            best = -1e300
            best_shape = 0
            best_size = 0
            s = 1 if occl else 0
            while s < s_last:
                two = inside and paired[s] and s + 1 < s_last
                if inside:
                    _ring_windows(two, s, ring[s], ring[s + 1] if two else ring[s], ring_end[s], base_u, bins,
                                  labels_f, layers_f, hist_a, hist_b, xlogx, log_n, occl, opposite, gap,
                                  m_centre, sizes_n, cap, side_r, alpha1, a2, e_k, offered)
                else:
                    _clipped_windows(y, x, rects[s], s, bins, labels_f, layers_f, hist_a, xlogx, log_n, occl,
                                     opposite, gap, m_centre, sizes_n, cap, side_r, alpha1, a2, H, W, e_k, offered)
                for j in range(2 if two else 1):
                    for k in range(n_sizes):
                        if not offered[j, k]:
                            continue
                        e = e_k[j, k]
                        kk = (s + j) * n_sizes + k
                        if dense:
                            all_e[y, x, kk] = e
                        row_values[row_n] = e
                        row_n += 1
                        counts[y * W + x] += 1
                        mask[y, x, kk >> 3] |= np.uint8(0x80 >> (kk & 7))
                        if e > best + 1e-9 or (abs(e - best) <= 1e-9 and sizes_n[k] > best_size):
                            best = e
                            best_shape = s + j
                            best_size = sizes_n[k]
                s += 2 if two else 1
            shape_map[y, x] = best_shape
            size_map[y, x] = best_size
            best_e[y, x] = best


def _ring_margin(sizes: tuple[int, ...]) -> int:
    # pixels this far from the border sum their windows along ring_order (none clipped)
    return (max(sizes) - 1) // 2


def select_windows(grey_q: np.ndarray, disp_q: np.ndarray, labels: np.ndarray, *,
                   sizes: tuple[int, ...], alpha1: float, alpha2_occlusion: float,
                   alpha2_other: float, strips: bool = True,
                   side_radius: np.ndarray | None = None, layers: np.ndarray | None = None,
                   layer_gap: float | None = None, max_size: np.ndarray | None = None,
                   return_all: bool | str = False, kernel: str = "auto"):
    """Window of largest matching entropy per pixel (compiled: the C twin of the kernel,
    ``recon/native/select.c``, where it loads, else numba's; ``kernel``: :func:`recon.native.chosen`).

    Parameters
    ----------
    grey_q
        ``(H, W)`` int grey-level bin of the centre view (:func:`quantise_grey`).
    disp_q
        ``(H, W)`` int initial-disparity bin (:func:`quantise_disparity`).
    labels
        ``(H, W)`` region labels (``recon.entropy.regions``).
    sizes
        Window sizes (odd), ascending.
    alpha1, alpha2_occlusion, alpha2_other
        Weights of Eq. 1 (``alpha2`` in occlusion regions and elsewhere).
    strips
        Also offer the strip windows (shapes 9, 10).
    side_radius
        ``(H, W)`` int, for texture and smooth pixels: the side windows (and strips) are offered at
        the sizes whose half-width ``(size - 1) // 2`` is at least this (e.g. the chessboard distance
        to the nearest jump of the layer map: only where the square would straddle the jump).
        ``None``: never (the paper: the square only in texture and smooth regions); 0: always.
    layers, layer_gap
        ``(H, W)`` layer map and gap: if given, texture and smooth pixels are not offered windows
        that reach a pixel of another layer (``|M(q) - M(p)| > layer_gap``), except the smallest
        square, which is always offered.
    max_size
        ``(H, W)`` int: texture and smooth pixels are not offered squares larger than this (the
        smallest square stays), e.g. :func:`recon.entropy.windows.curvature_size_cap`. ``None``: no
        cap.

    Returns
    -------
    ``(shape_map, size_map, entropy)``: ``(H, W)`` int64, int64, float32; with ``return_all``
    also the entropy of every window ``k = shape * len(sizes) + size_index`` (``K = 11 *
    len(sizes)`` windows with ``strips``, else ``9 * len(sizes)``), ``-inf`` for the windows not
    offered: ``return_all=True`` an ``(H, W, K)`` float32 array, ``return_all="sparse"`` the
    same as a :class:`recon.entropy.volume.SparseVolume` (what ``SparseVolume.pack`` makes of the
    dense array, bit for bit, without the dense array).
    """
    sizes = tuple(sorted(int(s) for s in sizes))
    H, W = grey_q.shape
    n_shapes = N_SHAPES if strips else 9
    rects = np.array([[window_rect(s, z) for z in sizes] for s in range(n_shapes)], np.int64)
    rings = [ring_order(r) for r in rects]
    shift = (max(sizes) - 1) // 2 * (W + 1)  # the kernel's ring_shift
    ring = np.zeros((n_shapes, max(len(o) for o, _ in rings)), np.uint64)
    for s, (offsets, _) in enumerate(rings):  # flat offsets, shifted to be >= 0
        ring[s, :len(offsets)] = offsets[:, 0] * W + offsets[:, 1] + shift
    ring_end = np.array([ends for _, ends in rings], np.int64)
    # shapes 1 and 2, 3 and 4, ...: the two half windows or quadrants of a side, rings alike long
    paired = np.array([s % 2 == 1 and s + 1 < n_shapes and np.array_equal(ring_end[s], ring_end[s + 1])
                       for s in range(n_shapes)], np.bool_)
    if grey_q.min(initial=0) < 0 or disp_q.min(initial=0) < 0:
        raise ValueError("grey_q and disp_q must be bin indices >= 0 (quantise_grey, quantise_disparity "
                         "with an origin at or below the map's minimum)")
    n_grey = int(grey_q.max()) + 1
    n_disp = int(disp_q.max()) + 1
    native = chosen("select", kernel)
    # each pixel's bins in a window's histograms, one array of three parts: grey, disparity and
    # mismatched grey, 16 bits each where the histograms' 2 n_grey + n_disp bins allow (6 bytes a
    # pixel instead of 12: the rows a window reads are half as many cache lines); the C kernel takes
    # the first two (4 bytes a pixel, read in one load) and adds n_grey + n_disp to the grey bin
    bins = np.empty((H * W, 2 if native else 3), np.uint16 if 2 * n_grey + n_disp <= 2 ** 16 else np.uint32)
    bins[:, 0] = grey_q.ravel()
    bins[:, 1] = disp_q.ravel() + n_grey
    if not native:
        bins[:, 2] = bins[:, 0] + (n_grey + n_disp)
    c = np.arange(max(sizes) ** 2 + 2, dtype=np.float64)
    xlogx = np.where(c > 0, c * np.log(np.maximum(c, 1)), 0.0)
    shape_map = np.zeros((H, W), np.int64)
    size_map = np.zeros((H, W), np.int64)
    best_e = np.zeros((H, W), np.float32)
    K = n_shapes * len(sizes)
    if return_all not in (False, True, "sparse"):
        raise ValueError(f"return_all must be False, True or 'sparse', got {return_all!r}")
    dense = return_all is True
    all_e = np.full((H, W, K) if dense else (0, 0, 0), -np.inf, np.float32)
    start = np.zeros(H * W + 1, np.int64)  # the kernel counts each pixel's values in start[1:]
    mask = np.zeros((H, W, (K + 7) // 8), np.uint8)
    if side_radius is None:
        side_radius = np.full((H, W), np.iinfo(np.int64).max // 2, np.int64)
    maps = (bins.ravel(), np.ascontiguousarray(labels, np.uint8), rects,
            np.array(sizes, np.int64), float(alpha1), float(alpha2_occlusion),
            float(alpha2_other), n_grey, n_disp, xlogx,
            np.ascontiguousarray(np.broadcast_to(side_radius, (H, W)), np.int64),
            np.zeros((H, W), np.float32) if layers is None else np.ascontiguousarray(layers, np.float32),
            -1.0 if layer_gap is None or layers is None else float(layer_gap),
            np.full((H, W), max(sizes), np.int64) if max_size is None
            else np.ascontiguousarray(np.broadcast_to(max_size, (H, W)), np.int64))
    band = max(1, min(H, int(SELECT_BAND_MIB * 2 ** 20 // (W * K * 4))))
    counts = start[1:]
    sparse = return_all == "sparse"
    # the bands' values, in one buffer: each band's rows written from the packed values' end on, a row
    # from its own offset (only the pages its values fill are touched), then packed down to the end;
    # at last the buffer is shrunk in place (realloc) to the packed values. No block grown (realloc
    # copied it) nor filled with zeros (ndarray.resize's), no page touched beyond the packed values and
    # one band: on backgammon the Python side 26 -> 10 ms, at 2000x1500 the peak 856 -> 815 MiB
    values = np.empty(H * W * K if sparse else band * W * K, np.float32)
    end = 0
    c_maps = ()  # the C kernel's arguments before the rows: maps, with the bins' width and the lengths
    if native:
        if maps[1].shape != (H, W) or maps[11].shape != (H, W):
            raise ValueError(f"labels and layers must be {H}x{W} as grey_q; got {maps[1].shape} and "
                             f"{maps[11].shape}")
        c_maps = (maps[0], int(bins.dtype == np.uint32), maps[1], H, W, rects, n_shapes, len(sizes), *maps[3:10],
                  xlogx.size, *maps[10:])
        threads = thread_count()
    for y0 in range(0, H, band):
        n = min(band, H - y0)
        row_values = values[end:end + n * W * K]
        if native:  # the C kernel deals the rows to its threads round-robin, as row_order does to numba's
            call("select", "lfrig_select", *c_maps, np.arange(y0, y0 + n, dtype=np.int64), n, _ring_margin(sizes),
                 ring, ring.shape[1], ring_end, paired, shape_map, size_map, best_e, all_e, int(dense), row_values,
                 y0, counts, mask, threads)
        else:
            _select_kernel(*maps, y0 + row_order(n), _ring_margin(sizes), ring, ring_end, paired, shape_map,
                           size_map, best_e, all_e, dense, row_values, y0, counts, mask)
        if sparse:
            per_row = counts[y0 * W:(y0 + n) * W].reshape(n, W).sum(axis=1)
            for i, m in enumerate(per_row.tolist()):  # row i's values down to end, at most i W K on
                values[end:end + m] = row_values[i * W * K:i * W * K + m]
                end += m
        del row_values
    if dense:
        return shape_map, size_map, best_e, all_e
    if sparse:
        del maps, c_maps, bins  # not alive beside the volume's offsets
        values.resize(end, refcheck=False)  # shrunk in place (realloc), the pages beyond given back
        np.cumsum(counts, out=counts)
        return shape_map, size_map, best_e, SparseVolume((H, W, K), float(-np.inf), mask, start, values)
    return shape_map, size_map, best_e
