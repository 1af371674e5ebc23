"""The export edge: point clouds and meshes to PLY files through open3d.

This is the only module that imports open3d (lazily, inside the functions that need it, so that
``import recon.export`` and ``lfrig --help`` stay fast). Everything before this point is plain numpy
(:mod:`recon.depth`, :mod:`recon.cloud`).

PLY files are binary little-endian by default, ASCII on request; coordinates are mm in the camera
frame of the centre view (x right, y down, z forward; ``docs/conventions.md``). Vertices carry
``x y z`` (double), ``nx ny nz`` (double) and, with an image, ``red green blue`` (uchar). Meshes add
``face`` lists of vertex indices. MeshLab, CloudCompare and open3d read these files.

Entry points
------------
- :func:`export_ply`: disparity (+ centre view and camera) -> PLY file; what ``lfrig reconstruct
  --ply`` and the simulated session call.
- :func:`export_result`: the same from a reconstruction folder (``lfrig export``; the folder is
  read by :func:`recon.result.read_result`).
- :func:`write_cloud_ply`, :func:`write_mesh_ply`, :func:`poisson_mesh`: the pieces.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from recon.cloud import MAX_RELATIVE_JUMP, Mesh, PointCloud, depth_mesh, point_cloud
from recon.camera import Camera
from recon.errors import ExportError


def _open3d():
    import open3d

    return open3d


# --------------------------------------------------------------------------------------------------
# arrays <-> open3d
# --------------------------------------------------------------------------------------------------


def to_open3d_cloud(cloud: PointCloud):
    """An ``open3d.geometry.PointCloud`` with points (mm), normals and colours (if any)."""
    o3d = _open3d()
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(cloud.points_mm, dtype=np.float64))
    pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(cloud.normals, dtype=np.float64))
    if cloud.colours is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.ascontiguousarray(cloud.colours, dtype=np.float64))
    return pcd


def to_open3d_mesh(mesh: Mesh):
    """An ``open3d.geometry.TriangleMesh`` with vertex normals and colours (if any)."""
    o3d = _open3d()
    out = o3d.geometry.TriangleMesh()
    out.vertices = o3d.utility.Vector3dVector(np.ascontiguousarray(mesh.vertices_mm, dtype=np.float64))
    out.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(mesh.triangles, dtype=np.int32))
    out.vertex_normals = o3d.utility.Vector3dVector(np.ascontiguousarray(mesh.normals, dtype=np.float64))
    if mesh.colours is not None:
        out.vertex_colors = o3d.utility.Vector3dVector(np.ascontiguousarray(mesh.colours, dtype=np.float64))
    return out


def _check_target(path: Path) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ExportError(f"{path}: the output file must end in .ply")
    if not path.parent.exists():
        raise ExportError(f"{path}: folder {path.parent} does not exist; create it first")
    return path


def write_cloud_ply(path, cloud: PointCloud, *, ascii: bool = False) -> Path:
    """Write a point cloud as PLY (binary unless ``ascii``). Returns the path."""
    path = _check_target(path)
    if len(cloud) == 0:
        raise ExportError(f"{path}: nothing to write, the point cloud is empty (no pixel had a trustworthy depth)")
    pcd = to_open3d_cloud(cloud)
    _write_atomic(path, lambda tmp: _open3d().io.write_point_cloud(str(tmp), pcd, write_ascii=ascii),
                  what="point cloud", vertices=len(cloud), faces=0, ascii=ascii)
    return path


def write_mesh_ply(path, mesh: Mesh, *, ascii: bool = False) -> Path:
    """Write a triangle mesh as PLY (binary unless ``ascii``). Returns the path."""
    path = _check_target(path)
    if len(mesh.triangles) == 0:
        raise ExportError(
            f"{path}: nothing to write, the mesh has no triangles (too few connected pixels); "
            "export --points instead, or raise the jump threshold"
        )
    o3d_mesh = to_open3d_mesh(mesh)
    _write_atomic(
        path,
        lambda tmp: _open3d().io.write_triangle_mesh(
            str(tmp), o3d_mesh, write_ascii=ascii, write_vertex_normals=True,
            write_vertex_colors=mesh.colours is not None, write_triangle_uvs=False,
        ),
        what="mesh", vertices=len(mesh.vertices_mm), faces=len(mesh.triangles), ascii=ascii,
    )
    return path


def _write_atomic(path: Path, write, *, what: str, vertices: int, faces: int, ascii: bool) -> None:
    """Let open3d write a temporary file beside ``path``, check it, sync it and rename it into place.

    open3d reports success even when the disk filled up under it, so the file is checked too: its
    header must announce ``vertices`` and ``faces`` elements and, for binary PLY, the body must be at
    least as long as those elements need. A failed or short write is an :class:`ExportError` naming
    ``path``, and ``path`` keeps what it held before.
    """
    from recon.errors import FileWriteError
    from recon.lf.imageio import atomic_output

    try:
        with atomic_output(path, what=what) as tmp:
            if not write(tmp):
                raise ExportError(f"{path}: open3d could not write the {what} (is the folder writable and not full?)")
            _check_ply(tmp, path, vertices=vertices, faces=faces, ascii=ascii)
    except FileWriteError as error:
        raise ExportError(str(error)) from None


def _check_ply(tmp: Path, path: Path, *, vertices: int, faces: int, ascii: bool) -> None:
    """Check the PLY open3d wrote at ``tmp`` holds what it should (see :func:`_write_atomic`)."""
    data_size = tmp.stat().st_size
    with open(tmp, "rb") as f:
        head = f.read(4096)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        raise ExportError(f"{path}: the PLY written has no complete header (a full disk?); nothing was replaced")
    header = head[:end].decode("ascii", "replace").splitlines()
    counts: dict[str, int] = {}
    props: dict[str, list[str]] = {}
    current = ""
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"] and len(parts) == 3:
            current = parts[1]
            counts[current] = int(parts[2])
            props[current] = []
        elif parts[:1] == ["property"] and current:
            props[current].append(line)
    if counts.get("vertex", 0) != vertices or counts.get("face", 0) != faces:
        raise ExportError(f"{path}: the PLY written holds {counts} elements, expected {vertices} vertices and "
                          f"{faces} faces; nothing was replaced")
    if ascii:
        with open(tmp, "rb") as f:
            f.seek(end + len(b"end_header\n"))
            lines = sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b""))
        short = lines < vertices + faces
    else:
        sizes = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
                 "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
        vertex_bytes = sum(sizes.get(line.split()[1], 0) for line in props.get("vertex", []))
        # a face is at least a count byte and three indices (open3d writes uchar + 3 int)
        need = vertices * vertex_bytes + faces * 13
        short = data_size - (end + len(b"end_header\n")) < need
    if short:
        raise ExportError(f"{path}: the PLY written is shorter than its header says (a full disk?); nothing was replaced")


def poisson_mesh(cloud: PointCloud, *, depth: int = 9, density_quantile: float = 0.02) -> Mesh:
    """Screened Poisson surface reconstruction (Kazhdan and Hoppe 2013, via open3d) of an oriented cloud.

    Poisson closes the surface; the parts it invents far from any point have low point density and
    are removed: vertices whose density is below the ``density_quantile`` quantile, and anything
    outside the cloud's bounding box.

    Parameters
    ----------
    cloud
        Points with camera-facing normals (:func:`recon.cloud.point_cloud`).
    depth
        Octree depth: the solution grid is at most ``2**depth`` cells across.
    density_quantile
        Fraction of the least supported vertices to drop, in ``[0, 1)``.

    Returns
    -------
    :class:`recon.cloud.Mesh` with ``pixels = None``; normals re-oriented to face the camera.
    """
    if len(cloud) < 4:
        raise ExportError(f"Poisson reconstruction needs at least 4 points; the cloud has {len(cloud)}")
    if not 0 <= density_quantile < 1:
        raise ValueError(f"density_quantile must be in [0, 1); got {density_quantile!r}")
    o3d = _open3d()
    pcd = to_open3d_cloud(cloud)
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    densities = np.asarray(densities)
    if density_quantile > 0 and len(densities):
        mesh.remove_vertices_by_mask(densities < np.quantile(densities, density_quantile))
    mesh = mesh.crop(pcd.get_axis_aligned_bounding_box())
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    vertices = np.asarray(mesh.vertices).copy()
    triangles = np.asarray(mesh.triangles).astype(np.int64)
    normals = np.asarray(mesh.vertex_normals).copy()
    away = np.einsum("ij,ij->i", normals, vertices) > 0
    if away.mean() > 0.5:  # Poisson's outward side is away from the camera: flip winding and normals
        triangles = triangles[:, [0, 2, 1]]
        normals = -normals
    colours = np.asarray(mesh.vertex_colors).astype(np.float32) if mesh.has_vertex_colors() else None
    return Mesh(vertices_mm=vertices, triangles=triangles, normals=normals, colours=colours, pixels=None)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


def add_vertex_property(path, name: str, values: np.ndarray) -> Path:
    """Rewrite the PLY file ``path`` (as open3d writes it: binary little-endian or ASCII, the vertex
    element first, its properties scalar) with one more ``float`` vertex property ``name``.

    ``values`` ``(N,)``: one per vertex, in the file's vertex order. Other elements are kept byte for
    byte. Returns the path."""
    path = Path(path)
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    fmt = next(line.split()[1] for line in lines if line.startswith("format "))
    try:
        at = next(i for i, line in enumerate(lines) if line.startswith("element vertex "))
    except StopIteration:
        raise ExportError(f"{path}: no vertex element in the PLY header") from None
    count = int(lines[at].split()[2])
    values = np.asarray(values, np.float32).reshape(-1)
    if len(values) != count:
        raise ValueError(f"{path}: {count} vertices but {len(values)} values for {name!r}")
    last = at + 1
    while last < len(lines) and lines[last].startswith("property "):
        last += 1
    props = [line.split() for line in lines[at + 1:last]]
    header = "\n".join(lines[:last] + [f"property float {name}"] + lines[last:]) + "\n"
    body = data[end:]
    if fmt == "ascii":
        text = body.decode("ascii").split("\n")
        rows = [f"{row} {v:.6g}" if row.strip() else row for row, v in zip(text[:count], values)]
        out = header.encode("ascii") + "\n".join(rows + text[count:]).encode("ascii")
    elif fmt == "binary_little_endian":
        if any(p[1] == "list" for p in props):
            raise ExportError(f"{path}: list properties in the vertex element are not supported")
        dtype = np.dtype([(p[2], _PLY_TYPES[p[1]]) for p in props])
        vertices = np.frombuffer(body[:count * dtype.itemsize], dtype=dtype)
        extended = np.empty(count, np.dtype(dtype.descr + [(name, "<f4")]))
        for field_name in dtype.names:
            extended[field_name] = vertices[field_name]
        extended[name] = values
        out = header.encode("ascii") + extended.tobytes() + body[count * dtype.itemsize:]
    else:
        raise ExportError(f"{path}: PLY format {fmt!r} not supported for adding a property")
    from recon.lf.imageio import write_bytes_atomic

    write_bytes_atomic(path, out)
    return path


#: Pixels whose confidence (``confidence.pfm``: the probability that the disparity is within 0.07
#: px/view of the truth, :mod:`recon.entropy.calibration`) is below this are left out of exports
#: unless the caller keeps everything: 0.5 keeps a pixel that is more likely right than wrong.
MIN_CONFIDENCE = 0.5


def trusted_pixels(disparity_px: np.ndarray, *, confidence: np.ndarray | None = None,
                   min_confidence: float = MIN_CONFIDENCE,
                   search_range: tuple[float, float] | None = None) -> np.ndarray:
    """``(H, W)`` bool: finite disparity, confidence at least ``min_confidence`` (when a map is
    given) and inside the searched range (when given; a value outside it was never matched)."""
    disparity = np.asarray(disparity_px, np.float64)
    keep = np.isfinite(disparity)
    if confidence is not None:
        keep &= np.asarray(confidence) >= min_confidence
    if search_range is not None:
        keep &= (disparity >= search_range[0] - 1e-6) & (disparity <= search_range[1] + 1e-6)
    return keep


# --------------------------------------------------------------------------------------------------
# from disparity to a file
# --------------------------------------------------------------------------------------------------

Kind = Literal["mesh", "points"]


@dataclass
class ExportSummary:
    """What :func:`export_ply` wrote."""

    path: Path
    kind: str  # "points", "mesh" or "poisson"
    points: int  # vertices in the file
    triangles: int  # 0 for a point cloud
    pixels_used: int  # pixels with a trustworthy depth
    pixels_total: int
    depth_range_mm: tuple[float, float] | None
    pixels_unreliable: int = 0  # left out for low confidence or a disparity outside the search range

    def as_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        out["path"] = str(self.path)
        return out

    def __str__(self) -> str:
        what = f"{self.points} points" + (f", {self.triangles} triangles" if self.triangles else "")
        span = ""
        if self.depth_range_mm:
            span = f", depth {self.depth_range_mm[0]:.1f}..{self.depth_range_mm[1]:.1f} mm"
        share = 100.0 * self.pixels_used / max(self.pixels_total, 1)
        return f"{self.path}: {self.kind}, {what} from {share:.1f} % of pixels{span}"


def export_ply(
    path,
    *,
    disparity_px: np.ndarray,
    image: np.ndarray | None,
    camera: Camera,
    mask: np.ndarray | None = None,
    kind: Kind = "mesh",
    poisson: bool = False,
    ascii: bool = False,
    max_relative_jump: float = MAX_RELATIVE_JUMP,
    poisson_depth: int = 9,
    confidence: np.ndarray | None = None,
    min_confidence: float = MIN_CONFIDENCE,
    search_range: tuple[float, float] | None = None,
    keep_all: bool = False,
) -> ExportSummary:
    """Disparity of the centre view -> depth -> coloured point cloud or cut mesh -> PLY.

    Parameters
    ----------
    path
        Output ``.ply`` file (its folder must exist).
    disparity_px
        ``(H, W)`` disparity of the centre view, pixels per view step; ``NaN`` where not trusted.
    image
        ``(H, W, 3)`` RGB or ``(H, W)`` grey centre view for the colours, or ``None``.
    camera
        The rectified camera (:class:`recon.camera.Camera`: focal length, pitch, disparity offset,
        principal point).
    mask
        ``(H, W)`` bool, ``True`` where the disparity is trustworthy; ``NaN`` disparities and
        non-positive effective disparities are left out in any case.
    kind
        ``"mesh"`` (the depth grid triangulated, cut at depth jumps) or ``"points"``.
    poisson
        Mesh by screened Poisson reconstruction of the oriented cloud instead of the grid
        (``kind`` must be ``"mesh"``).
    ascii
        Write ASCII PLY instead of binary.
    max_relative_jump
        Neighbours whose depths differ by more than this fraction are not joined
        (:data:`recon.cloud.MAX_RELATIVE_JUMP`).
    poisson_depth
        Octree depth for :func:`poisson_mesh`.
    confidence
        ``(H, W)`` confidence in ``[0, 1]`` (``confidence.pfm``), or ``None``. Written as the float
        vertex property ``confidence`` (points and grid meshes; a Poisson mesh's vertices are new).
    min_confidence, search_range, keep_all
        Unless ``keep_all``, pixels with confidence below ``min_confidence`` or a disparity outside
        ``search_range`` are left out (:func:`trusted_pixels`).
    """
    if kind not in ("mesh", "points"):
        raise ValueError(f"kind must be 'mesh' or 'points'; got {kind!r}")
    if poisson and kind != "mesh":
        raise ExportError("Poisson reconstruction makes a mesh; use it with --mesh (the default), not --points")
    disparity = np.asarray(disparity_px)
    if disparity.ndim != 2:
        raise ValueError(f"disparity_px must be an (H, W) map; got shape {disparity.shape}")
    if confidence is not None and np.shape(confidence) != disparity.shape:
        raise ValueError(f"confidence must be {disparity.shape} like the disparity; got {np.shape(confidence)}")
    unreliable = 0
    if not keep_all:
        trusted = trusted_pixels(disparity, confidence=confidence, min_confidence=min_confidence,
                                 search_range=search_range)
        unreliable = int(np.count_nonzero(np.isfinite(disparity) & ~trusted))
        mask = trusted if mask is None else (np.asarray(mask, bool) & trusted)
    depth = camera.depth_mm(disparity.astype(np.float64))
    options = {"focal_px": camera.focal_px, "principal_point_px": camera.principal_point_px, "mask": mask,
               "max_relative_jump": max_relative_jump}
    cloud = point_cloud(depth, image, **options)
    depth_range = (float(cloud.points_mm[:, 2].min()), float(cloud.points_mm[:, 2].max())) if len(cloud) else None
    common = {"pixels_used": len(cloud), "pixels_total": int(disparity.size), "depth_range_mm": depth_range,
              "pixels_unreliable": unreliable}
    if kind == "points":
        written = write_cloud_ply(path, cloud, ascii=ascii)
        if confidence is not None:
            add_vertex_property(written, "confidence", np.asarray(confidence)[cloud.pixels[:, 0], cloud.pixels[:, 1]])
        return ExportSummary(path=written, kind="points", points=len(cloud), triangles=0, **common)
    mesh = poisson_mesh(cloud, depth=poisson_depth) if poisson else depth_mesh(depth, image, **options)
    written = write_mesh_ply(path, mesh, ascii=ascii)
    if confidence is not None and mesh.pixels is not None:
        add_vertex_property(written, "confidence", np.asarray(confidence)[mesh.pixels[:, 0], mesh.pixels[:, 1]])
    return ExportSummary(
        path=written, kind="poisson" if poisson else "mesh", points=len(mesh.vertices_mm),
        triangles=len(mesh.triangles), **common,
    )


def export_result(
    result_dir,
    ply_path,
    *,
    kind: Kind = "mesh",
    poisson: bool = False,
    ascii: bool = False,
    focal_px: float | None = None,
    pitch_mm: float | None = None,
    disparity_offset: float | None = None,
    max_relative_jump: float = MAX_RELATIVE_JUMP,
    min_confidence: float = MIN_CONFIDENCE,
    keep_all: bool = False,
) -> ExportSummary:
    """:func:`export_ply` for a reconstruction folder (:func:`recon.result.read_result`).

    ``focal_px``, ``pitch_mm`` and ``disparity_offset`` override ``result.json`` when given. The
    folder's ``confidence.pfm`` and searched range (``result.json`` options) filter the pixels unless
    ``keep_all``.
    """
    from recon.result import read_result

    result = read_result(result_dir)
    camera = result.camera(focal_px=focal_px, pitch_mm=pitch_mm, disparity_offset=disparity_offset)
    return export_ply(
        ply_path,
        disparity_px=result.disparity_px,
        image=result.image,
        camera=camera,
        mask=result.mask,
        kind=kind,
        poisson=poisson,
        ascii=ascii,
        max_relative_jump=max_relative_jump,
        confidence=result.confidence,
        min_confidence=min_confidence,
        search_range=result.search_range,
        keep_all=keep_all,
    )
