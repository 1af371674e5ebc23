"""Visibility-aware boundary decision after matching: is a pixel beside a depth jump on the near
surface or on the one behind? (``docs/entropy-method.md``, "Boundaries").

Why. A window matched with one disparity fattens the near surface: a background pixel one pixel from
a foreground edge gets the foreground's disparity, because every window that reaches onto the
foreground fits it and the only windows that stay on the background see it through fewer views.
Eq. 5 weighs every pixel of a window alike, so the pixel's own evidence is drowned. Backgammon's
slits: ~4 000 background pixels on the slits' rims and tips carry the foreground's disparity (84 %
of its squared error).

Which pixels: those of the matched map ``m`` whose value lies more than ``jump`` above the least of
their 3x3 neighbourhood. Their *far* hypothesis is that least value ``d_f``, kept only where at least
``support`` pixels of the 5x5 neighbourhood are within :data:`SUPPORT_TOLERANCE` of it (a surface
behind, not an outlier of the map). The views that would see the pixel at ``d_f`` are found by
marching its ray through the occluder map (``m`` grey-eroded by 3x3, so that the one-pixel rim in
question does not hide it): a view is lost where a pixel ``q = p + (du, dv) s`` (``q != p``) of the
occluder map is nearer than ``d_f + s - LANDING_PX / max(|du|, |dv|)``.

The pixel takes ``d_f`` (and keeps its value otherwise) when, with at least :data:`MIN_VIEWS` views
seeing it there, either

- *the view test*: over those views, the mean absolute difference between its own centre grey value
  and the views at ``d_f`` is lower than at the best near value ``m(p) + k 0.1``
  (``|k 0.1| <= NEAR_WIDTH``; the matched value may itself be off by a few tenths) by more than
  ``confidence`` standard errors of noise (``confidence * sigma / sqrt(n)``), and the centre view
  does not contradict it (:data:`CENTRE_FRACTION`: where the neighbours on both sides differ, the
  pixel's grey value is nearer the far one's); or
- *the mix test* (``mix > 0``): its grey value ``c`` holds less than ``mix`` of the near surface,
  ``alpha = (c - B) / (F - B) < mix`` with ``B`` the far surface's grey value at the pixel (the
  median of the views at ``d_f``: the very point behind, unmixed) and ``F`` the near neighbour's
  (with ``mix_extrapolate``: carried on linearly to the pixel from two pixels inside), where the two
  differ by ``mix_contrast`` noise sigmas and each surface is even beside the pixel
  (:data:`UNIFORMITY`). An anti-aliased rim pixel mixes both surfaces and matches neither; the truth
  is the surface at its centre, which is the far one when ``alpha < 0.5``. The default 0.4 leaves a
  margin; without the extrapolation shading at a curved silhouette (occlusion-v1's post) reads as
  mixing and 0.3 was the most that did not cost elsewhere.

Only the near-to-far direction is tested: the window bias this corrects runs that way (flipping to
the near value as well made every dev scene worse).

:func:`snap_boundaries` (numba kernel over the tested pixels) and :func:`snap_boundaries_reference`
(readable loops, ``scipy.ndimage.map_coordinates`` for the samples) give the same map.
"""

from __future__ import annotations

import math

from recon.jit import numba
import numpy as np

from recon.entropy.regions import box_extreme
from recon.native import call, chosen, thread_count

#: A 5x5 neighbour supports the far value when it lies within this of it (px/view).
SUPPORT_TOLERANCE = 0.1
#: The near hypothesis is searched over ``m(p) + k * NEAR_STEP`` with ``|k NEAR_STEP| <= NEAR_WIDTH``.
NEAR_WIDTH = 0.4
NEAR_STEP = 0.1
#: Fewest views that must see ``p`` at the far value for the test to count.
MIN_VIEWS = 9
#: An occluder that lands within this many pixels before ``p``'s spot counts as hiding it.
LANDING_PX = 0.5


def near_offsets() -> np.ndarray:
    """The near hypothesis' offsets from the matched value, 0 first (float64)."""
    k = int(round(NEAR_WIDTH / NEAR_STEP))
    ks = [0] + [j for i in range(1, k + 1) for j in (-i, i)]
    return np.array(ks, np.float64) * NEAR_STEP


def ray_reach_px(disparity_range: tuple[float, float], grid_shape: tuple[int, int]) -> int:
    """How far (pixels, chessboard) a visibility ray of :func:`snap_boundaries` can run from its
    pixel: the largest view offset times the range, widened by 1 px/view (a matched value may lie a
    few tenths outside the range: the centroid correction moves it) and the landing margin."""
    U, V = grid_shape
    a = max(U // 2, V // 2, U - 1 - U // 2, V - 1 - V // 2)
    lo, hi = disparity_range
    return int(math.ceil(a * (hi - lo + 1.0) + LANDING_PX + 1))


def boundary_reach_px(disparity_range: tuple[float, float], grid_shape: tuple[int, int]) -> int:
    """Pixels around a pixel that :func:`snap_boundaries` reads of the matched map (for a tile's
    halo): its rays (:func:`ray_reach_px`) and their bound, plus the 3x3 erosion of the occluder map
    and the 5x5 support."""
    return ray_reach_px(disparity_range, grid_shape) + 3


def boundary_candidates(matched: np.ndarray, *, jump: float, support: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ys, xs, far)`` of the pixels :func:`snap_boundaries` tests: value more than ``jump`` above
    the 3x3 minimum, that minimum supported by ``support`` pixels of the 5x5 neighbourhood."""
    m = np.asarray(matched, np.float32)
    low = box_extreme(m, 3, maximum=False)
    ys, xs = np.nonzero(m - low > jump)
    far = low[ys, xs]
    padded = np.pad(m, 2, mode="edge")
    row = padded.shape[1]
    flat, at = padded.ravel(), (ys + 2) * row + (xs + 2)  # each neighbour by its offset: one take, not a 2-D index
    count = np.zeros(ys.size, np.int64)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            count += np.abs(flat[at + (dy * row + dx)] - far) <= SUPPORT_TOLERANCE
    keep = count >= support
    return ys[keep], xs[keep], far[keep]


def occluder_map(matched: np.ndarray) -> np.ndarray:
    """The map the visibility rays march through: ``matched`` grey-eroded by 3x3 (float32)."""
    return box_extreme(np.asarray(matched, np.float32), 3, maximum=False)  # scipy's grey_erosion: the 3x3 minimum


def _check(gray: np.ndarray, matched: np.ndarray) -> None:
    if gray.ndim != 4 or gray.shape[2:] != matched.shape:
        raise ValueError(f"snap_boundaries needs (U, V, H, W) grey views over the matched map's "
                         f"{matched.shape}; got views of shape {gray.shape}")


#: The mix test needs each surface even beside the pixel: grey spread at most this fraction of the
#: two surfaces' contrast (the near one between one and two pixels inside, the far one between the
#: views' median and the centre view's far neighbour). Uneven texture reads as mixing by chance.
UNIFORMITY = 0.5
#: The view test's flip also needs the centre view not to contradict it: where the near and far
#: neighbours differ by the mix contrast, the pixel's grey value must lie less than this fraction
#: of the way from the far neighbour's to the near neighbour's.
CENTRE_FRACTION = 0.5
#: The 8 neighbours in the order :func:`rim_evidence` breaks ties (first least value wins).
NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def rim_evidence(gray: np.ndarray, matched: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                 far: np.ndarray, far_grey: np.ndarray, *, jump: float, min_contrast: float,
                 extrapolate: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """What the centre view says about each tested pixel ``(ys, xs)`` (1-D arrays), with ``c`` its
    grey value, ``F`` the grey value of the neighbour opposite its farthest 8-neighbour (the near
    surface one pixel inside; it must itself be near, ``matched > far + jump``), ``N`` that farthest
    neighbour's grey value and ``B = far_grey`` the far surface's grey value at the pixel (median
    over the views that see it there):

    - ``alpha = (c - B) / (F - B)``: the near surface's fraction in ``c`` (a mix of the two), where
      ``|F - B| >= min_contrast`` and both surfaces are even (:data:`UNIFORMITY`); else ``inf``;
    - ``centre = (c - N) / (F - N)``: the same from the centre view alone, where
      ``|F - N| >= min_contrast``; else ``-inf`` (no objection).

    ``extrapolate``: ``F`` is the near surface's grey value carried on linearly to the pixel
    (``2 F - F2``, ``F2`` two pixels inside): a silhouette whose shading changes towards the rim is
    not read as a mix.
    """
    m = np.asarray(matched, np.float32)
    H, W = m.shape
    grey = gray[gray.shape[0] // 2, gray.shape[1] // 2]
    offsets = np.array(NEIGHBOURS, np.int64)
    values = np.stack([m[np.clip(ys + dy, 0, H - 1), np.clip(xs + dx, 0, W - 1)]
                       for dy, dx in offsets], axis=1)
    away = offsets[np.argmin(values, axis=1)]

    def at(k: int) -> tuple[np.ndarray, np.ndarray]:  # k pixels towards the far neighbour
        return np.clip(ys + k * away[:, 0], 0, H - 1), np.clip(xs + k * away[:, 1], 0, W - 1)

    iy, ix = ys - away[:, 0], xs - away[:, 1]
    near_inside = ((iy >= 0) & (iy < H) & (ix >= 0) & (ix < W)
                   & (m[at(-1)] > np.asarray(far, np.float32) + jump))
    c = grey[ys, xs].astype(np.float64)
    F = grey[at(-1)].astype(np.float64)
    if extrapolate:  # the near surface's grey carried on to the pixel (a shading gradient)
        F = 2 * F - grey[at(-2)]
    N = grey[at(1)].astype(np.float64)
    B = np.asarray(far_grey, np.float64)
    spread = np.maximum(np.abs(F - grey[at(-2)]), np.abs(N - B))
    mixed = (near_inside & np.isfinite(B) & (np.abs(F - B) >= min_contrast)
             & (spread <= UNIFORMITY * np.abs(F - B)))
    seen = near_inside & (np.abs(F - N) >= min_contrast)
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.where(mixed, (c - B) / np.where(mixed, F - B, 1.0), np.inf)
        centre = np.where(seen, (c - N) / np.where(seen, F - N, 1.0), -np.inf)
    return alpha, centre


def snap_boundaries_reference(gray: np.ndarray, matched: np.ndarray, *, noise_sigma: float,
                              disparity_range: tuple[float, float], jump: float, support: int,
                              confidence: float, mix: float = 0.0, mix_contrast: float = 12.0,
                              mix_extrapolate: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Readable twin of :func:`snap_boundaries` (module docstring); slow, for tests."""
    gray = np.asarray(gray, np.float32)
    m = np.asarray(matched, np.float32)
    _check(gray, m)
    U, V, H, W = gray.shape
    u0, v0 = U // 2, V // 2
    occ = occluder_map(m)
    reach = ray_reach_px(disparity_range, (U, V))
    ys, xs, far = boundary_candidates(m, jump=jump, support=support)
    offsets = near_offsets()
    out = m.copy()
    changed = np.zeros((H, W), bool)
    far_grey = np.full(ys.size, np.nan)
    enough = np.zeros(ys.size, bool)
    view_test = np.zeros(ys.size, bool)
    for i, (y, x, df) in enumerate(zip(ys, xs, far.astype(np.float64))):
        centre = float(gray[u0, v0, y, x])
        far_sum, near_sums, n, samples = 0.0, np.zeros(offsets.size), 0, []
        far_line, near_line, n_line = 0.0, np.zeros(offsets.size), 0  # views in line: du or dv 0
        for u in range(U):
            for v in range(V):
                du, dv = u - u0, v - v0
                if (du, dv) == (0, 0) or _hidden_reference(
                        occ, y, x, du, dv, df, disparity_range[1], reach):
                    continue
                n += 1
                samples.append(_sample(gray[u, v], y - du * df, x - dv * df))
                far_sum += abs(samples[-1] - centre)
                in_line = du == 0 or dv == 0
                if in_line:
                    n_line += 1
                    far_line += abs(samples[-1] - centre)
                for j, off in enumerate(offsets):
                    d = float(m[y, x]) + off
                    e = abs(_sample(gray[u, v], y - du * d, x - dv * d) - centre)
                    near_sums[j] += e
                    near_line[j] += e if in_line else 0.0
        if samples:
            far_grey[i] = np.median(samples)
        enough[i] = n >= MIN_VIEWS
        view_test[i] = (enough[i] and (near_sums.min() - far_sum) / n
                        > confidence * noise_sigma / math.sqrt(n)
                        and (n_line == 0 or near_line.min() > far_line))
    alpha, centre = rim_evidence(gray, m, ys, xs, far, far_grey, jump=jump,
                                 min_contrast=mix_contrast * noise_sigma,
                                 extrapolate=mix_extrapolate)
    for i in range(ys.size):
        flip = view_test[i] and centre[i] < CENTRE_FRACTION
        if not flip and mix > 0 and enough[i] and alpha[i] < mix:
            flip = True
        if flip:
            out[ys[i], xs[i]] = far[i]
            changed[ys[i], xs[i]] = True
    return out, changed


def _sample(image: np.ndarray, y: float, x: float) -> float:
    # bilinear, coordinates clamped to the image (as recon.entropy.cost._bilinear)
    from scipy import ndimage

    return float(ndimage.map_coordinates(image.astype(np.float64), [[y], [x]], order=1, mode="nearest")[0])


def _hidden_reference(occ: np.ndarray, y: int, x: int, du: int, dv: int, d: float,
                      nearest: float, reach: int) -> bool:
    # Is the pixel at disparity d hidden in view (du, dv)? March q = p + (du, dv) s, s in steps of
    # half a pixel, while an occluder could still be near enough (occ <= nearest) and within reach.
    H, W = occ.shape
    a = max(abs(du), abs(dv))
    ds, tol = 0.5 / a, LANDING_PX / a
    k = 1
    while k * ds <= min(nearest - d + tol + ds, reach / a):
        s = k * ds
        qy, qx = int(np.floor(y + du * s + 0.5)), int(np.floor(x + dv * s + 0.5))
        if not (0 <= qy < H and 0 <= qx < W):
            return False
        if (qy, qx) != (y, x) and occ[qy, qx] > d + s - tol:
            return True
        k += 1
    return False


@numba.njit(cache=True)
def _bilinear(image, y, x):
    H, W = image.shape
    y = min(max(y, 0.0), H - 1.0)
    x = min(max(x, 0.0), W - 1.0)
    y0 = min(int(np.floor(y)), H - 2) if H > 1 else 0
    x0 = min(int(np.floor(x)), W - 2) if W > 1 else 0
    fy = y - y0
    fx = x - x0
    y1 = min(y0 + 1, H - 1)
    x1 = min(x0 + 1, W - 1)
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x1])
            + fy * ((1 - fx) * image[y1, x0] + fx * image[y1, x1]))


@numba.njit(cache=True)
def _hidden(occ, y, x, du, dv, d, nearest, landing_px, reach):
    H, W = occ.shape
    a = max(abs(du), abs(dv))
    ds = 0.5 / a
    tol = landing_px / a
    bound = min(nearest - d + tol + ds, reach / a)
    k = 1
    while k * ds <= bound:
        s = k * ds
        qy = int(np.floor(y + du * s + 0.5))
        qx = int(np.floor(x + dv * s + 0.5))
        if qy < 0 or qy >= H or qx < 0 or qx >= W:
            return False
        if not (qy == y and qx == x) and occ[qy, qx] > d + s - tol:
            return True
        k += 1
    return False


@numba.njit(cache=True, parallel=True)
def _snap_kernel(gray, m, occ, top, reach, ys, xs, far, offsets, landing_px, min_views,
                 threshold, out_far_mean, out_near_mean, out_views, out_far_median, out_line):
    U, V = gray.shape[0], gray.shape[1]
    u0 = U // 2
    v0 = V // 2
    n_off = offsets.size
    for i in numba.prange(ys.size):
        y = ys[i]
        x = xs[i]
        df = far[i]
        nearest = top[y, x]  # no occluder on any of its rays is nearer
        dm = np.float64(m[y, x])
        centre = np.float64(gray[u0, v0, y, x])
        seen = np.zeros((U, V), np.bool_)
        samples = np.empty(U * V, np.float64)
        n = 0
        far_sum = 0.0
        near0 = 0.0
        n_line = 0
        far_line = 0.0
        near_line0 = 0.0
        for u in range(U):
            for v in range(V):
                du = u - u0
                dv = v - v0
                if du == 0 and dv == 0:
                    continue
                if _hidden(occ, y, x, du, dv, df, nearest, landing_px, reach):
                    continue
                seen[u, v] = True
                sample = _bilinear(gray[u, v], y - du * df, x - dv * df)
                samples[n] = sample
                n += 1
                far_sum += abs(sample - centre)
                e = abs(_bilinear(gray[u, v], y - du * dm, x - dv * dm) - centre)
                near0 += e
                if du == 0 or dv == 0:
                    n_line += 1
                    far_line += abs(sample - centre)
                    near_line0 += e
        out_views[i] = n
        out_far_mean[i] = far_sum / max(n, 1)
        out_far_median[i] = np.median(samples[:n]) if n > 0 else np.nan
        best = near0
        best_line = near_line0
        # the other near offsets only where the far value already wins against m(p) itself
        if n >= min_views and (near0 - far_sum) / n > threshold / math.sqrt(n):
            for j in range(1, n_off):
                d = dm + offsets[j]
                s = 0.0
                s_line = 0.0
                for u in range(U):
                    for v in range(V):
                        if seen[u, v]:
                            e = abs(_bilinear(gray[u, v], y - (u - u0) * d, x - (v - v0) * d) - centre)
                            s += e
                            if u == u0 or v == v0:
                                s_line += e
                if s < best:
                    best = s
                if s_line < best_line:
                    best_line = s_line
        out_near_mean[i] = best / max(n, 1)
        out_line[i] = (best_line - far_line) / n_line if n_line > 0 else np.nan


def snap_boundaries(gray: np.ndarray, matched: np.ndarray, *, noise_sigma: float,
                    disparity_range: tuple[float, float], jump: float, support: int,
                    confidence: float,
                    mix: float = 0.0, mix_contrast: float = 12.0,
                    mix_extrapolate: bool = False, kernel: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """The matched map with the pixels beside a depth jump that their own grey value places on the
    surface behind given that surface's value (module docstring). The tested pixels' view test runs
    compiled: the C twin of the kernel, ``recon/native/regions.c``, where it loads, else numba's
    (``kernel``: :func:`recon.native.chosen`).

    Parameters
    ----------
    gray
        ``(U, V, H, W)`` float32 grey views, ``[0, 1]``.
    matched
        ``(H, W)`` matched disparity (px/view).
    noise_sigma
        The centre view's noise sigma, ``[0, 1]`` grey units.
    disparity_range
        The searched ``(min, max)``: a ray is marched until nothing within it can be nearer
        (constants of the whole image, so that a tile decides as the whole image does;
        :func:`boundary_reach_px`).
    jump, support, confidence, mix, mix_contrast, mix_extrapolate
        :class:`recon.entropy.EntropyOptions` ``boundary_jump``, ``boundary_support``,
        ``boundary_confidence``, ``boundary_mix``, ``boundary_mix_contrast``,
        ``boundary_mix_extrapolate`` (``mix=0``: no mix test).

    Returns
    -------
    ``(snapped float32 (H, W), changed bool (H, W))``.
    """
    native = chosen("regions", kernel)
    gray = np.ascontiguousarray(gray, np.float32)
    m = np.ascontiguousarray(matched, np.float32)
    _check(gray, m)
    ys, xs, far = boundary_candidates(m, jump=jump, support=support)
    out = m.copy()
    changed = np.zeros(m.shape, bool)
    if ys.size == 0:
        return out, changed
    n = ys.size
    far_mean, near_mean, far_median = np.empty(n), np.empty(n), np.empty(n)
    views = np.empty(n, np.int64)
    line = np.empty(n)
    threshold = confidence * noise_sigma
    occ = occluder_map(m)
    # the nearest occluder any ray of a pixel can meet: bounds its march (exact: nothing farther
    # on the ray can hide it)
    reach = ray_reach_px(disparity_range, gray.shape[:2])
    top = np.minimum(box_extreme(occ, 2 * reach + 1, maximum=True),
                     np.float32(disparity_range[1]))
    ys64, xs64, far64 = ys.astype(np.int64), xs.astype(np.int64), far.astype(np.float64)
    if native:
        U, V, H, W = gray.shape
        offsets = near_offsets()
        call("regions", "lfrig_snap", gray, U, V, H, W, m, occ, top, int(reach), ys64, xs64, far64, n, offsets,
             offsets.size, float(LANDING_PX), int(MIN_VIEWS), float(threshold), far_mean, near_mean, views,
             far_median, line, thread_count())
    else:
        _snap_kernel(gray, m, occ, top, reach, ys64, xs64, far64, near_offsets(), LANDING_PX,
                     MIN_VIEWS, threshold, far_mean, near_mean, views, far_median, line)
    enough = views >= MIN_VIEWS
    flip = enough & (near_mean - far_mean > threshold / np.sqrt(np.maximum(views, 1)))
    alpha, centre = rim_evidence(gray, m, ys, xs, far, far_median, jump=jump,
                                 min_contrast=mix_contrast * noise_sigma,
                                 extrapolate=mix_extrapolate)
    flip &= (centre < CENTRE_FRACTION) & ~(line <= 0)  # NaN: no view in line sees it
    if mix > 0:
        flip |= enough & (alpha < mix)
    out[ys[flip], xs[flip]] = far[flip]
    changed[ys[flip], xs[flip]] = True
    return out, changed
