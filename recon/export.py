"""The export edge: point clouds and meshes to PLY files.

open3d is imported only here (lazily, inside the functions that need it, so that ``import
recon.export`` and ``lfrig --help`` stay fast), for Poisson reconstruction; the PLY files are
written by :func:`write_ply`. Everything before this point is plain numpy (:mod:`recon.depth`,
:mod:`recon.cloud`).

PLY files are binary little-endian by default, ASCII on request; coordinates are mm in the camera
frame of the centre view (x right, y down, z forward; ``docs/conventions.md``). Vertices carry
``x y z`` (float32), ``nx ny nz`` (float32), with an image ``red green blue`` (uchar) and with a
confidence map ``confidence`` (float32). Meshes add ``face`` lists of vertex indices. The header's
``comment`` lines give units, frame, the meaning of ``confidence`` and the provenance
(:mod:`recon.provenance`). MeshLab, CloudCompare and open3d read these files.

Entry points
------------
- :func:`export_ply`: disparity (+ centre view and camera) -> PLY file; what ``lfrig reconstruct
  --ply`` and the simulated session call.
- :func:`export_result`: the same from a reconstruction folder (``lfrig export``; the folder is
  read by :func:`recon.result.read_result`).
- :func:`write_cloud_ply`, :func:`write_mesh_ply`, :func:`write_ply`, :func:`poisson_mesh`: the pieces.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from recon.cloud import (MAX_RELATIVE_JUMP, MAX_STEP_FOOTPRINTS, Mesh, PointCloud, depth_mesh, longest_edges,
                         point_cloud)
from recon.camera import Camera
from recon.errors import ExportError
from recon.provenance import ply_comments, provenance as make_provenance


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


def _check_target(path: Path) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ExportError(f"{path}: the output file must end in .ply")
    if not path.parent.exists():
        raise ExportError(f"{path}: folder {path.parent} does not exist; create it first")
    return path


#: What every PLY header says about the coordinates (``docs/conventions.md``).
PLY_FRAME_COMMENTS = (
    "units mm",
    "frame centre camera of the light field: x right, y down, z forward along the optical axis "
    "(docs/conventions.md)",
    "normals unit vectors facing the camera (n . P < 0)",
)
#: What the ``confidence`` vertex property means.
PLY_CONFIDENCE_COMMENT = ("confidence per-vertex confidence of the disparity in [0, 1] "
                          "(recon.entropy.confidence), from the pixel the vertex comes from")


def write_cloud_ply(path, cloud: PointCloud, *, ascii: bool = False, confidence: np.ndarray | None = None,
                    comments: Sequence[str] = ()) -> Path:
    """Write a point cloud as PLY (binary unless ``ascii``, :func:`write_ply`). Returns the path.

    ``confidence``: ``(N,)`` per point, written as the float vertex property ``confidence``, or ``None``."""
    path = _check_target(path)
    if len(cloud) == 0:
        raise ExportError(f"{path}: nothing to write, the point cloud is empty (no pixel had a trustworthy depth)")
    return write_ply(path, vertices_mm=cloud.points_mm, normals=cloud.normals, colours=cloud.colours,
                     confidence=confidence, comments=comments, ascii=ascii)


def write_mesh_ply(path, mesh: Mesh, *, ascii: bool = False, confidence: np.ndarray | None = None,
                   comments: Sequence[str] = ()) -> Path:
    """Write a triangle mesh as PLY (binary unless ``ascii``, :func:`write_ply`). Returns the path.

    ``confidence``: ``(N,)`` per vertex, written as the float vertex property ``confidence``, or ``None``."""
    path = _check_target(path)
    if len(mesh.triangles) == 0:
        raise ExportError(
            f"{path}: nothing to write, the mesh has no triangles (too few connected pixels); "
            "export --points instead, or raise --max-step"
        )
    return write_ply(path, vertices_mm=mesh.vertices_mm, normals=mesh.normals, colours=mesh.colours,
                     confidence=confidence, triangles=mesh.triangles, comments=comments, ascii=ascii)


def write_ply(path, *, vertices_mm: np.ndarray, normals: np.ndarray, colours: np.ndarray | None = None,
              confidence: np.ndarray | None = None, triangles: np.ndarray | None = None,
              comments: Sequence[str] = (), ascii: bool = False) -> Path:
    """Write vertices (and faces) as a PLY file, atomically (a temporary file renamed into place).

    Parameters
    ----------
    vertices_mm, normals
        ``(N, 3)``: written as ``float`` (float32) ``x y z`` and ``nx ny nz``.
    colours
        ``(N, 3)`` RGB in ``[0, 1]``, written as ``uchar`` ``red green blue``; or ``None``.
    confidence
        ``(N,)``, written as ``float confidence``; or ``None``.
    triangles
        ``(M, 3)`` vertex indices, written as ``face`` lists (``uchar`` count, ``uint`` indices); or
        ``None`` for a point cloud.
    comments
        Header ``comment`` lines (one line each, printable ASCII; other characters are escaped),
        after ``Created by lfrig``.
    ascii
        ASCII PLY instead of binary little-endian.

    Raises
    ------
    ExportError
        When the file cannot be written (a full disk, no permission); ``path`` keeps what it held.
    """
    from recon.errors import FileWriteError
    from recon.lf.imageio import write_bytes_atomic
    from recon.provenance import ascii_line

    path = Path(path)
    count = len(vertices_mm)
    fields = [(name, "<f4") for name in ("x", "y", "z", "nx", "ny", "nz")]
    if colours is not None:
        fields += [(name, "u1") for name in ("red", "green", "blue")]
    if confidence is not None:
        fields.append(("confidence", "<f4"))
    vertex = np.empty(count, np.dtype(fields))
    for k, name in enumerate(("x", "y", "z")):
        vertex[name] = vertices_mm[:, k]
    for k, name in enumerate(("nx", "ny", "nz")):
        vertex[name] = normals[:, k]
    if colours is not None:
        rgb = np.clip(np.rint(np.asarray(colours, np.float64) * 255.0), 0, 255).astype(np.uint8)
        for k, name in enumerate(("red", "green", "blue")):
            vertex[name] = rgb[:, k]
    if confidence is not None:
        vertex["confidence"] = np.asarray(confidence, np.float32).reshape(-1)
    faces = None if triangles is None else np.asarray(triangles)
    if faces is not None and len(faces) and (faces.min() < 0 or faces.max() >= count):
        raise ValueError(f"triangles index vertices 0..{count - 1}; got {faces.min()}..{faces.max()}")
    header = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0", "comment Created by lfrig"]
    header += [f"comment {ascii_line(line)}" for line in comments]
    header.append(f"element vertex {count}")
    types = {"<f4": "float", "u1": "uchar"}
    header += [f"property {types[kind]} {name}" for name, kind in fields]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar uint vertex_indices"]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii")
    if ascii:
        body = _ascii_rows(vertex) + (b"" if faces is None else _ascii_faces(faces))
    else:
        body = vertex.tobytes()
        if faces is not None:
            face = np.empty(len(faces), np.dtype([("n", "u1"), ("v", "<u4", 3)]))
            face["n"] = 3
            face["v"] = faces
            body += face.tobytes()
    try:
        write_bytes_atomic(path, head + body)
    except FileWriteError as error:
        raise ExportError(str(error)) from None
    return path


def _ascii_rows(vertex: np.ndarray) -> bytes:
    """One line per vertex: floats to 7 significant digits (float32's precision), integers as they are."""
    if not len(vertex):
        return b""
    columns = [vertex[name].astype(str) if vertex[name].dtype.kind == "u" else np.char.mod("%.7g", vertex[name])
               for name in vertex.dtype.names]
    lines = columns[0]
    for column in columns[1:]:
        lines = np.char.add(np.char.add(lines, " "), column)
    return ("\n".join(lines.tolist()) + "\n").encode("ascii")


def _ascii_faces(faces: np.ndarray) -> bytes:
    return "".join(f"3 {a} {b} {c}\n" for a, b, c in faces.tolist()).encode("ascii")


def _check_ply(tmp: Path, path: Path, *, vertices: int, faces: int, ascii: bool) -> None:
    """Check the PLY file at ``tmp`` holds what it should: its header announces ``vertices`` and
    ``faces`` elements and the body is at least as long as those elements need; else an
    :class:`ExportError` naming ``path``."""
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
    long_triangles: int = 0  # triangles whose longest edge is over 10x the median one (curtains, spikes)

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
    max_step_footprints: float = MAX_STEP_FOOTPRINTS,
    poisson_depth: int = 9,
    confidence: np.ndarray | None = None,
    min_confidence: float = MIN_CONFIDENCE,
    search_range: tuple[float, float] | None = None,
    keep_all: bool = False,
    provenance: Mapping[str, Any] | None = None,
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
        ``"mesh"`` (the depth grid triangulated, cut where the surface breaks) or ``"points"``.
    poisson
        Mesh by screened Poisson reconstruction of the oriented cloud instead of the grid
        (``kind`` must be ``"mesh"``).
    ascii
        Write ASCII PLY instead of binary.
    max_relative_jump
        Neighbours whose depths differ by more than this fraction are not joined
        (:data:`recon.cloud.MAX_RELATIVE_JUMP`).
    max_step_footprints
        Neighbours whose step, beyond the local slope of the disparity, is more than this many pixel
        footprints are not joined (:func:`recon.cloud.surface_breaks`,
        :data:`recon.cloud.MAX_STEP_FOOTPRINTS`).
    poisson_depth
        Octree depth for :func:`poisson_mesh`.
    confidence
        ``(H, W)`` confidence in ``[0, 1]`` (``confidence.pfm``), or ``None``. Written as the float
        vertex property ``confidence`` (points and grid meshes; a Poisson mesh's vertices are new).
    min_confidence, search_range, keep_all
        Unless ``keep_all``, pixels with confidence below ``min_confidence`` or a disparity outside
        ``search_range`` are left out (:func:`trusted_pixels`).
    provenance
        :func:`recon.provenance.provenance` of what made the file, written into the PLY header as
        ``comment`` lines (:func:`recon.provenance.ply_comments`) beside units, frame and the
        meaning of ``confidence``; or ``None``.
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
               "max_relative_jump": max_relative_jump, "max_step_footprints": max_step_footprints}
    cloud = point_cloud(depth, image, **options)
    depth_range = (float(cloud.points_mm[:, 2].min()), float(cloud.points_mm[:, 2].max())) if len(cloud) else None
    common = {"pixels_used": len(cloud), "pixels_total": int(disparity.size), "depth_range_mm": depth_range,
              "pixels_unreliable": unreliable}
    comments = list(PLY_FRAME_COMMENTS) + ply_comments(provenance)
    if confidence is not None:
        comments.append(PLY_CONFIDENCE_COMMENT)
        comments.append("confidence_filter every finite pixel kept" if keep_all else
                        f"confidence_filter pixels below {min_confidence:g} left out")

    def per_vertex(pixels: np.ndarray | None) -> np.ndarray | None:
        if confidence is None or pixels is None:
            return None
        return np.asarray(confidence)[pixels[:, 0], pixels[:, 1]]

    if kind == "points":
        written = write_cloud_ply(path, cloud, ascii=ascii, confidence=per_vertex(cloud.pixels), comments=comments)
        return ExportSummary(path=written, kind="points", points=len(cloud), triangles=0, **common)
    if poisson:
        mesh = poisson_mesh(cloud, depth=poisson_depth)
        comments.append(f"mesh screened Poisson reconstruction of the oriented cloud, octree depth {poisson_depth}")
    else:
        mesh = depth_mesh(depth, image, cloud=cloud, **options)
        comments.append(f"mesh pixel grid, cut where the disparity steps more than {max_step_footprints:g} pixel "
                        f"footprints beyond its local slope or depth jumps more than {max_relative_jump:g}")
    written = write_mesh_ply(path, mesh, ascii=ascii, confidence=per_vertex(mesh.pixels), comments=comments)
    edges = longest_edges(mesh.vertices_mm, mesh.triangles)
    return ExportSummary(
        path=written, kind="poisson" if poisson else "mesh", points=len(mesh.vertices_mm),
        triangles=len(mesh.triangles), long_triangles=int(np.count_nonzero(edges > 10 * np.median(edges))),
        **common,
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
    max_step_footprints: float = MAX_STEP_FOOTPRINTS,
    min_confidence: float = MIN_CONFIDENCE,
    keep_all: bool = False,
    command: Sequence[str] | None = None,
) -> ExportSummary:
    """:func:`export_ply` for a reconstruction folder (:func:`recon.result.read_result`).

    ``focal_px``, ``pitch_mm`` and ``disparity_offset`` override ``result.json`` when given. The
    folder's ``confidence.pfm`` and searched range (``result.json`` options) filter the pixels unless
    ``keep_all``. The PLY header names the light field the reconstruction read (``result.json``'s
    provenance, :func:`result_input`) and ``command`` (default: this process's command line).
    """
    from recon.result import read_result

    result = read_result(result_dir)
    camera = result.camera(focal_px=focal_px, pitch_mm=pitch_mm, disparity_offset=disparity_offset)
    return export_ply(
        ply_path,
        provenance=make_provenance(input=result_input(result), timings_s={}, command=command),
        disparity_px=result.disparity_px,
        image=result.image,
        camera=camera,
        mask=result.mask,
        kind=kind,
        poisson=poisson,
        ascii=ascii,
        max_relative_jump=max_relative_jump,
        max_step_footprints=max_step_footprints,
        confidence=result.confidence,
        min_confidence=min_confidence,
        search_range=result.search_range,
        keep_all=keep_all,
    )


def result_input(result) -> dict[str, Any]:
    """The input identity of a reconstruction folder (:class:`recon.result.ResultFolder`): its
    ``result.json`` provenance's ``input``, else the ``source`` folder it names, not hashed."""
    recorded = (result.record.provenance or {}).get("input")
    if isinstance(recorded, dict) and recorded.get("kind"):
        return recorded
    return {"kind": "unknown", "path": result.record.source}
