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
    """
    if kind not in ("mesh", "points"):
        raise ValueError(f"kind must be 'mesh' or 'points'; got {kind!r}")
    if poisson and kind != "mesh":
        raise ExportError("Poisson reconstruction makes a mesh; use it with --mesh (the default), not --points")
    disparity = np.asarray(disparity_px)
    if disparity.ndim != 2:
        raise ValueError(f"disparity_px must be an (H, W) map; got shape {disparity.shape}")
    depth = camera.depth_mm(disparity.astype(np.float64))
    options = {"focal_px": camera.focal_px, "principal_point_px": camera.principal_point_px, "mask": mask,
               "max_relative_jump": max_relative_jump}
    cloud = point_cloud(depth, image, **options)
    depth_range = (float(cloud.points_mm[:, 2].min()), float(cloud.points_mm[:, 2].max())) if len(cloud) else None
    common = {"pixels_used": len(cloud), "pixels_total": int(disparity.size), "depth_range_mm": depth_range}
    if kind == "points":
        written = write_cloud_ply(path, cloud, ascii=ascii)
        return ExportSummary(path=written, kind="points", points=len(cloud), triangles=0, **common)
    mesh = poisson_mesh(cloud, depth=poisson_depth) if poisson else depth_mesh(depth, image, **options)
    written = write_mesh_ply(path, mesh, ascii=ascii)
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
) -> ExportSummary:
    """:func:`export_ply` for a reconstruction folder (:func:`recon.result.read_result`).

    ``focal_px``, ``pitch_mm`` and ``disparity_offset`` override ``result.json`` when given.
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
    )
