"""Point clouds and meshes from a depth map, as plain numpy arrays.

Frame (``docs/conventions.md``): the camera frame of the centre view, x right, y down, z forward
along the optical axis, in mm. A pixel ``(y, x)`` (row, column; pixel centres at integer
coordinates) with depth ``Z`` (mm along ``z``) is the point::

    X = (x - cx) * Z / focal_px,   Y = (y - cy) * Z / focal_px,   Z

where ``(cx, cy)`` is the principal point in pixels (x first, as in a camera matrix ``K``), by
default the image centre ``((W - 1) / 2, (H - 1) / 2)``.

Pixels without a trustworthy depth (``NaN``, ``inf``, ``<= 0``, or ``False`` in an optional mask)
are left out. Two neighbouring pixels are *connected* when both are kept, their depths differ by at
most ``max_relative_jump`` times the nearer one and the disparity (``focal_px / Z``) does not break
between them against its local slope (:func:`surface_breaks`); the mesh has triangles only over
connected pixels, so a foreground object and the background behind it are not joined by a skin even
where the estimate ramps over a few pixels, while a slanted plane stays whole. Normals are unit
vectors that face the camera (``n . P < 0``).

Nothing here imports open3d; :mod:`recon.export` turns these arrays into files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.lf.lightfield import to_float

#: Default for ``max_relative_jump``: neighbours whose depths differ by more than 5 % of the nearer
#: one are not joined. At 1 m with ``focal_px = 1000`` a surface must be seen within about 1.1 deg of
#: grazing before one of its own steps is that large, while disparity noise of 0.05 px at an
#: effective disparity of 2 px moves depth by 2.5 %.
MAX_RELATIVE_JUMP = 0.05
#: Default for ``max_step_footprints``: neighbours whose step, beyond the local slope of the surface,
#: is more than this many pixel footprints (the width one pixel covers at that depth, ``Z / focal_px``)
#: are not joined (:func:`surface_breaks`). A surface would have to turn by atan(8) = 83 deg within a
#: few pixels to make such a step; at 1 m with ``focal_px = 3645`` (the simulated rig) it is 2.2 mm.
MAX_STEP_FOOTPRINTS = 8.0
#: The threshold is at least this many times the map's own noise (:func:`step_noise`).
STEP_NOISE_FACTOR = 8.0
#: Spans (links, odd) a jump is measured over: one link (a step or a spike), and the widths over which
#: an estimate's edge ramps.
JUMP_SPANS_LINKS = (1, 3, 5)
#: Pixels beyond each end of the span over which the local slope on either side is measured (each
#: base gives a candidate slope per side). Two: one pixel beyond a ramp that is one link wider than
#: the span would still be on the ramp and excuse it.
SLOPE_BASES_PX = (2,)


@dataclass
class PointCloud:
    """Coloured points with normals.

    Attributes
    ----------
    points_mm
        ``(N, 3)`` ``float64``, camera frame, mm.
    normals
        ``(N, 3)`` ``float64`` unit vectors facing the camera.
    colours
        ``(N, 3)`` ``float32`` RGB in ``[0, 1]``, or ``None`` when no image was given.
    pixels
        ``(N, 2)`` ``int64`` ``(y, x)`` of the centre-view pixel each point comes from.
    """

    points_mm: np.ndarray
    normals: np.ndarray
    colours: np.ndarray | None
    pixels: np.ndarray

    def __len__(self) -> int:
        return int(self.points_mm.shape[0])


@dataclass
class Mesh:
    """A triangle mesh over the depth grid.

    Attributes
    ----------
    vertices_mm, normals, colours, pixels
        As in :class:`PointCloud`, one row per vertex (only pixels used by some triangle).
        ``pixels`` is ``None`` for a mesh not made on the pixel grid (Poisson reconstruction).
    triangles
        ``(M, 3)`` ``int64`` vertex indices, wound counter-clockwise as seen from the camera, so the
        right-hand-rule face normal points towards the camera.
    """

    vertices_mm: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    colours: np.ndarray | None
    pixels: np.ndarray | None


# --------------------------------------------------------------------------------------------------
# pixels to points
# --------------------------------------------------------------------------------------------------


def _principal_point(shape: tuple[int, int], principal_point_px) -> tuple[float, float]:
    height, width = shape
    if principal_point_px is None:
        return (width - 1) / 2.0, (height - 1) / 2.0
    cx, cy = (float(c) for c in principal_point_px)
    return cx, cy


def _check_depth(depth_mm, focal_px: float) -> np.ndarray:
    depth = np.asarray(depth_mm, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_mm must be an (H, W) map; got shape {depth.shape}")
    if not (np.isfinite(focal_px) and focal_px > 0):
        raise ValueError(f"focal_px must be a positive number of pixels; got {focal_px!r}")
    return depth


def depth_to_points(depth_mm, *, focal_px: float, principal_point_px=None) -> np.ndarray:
    """Back-project every pixel of a depth map into the camera frame.

    Parameters
    ----------
    depth_mm
        ``(H, W)`` depth along the optical axis in mm.
    focal_px
        Focal length in pixels (square pixels).
    principal_point_px
        ``(cx, cy)`` in pixels, x first; default the image centre ``((W - 1) / 2, (H - 1) / 2)``.

    Returns
    -------
    ``(H, W, 3)`` ``float64`` ``(X, Y, Z)`` in mm; ``NaN`` rows where the depth is not finite.
    """
    depth = _check_depth(depth_mm, focal_px)
    cx, cy = _principal_point(depth.shape, principal_point_px)
    ys, xs = np.indices(depth.shape, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.stack([(xs - cx) * depth / focal_px, (ys - cy) * depth / focal_px, depth], axis=-1)


def valid_depth(depth_mm, *, mask=None) -> np.ndarray:
    """``(H, W)`` bool: depth finite and positive, and ``mask`` (if given, ``(H, W)``) true."""
    depth = np.asarray(depth_mm, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != depth.shape:
            raise ValueError(f"mask must have the depth map's shape {depth.shape}; got {mask.shape}")
        valid &= mask
    return valid


def _connected(za: np.ndarray, zb: np.ndarray, va: np.ndarray, vb: np.ndarray, max_relative_jump: float) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return va & vb & (np.abs(za - zb) <= max_relative_jump * np.minimum(za, zb))


def jump_residual(disparity_px, *, axis: int, span_links: int = 3,
                  slope_bases_px: tuple[int, ...] = SLOPE_BASES_PX) -> np.ndarray:
    """How far the disparity jumps at each link along ``axis``, beyond what the local slope explains.

    For the link between pixels ``i`` and ``i + 1`` (along ``axis``) with ``h = span_links // 2``, the
    change over the span ``J = d[i + 1 + h] - d[i - h]`` (``span_links`` links, centred on the link) is
    compared with the slopes measured just outside the span on either side, ``sL = (d[i - h] -
    d[i - h - b]) / b`` and ``sR = (d[i + 1 + h + b] - d[i + 1 + h]) / b`` for each base ``b`` of
    ``slope_bases_px``; with ``S`` the set of these candidate slopes and 0 (flat)::

        span_residual = min over s' in S of |J - span_links * s'|
        own_residual  = min over s' in S of |s - s'|          s = d[i + 1] - d[i]
        residual      = min(span_residual, span_links * own_residual)

    A plane, however steep, has ``J = span_links * sL = span_links * sR``: residual 0 (up to noise).
    A step that the estimate spreads over 2-3 pixels has flat sides, so the links of the ramp have
    (most of) the whole step as residual, although each one-pixel step is small; the second term
    keeps the flat links beside a sharp step (``s = 0``) connected. Missing pixels (``NaN``):
    a side without a slope offers slope 0 instead; without the span's ends, the link alone is the
    span (``J = d[i + 1] - d[i]``, one link); with no slope on either side, a span of more than one
    link gives ``NaN`` (it cannot tell a ramp from a steep plane there).

    Parameters
    ----------
    disparity_px
        ``(H, W)`` disparity (pixels per view step), or anything affine in it such as
        ``focal_px / Z``; ``NaN`` where there is none.
    axis
        1: links ``(y, x)``-``(y, x + 1)``, shape ``(H, W - 1)``; 0: ``(y, x)``-``(y + 1, x)``,
        shape ``(H - 1, W)``.

    Returns
    -------
    float64 residual per link, in the unit of ``disparity_px``; ``NaN`` where either pixel of the
    link is ``NaN`` (or, see above, no slope is known).
    """
    if span_links < 1 or span_links % 2 != 1:
        raise ValueError(f"span_links must be a positive odd number; got {span_links!r}")
    if not slope_bases_px or min(slope_bases_px) < 1:
        raise ValueError(f"slope_bases_px must be whole numbers >= 1; got {slope_bases_px!r}")
    d = np.moveaxis(np.asarray(disparity_px, dtype=np.float64), axis, -1)
    half, far = span_links // 2, max(slope_bases_px)
    before, after = half + far, half + far + 1
    padded = np.pad(d, [(0, 0)] * (d.ndim - 1) + [(before, after)], constant_values=np.nan)
    links = d.shape[-1] - 1

    def at(offset: int) -> np.ndarray:
        """``d[i + offset]`` for every link ``i`` (``NaN`` beyond the edges)."""
        start = before + offset
        return padded[..., start:start + links]

    with np.errstate(invalid="ignore"):
        step = at(1) - at(0)
        span = at(1 + half) - at(-half)
        whole = np.isfinite(span)
        change = np.where(whole, span, step)
        count = np.where(whole, span_links, 1)
        residual = np.abs(change)  # a flat surface (slope 0) is always a candidate
        own = np.abs(step)
        sloped = np.zeros(step.shape, bool)
        for base in slope_bases_px:
            for slope in ((at(-half) - at(-half - base)) / base, (at(1 + half + base) - at(1 + half)) / base):
                sloped |= np.isfinite(slope)
                slope = np.nan_to_num(slope, nan=0.0)  # a side without a slope (an edge, a hole) offers 0
                residual = np.minimum(residual, np.abs(change - count * slope))
                own = np.minimum(own, np.abs(step - slope))
        residual = np.minimum(residual, count * own)  # the link must take its share of the jump
        residual[~np.isfinite(step)] = np.nan
        if span_links > 1:  # with no slope on either side a wide span judges nothing; one link still does
            residual[~sloped] = np.nan
    return np.moveaxis(residual, -1, axis)


def step_residuals(depth_mm, *, focal_px: float, span_links: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`jump_residual` of the disparity, in pixel footprints, along x and along y.

    The disparity is taken as ``w = focal_px / Z`` (the disparity per mm of baseline: the disparity
    ``d + d0`` divided by the pitch, so its jumps do not depend on the pitch or the offset). A
    residual ``r`` of ``w`` at depth ``Z`` is a step of ``r * Z**2 / focal_px`` mm beyond the local
    slope, ``r * Z`` pixel footprints (``Z / focal_px`` mm each), ``Z`` the mean of the link's two
    depths.

    Returns
    -------
    (right, down)
        ``(H, W - 1)`` and ``(H - 1, W)`` float64, ``NaN`` where either end has no depth.
    """
    depth = np.asarray(depth_mm, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(np.isfinite(depth) & (depth > 0), focal_px / depth, np.nan)
        right = jump_residual(w, axis=1, span_links=span_links) * (depth[:, :-1] + depth[:, 1:]) / 2
        down = jump_residual(w, axis=0, span_links=span_links) * (depth[:-1, :] + depth[1:, :]) / 2
    return right, down


def step_noise(depth_mm, *, focal_px: float) -> float:
    """Robust noise of a depth map in pixel footprints: ``1.4826 * median`` of the one-link
    :func:`step_residuals` along both axes; 0 without links."""
    residuals = np.concatenate([r.ravel() for r in step_residuals(depth_mm, focal_px=focal_px, span_links=1)])
    residuals = residuals[np.isfinite(residuals)]
    return 1.4826 * float(np.median(residuals)) if residuals.size else 0.0


def surface_breaks(depth_mm, *, focal_px: float, max_step_footprints: float = MAX_STEP_FOOTPRINTS,
                   noise_factor: float = STEP_NOISE_FACTOR) -> tuple[np.ndarray, np.ndarray]:
    """Links where the surface breaks, judged on the disparity against its local slope.

    A link breaks where :func:`step_residuals` over any span of :data:`JUMP_SPANS_LINKS` (one link:
    a step or a spike off the local slope; 3 and 5 links: an edge the estimate ramps over a few
    pixels, each step small) exceeds ``max(max_step_footprints, noise_factor * step_noise(...))``.
    A plane stays whole however steep it is (its slope is subtracted); so does a band a couple of
    pixels wide.

    Parameters
    ----------
    depth_mm
        ``(H, W)`` depth along the optical axis in mm; ``NaN`` (or a pixel left out by a mask, set
        to ``NaN`` by the caller) where unknown.
    focal_px
        Focal length in pixels.
    max_step_footprints
        Smallest threshold, in pixel footprints (``Z / focal_px`` mm at the link's depth).
    noise_factor
        The threshold is at least this many times the map's noise (:func:`step_noise`), so a noisy
        estimate is not cut into pieces.

    Returns
    -------
    (right, down)
        ``(H, W - 1)`` and ``(H - 1, W)`` bool, ``True`` where the link crosses a break (shapes as in
        :func:`neighbour_links`). A link with a missing end is not a break here (it is not connected
        anyway).
    """
    if not (np.isfinite(max_step_footprints) and max_step_footprints > 0):
        raise ValueError(f"max_step_footprints must be a positive number of pixel footprints; "
                         f"got {max_step_footprints!r}")
    depth = np.asarray(depth_mm, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_mm must be an (H, W) map; got shape {depth.shape}")
    threshold = max(float(max_step_footprints), noise_factor * step_noise(depth, focal_px=focal_px))
    right = np.zeros((depth.shape[0], max(depth.shape[1] - 1, 0)), bool)
    down = np.zeros((max(depth.shape[0] - 1, 0), depth.shape[1]), bool)
    with np.errstate(invalid="ignore"):
        for span in JUMP_SPANS_LINKS:
            span_right, span_down = step_residuals(depth, focal_px=focal_px, span_links=span)
            right |= span_right > threshold
            down |= span_down > threshold
    return right, down


def neighbour_links(depth_mm, *, mask=None, max_relative_jump: float = MAX_RELATIVE_JUMP, focal_px: float | None = None,
                    max_step_footprints: float = MAX_STEP_FOOTPRINTS):
    """Which neighbouring pixels belong to the same surface.

    Parameters
    ----------
    depth_mm, mask
        As in :func:`point_cloud`.
    max_relative_jump
        Neighbours whose depths differ by more than this fraction of the nearer one are not joined.
    focal_px, max_step_footprints
        With ``focal_px`` (pixels), links where :func:`surface_breaks` finds a break in the
        disparity are not joined either; ``None`` leaves that test out.

    Returns
    -------
    (right, down)
        ``(H, W - 1)`` bool: pixel ``(y, x)`` is connected to ``(y, x + 1)``; ``(H - 1, W)`` bool:
        ``(y, x)`` is connected to ``(y + 1, x)``. Connected means both pixels are valid
        (:func:`valid_depth`), ``|Z1 - Z2| <= max_relative_jump * min(Z1, Z2)`` and, with
        ``focal_px``, no break between them.
    """
    if not max_relative_jump >= 0:
        raise ValueError(f"max_relative_jump must be >= 0 (a fraction of depth); got {max_relative_jump!r}")
    depth = np.asarray(depth_mm, dtype=np.float64)
    valid = valid_depth(depth, mask=mask)
    right = _connected(depth[:, :-1], depth[:, 1:], valid[:, :-1], valid[:, 1:], max_relative_jump)
    down = _connected(depth[:-1, :], depth[1:, :], valid[:-1, :], valid[1:, :], max_relative_jump)
    if focal_px is not None:
        break_right, break_down = surface_breaks(np.where(valid, depth, np.nan), focal_px=focal_px,
                                                 max_step_footprints=max_step_footprints)
        right &= ~break_right
        down &= ~break_down
    return right, down


def _tangent(points: np.ndarray, links: np.ndarray, axis: int) -> np.ndarray:
    """Mean of the forward and backward differences along ``axis`` over connected neighbours."""
    steps = np.diff(points, axis=axis)  # step from pixel i to i + 1, where linked
    steps = np.where(links[..., None], steps, 0.0)
    pad_after = [(0, 0)] * 3
    pad_before = [(0, 0)] * 3
    pad_after[axis] = (0, 1)
    pad_before[axis] = (1, 0)
    forward = np.pad(steps, pad_after)
    backward = np.pad(steps, pad_before)
    count = np.pad(links.astype(np.float64), pad_after[:2]) + np.pad(links.astype(np.float64), pad_before[:2])
    with np.errstate(invalid="ignore", divide="ignore"):
        return (forward + backward) / count[..., None]


def grid_normals(points_mm: np.ndarray, right: np.ndarray, down: np.ndarray) -> np.ndarray:
    """Unit normals of a back-projected depth grid, facing the camera.

    Parameters
    ----------
    points_mm
        ``(H, W, 3)`` from :func:`depth_to_points`.
    right, down
        From :func:`neighbour_links`; differences are taken only across connected neighbours, so
        normals near a depth jump come from the pixel's own surface.

    Returns
    -------
    ``(H, W, 3)`` ``float64`` unit vectors with ``n . P < 0``. Where a pixel has no connected
    neighbour along x or along y, the normal points back along the line of sight (``-P / |P|``).
    ``NaN`` where the point itself is ``NaN``.
    """
    points = np.where(np.isfinite(points_mm), points_mm, 0.0)
    along_x = _tangent(points, right, axis=1)
    along_y = _tangent(points, down, axis=0)
    normals = np.cross(along_y, along_x)  # y x x = -z: towards the camera for a fronto-parallel plane
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    sight = -points_mm / np.linalg.norm(points_mm, axis=-1, keepdims=True)
    ok = np.isfinite(length) & (length > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = np.where(ok, normals / length, sight)
    facing_away = np.einsum("...i,...i->...", normals, points_mm) > 0
    return np.where(facing_away[..., None], -normals, normals)


def _colours(image, shape: tuple[int, int]) -> np.ndarray | None:
    if image is None:
        return None
    image = np.asarray(image)
    if image.shape[:2] != shape or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"image must be (H, W) or (H, W, 3) with (H, W) = {shape}; got {image.shape}")
    colours = to_float(image)
    if colours.ndim == 2:
        colours = np.repeat(colours[..., None], 3, axis=-1)
    return np.clip(colours, 0.0, 1.0).astype(np.float32)


def point_cloud(
    depth_mm,
    image=None,
    *,
    focal_px: float,
    principal_point_px=None,
    mask=None,
    max_relative_jump: float = MAX_RELATIVE_JUMP,
    max_step_footprints: float = MAX_STEP_FOOTPRINTS,
) -> PointCloud:
    """Coloured points with camera-facing normals from a depth map.

    Parameters
    ----------
    depth_mm
        ``(H, W)`` depth along the optical axis in mm; ``NaN`` where unknown.
    image
        ``(H, W, 3)`` RGB or ``(H, W)`` grey centre view (``uint8``, ``uint16`` or float in
        ``[0, 1]``) for the colours, or ``None``.
    focal_px, principal_point_px
        As in :func:`depth_to_points`.
    mask
        ``(H, W)`` bool, ``True`` where the depth is trustworthy; ``None`` keeps every finite depth.
    max_relative_jump, max_step_footprints
        Which neighbours are connected (:func:`neighbour_links`); only connected neighbours are used
        for each other's normal.

    Returns
    -------
    :class:`PointCloud` with one point per valid pixel, in row-major pixel order.
    """
    depth = _check_depth(depth_mm, focal_px)
    points = depth_to_points(depth, focal_px=focal_px, principal_point_px=principal_point_px)
    valid = valid_depth(depth, mask=mask)
    right, down = neighbour_links(depth, mask=mask, max_relative_jump=max_relative_jump, focal_px=focal_px,
                                  max_step_footprints=max_step_footprints)
    normals = grid_normals(points, right, down)
    colours = _colours(image, depth.shape)
    pixels = np.argwhere(valid)
    return PointCloud(
        points_mm=points[valid],
        normals=normals[valid],
        colours=None if colours is None else colours[valid],
        pixels=pixels.astype(np.int64),
    )


def grid_triangles(depth_mm, *, mask=None, max_relative_jump: float = MAX_RELATIVE_JUMP,
                   focal_px: float | None = None, max_step_footprints: float = MAX_STEP_FOOTPRINTS) -> np.ndarray:
    """Triangles over the pixel grid, cut wherever the surface breaks.

    Each 2x2 cell ``a = (y, x)``, ``b = (y, x + 1)``, ``c = (y + 1, x)``, ``d = (y + 1, x + 1)`` is
    split along the diagonal ``b-c`` (triangles ``a c b`` and ``b c d``) or ``a-d`` (``a c d`` and
    ``a d b``). A triangle is kept only if all three of its edges join connected pixels: the sides
    by :func:`neighbour_links`, the diagonal by the relative depth test (a triangle's two sides
    already put its three corners on one surface). Per cell the diagonal that keeps more triangles
    wins; on a tie, the one with the smaller depth difference.

    Returns
    -------
    ``(M, 3)`` ``int64`` flat pixel indices ``y * W + x``, counter-clockwise as seen from the camera.
    """
    depth = np.asarray(depth_mm, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_mm must be an (H, W) map; got shape {depth.shape}")
    height, width = depth.shape
    if height < 2 or width < 2:
        return np.zeros((0, 3), dtype=np.int64)
    valid = valid_depth(depth, mask=mask)
    right, down = neighbour_links(depth, mask=mask, max_relative_jump=max_relative_jump, focal_px=focal_px,
                                  max_step_footprints=max_step_footprints)
    za, zb, zc, zd = depth[:-1, :-1], depth[:-1, 1:], depth[1:, :-1], depth[1:, 1:]
    va, vb, vc, vd = valid[:-1, :-1], valid[:-1, 1:], valid[1:, :-1], valid[1:, 1:]
    ab, cd = right[:-1, :], right[1:, :]
    ac, bd = down[:, :-1], down[:, 1:]
    bc = _connected(zb, zc, vb, vc, max_relative_jump)
    ad = _connected(za, zd, va, vd, max_relative_jump)

    acb = ac & bc & ab
    bcd = bc & cd & bd
    acd = ac & cd & ad
    adb = ad & bd & ab
    kept_bc = acb.astype(np.int8) + bcd
    kept_ad = acd.astype(np.int8) + adb
    with np.errstate(invalid="ignore"):
        closer_ad = np.abs(za - zd) < np.abs(zb - zc)
    use_ad = (kept_ad > kept_bc) | ((kept_ad == kept_bc) & closer_ad)

    index = np.arange(height * width, dtype=np.int64).reshape(height, width)
    ia, ib, ic, id_ = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    pieces = []
    for keep, corners in (
        (acb & ~use_ad, (ia, ic, ib)),
        (bcd & ~use_ad, (ib, ic, id_)),
        (acd & use_ad, (ia, ic, id_)),
        (adb & use_ad, (ia, id_, ib)),
    ):
        pieces.append(np.stack([corner[keep] for corner in corners], axis=-1))
    triangles = np.concatenate(pieces, axis=0)
    # row-major cell order makes files reproducible and easy to inspect
    return triangles[np.lexsort((triangles[:, 2], triangles[:, 1], triangles[:, 0]))]


def depth_mesh(
    depth_mm,
    image=None,
    *,
    focal_px: float,
    principal_point_px=None,
    mask=None,
    max_relative_jump: float = MAX_RELATIVE_JUMP,
    max_step_footprints: float = MAX_STEP_FOOTPRINTS,
    cloud: PointCloud | None = None,
) -> Mesh:
    """A mesh over the depth grid, cut where the surface breaks (see :func:`grid_triangles`).

    Parameters are those of :func:`point_cloud`; ``cloud`` is what :func:`point_cloud` gives for
    the same arguments when the caller already has it (it is not computed again). Vertices are the
    valid pixels that belong to at least one triangle (isolated pixels are left out of the mesh;
    :func:`point_cloud` keeps them).

    Returns
    -------
    :class:`Mesh` with vertex colours (if ``image`` is given) and camera-facing vertex normals.
    """
    depth = _check_depth(depth_mm, focal_px)
    links = {"mask": mask, "max_relative_jump": max_relative_jump, "focal_px": focal_px,
             "max_step_footprints": max_step_footprints}
    if cloud is None:
        cloud = point_cloud(depth, image, principal_point_px=principal_point_px, **links)
    flat = grid_triangles(depth, **links)
    width = depth.shape[1]
    cloud_flat = cloud.pixels[:, 0] * width + cloud.pixels[:, 1]  # sorted: point_cloud is row-major
    used = np.zeros(len(cloud), dtype=bool)
    position = np.searchsorted(cloud_flat, flat)
    used[position.ravel()] = True
    renumber = np.cumsum(used) - 1
    return Mesh(
        vertices_mm=cloud.points_mm[used],
        triangles=renumber[position].astype(np.int64),
        normals=cloud.normals[used],
        colours=None if cloud.colours is None else cloud.colours[used],
        pixels=cloud.pixels[used],
    )


def longest_edges(vertices_mm: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(M,)`` length of each triangle's longest edge, in the vertices' unit (mm)."""
    vertices = np.asarray(vertices_mm, np.float64)
    corners = [vertices[triangles[:, k]] for k in range(3)]
    lengths = [np.linalg.norm(corners[k] - corners[(k + 1) % 3], axis=-1) for k in range(3)]
    return np.max(lengths, axis=0) if len(triangles) else np.zeros(0)


def triangle_normals(vertices_mm: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(M, 3)`` unit face normals by the right-hand rule over ``(v1 - v0) x (v2 - v0)``."""
    v0, v1, v2 = (vertices_mm[triangles[:, k]] for k in range(3))
    normals = np.cross(v1 - v0, v2 - v0)
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)
