"""The 3D model that the report's interactive view shows, and the files that carry it to the browser.

A page opened from ``file://`` can neither ``fetch()`` a PLY nor load ES modules, so the model travels
in a classic script, ``model-data.js``, that sets the global ``LFRIG_MODEL``: vertex positions
(float32, mm, centre camera frame of ``docs/conventions.md``), triangle indices (uint32) and three
ready-made vertex colourings (the centre view, depth, confidence; uint8 RGB), each base64 encoded.
``viewer.js`` (lfrig's) draws it with the vendored three.js bundle (``vendor/``).

- :func:`read_ply`: an exported PLY (binary little-endian or ASCII, as :mod:`recon.export` writes
  them) as a :class:`ViewerModel`;
- :func:`cloud_model`: the points of a depth map, when no PLY was exported;
- :func:`decimate`: at most ``max_triangles`` triangles (vertex clustering) or ``max_points`` points
  (a seeded sample), so that a browser draws the model smoothly;
- :func:`write_viewer_files`: ``model-data.js`` and the viewer's scripts into a report folder.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from recon.colour import LUTS, colour_map
from recon.errors import ReconError

#: What the browser is given at most: triangles of a mesh, points of a cloud.
MAX_TRIANGLES = 250_000
MAX_POINTS = 250_000
#: The files :func:`write_viewer_files` puts into a report folder (scripts in load order, then the licence).
LIBRARY_JS = "three.viewer.min.js"
LIBRARY_LICENCE = "LICENSE-three.txt"
VIEWER_JS = "viewer.js"
MODEL_JS = "model-data.js"

_HERE = Path(__file__).parent


@dataclass
class ViewerModel:
    """A mesh or point cloud for the 3D view.

    Attributes
    ----------
    vertices_mm
        ``(N, 3)`` float32, mm, camera frame of the centre view (x right, y down, z forward).
    triangles
        ``(M, 3)`` int64 vertex indices, counter-clockwise as seen from the camera; ``None`` for a cloud.
    colours
        ``(N, 3)`` uint8 RGB of the centre view, or ``None``.
    confidence
        ``(N,)`` float32 in ``[0, 1]``, or ``None``.
    name
        What the model is, for the page (e.g. the PLY's file name).
    original
        ``(vertices, triangles)`` before :func:`decimate`.
    """

    vertices_mm: np.ndarray
    triangles: np.ndarray | None
    colours: np.ndarray | None
    confidence: np.ndarray | None
    name: str
    original: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        self.vertices_mm = np.asarray(self.vertices_mm, np.float32).reshape(-1, 3)
        n = len(self.vertices_mm)
        if self.triangles is not None:
            self.triangles = np.asarray(self.triangles, np.int64).reshape(-1, 3)
            if self.triangles.size and (self.triangles.min() < 0 or self.triangles.max() >= n):
                raise ValueError(f"{self.name}: triangle indices must lie in [0, {n})")
        if self.colours is not None:
            self.colours = np.asarray(self.colours, np.uint8).reshape(n, 3)
        if self.confidence is not None:
            self.confidence = np.asarray(self.confidence, np.float32).reshape(n)
        if self.original == (0, 0):
            self.original = (n, 0 if self.triangles is None else len(self.triangles))

    @property
    def kind(self) -> str:
        return "points" if self.triangles is None else "mesh"


# --------------------------------------------------------------------------------------------------
# models from files and maps
# --------------------------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path) -> ViewerModel:
    """Read a PLY point cloud or triangle mesh (``format binary_little_endian`` or ``ascii``).

    Reads the vertex properties ``x y z`` (mm), ``red green blue`` (uchar) and ``confidence`` when
    present, and a ``face`` element's ``vertex_indices`` (or ``vertex_index``) lists of three.

    Raises
    ------
    ReconError
        Naming the file: missing, not a PLY, another encoding, or faces that are not triangles.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise ReconError(f"{path}: cannot read the PLY file ({error.strerror})") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ReconError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    body_at = data.index(b"\n", end) + 1
    elements: list[tuple[str, int, list[list[str]]]] = []
    fmt = None
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) >= 2:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and elements:
            elements[-1][2].append(words[1:])
    if fmt not in ("binary_little_endian", "ascii"):
        raise ReconError(f"{path}: PLY format {fmt!r} is not read here; write binary little-endian or ASCII")
    columns: dict[str, dict[str, np.ndarray]] = {}
    if fmt == "ascii":
        tokens = data[body_at:].split()
        at = 0
        for name, count, props in elements:
            columns[name], at = _ascii_element(path, tokens, at, count, props)
    else:
        at = body_at
        for name, count, props in elements:
            if any(p[0] == "list" for p in props):
                columns[name], at = _binary_lists(path, data, at, count, props)
            else:
                dtype = np.dtype([(p[-1], "<" + _PLY_TYPES[p[0]]) for p in props])
                size = count * dtype.itemsize
                if at + size > len(data):
                    raise ReconError(f"{path}: the file is shorter than its header says")
                block = np.frombuffer(data, dtype, count, at)
                columns[name] = {key: block[key] for key in dtype.names}
                at += size
    vertex = columns.get("vertex", {})
    if not {"x", "y", "z"} <= set(vertex):
        raise ReconError(f"{path}: the PLY has no vertex x, y, z")
    vertices = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=-1)
    colours = (np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=-1)
               if {"red", "green", "blue"} <= set(vertex) else None)
    confidence = vertex.get("confidence")
    triangles = None
    face = columns.get("face")
    if face:
        lists = face.get("vertex_indices", face.get("vertex_index"))
        if lists is None or lists.ndim != 2 or (len(lists) and lists.shape[1] != 3):
            raise ReconError(f"{path}: the faces are not triangles; lfrig's 3D view shows triangle meshes")
        triangles = lists.astype(np.int64).reshape(-1, 3)
    return ViewerModel(vertices_mm=vertices, triangles=triangles, colours=colours, confidence=confidence,
                       name=path.name)


def _ascii_element(path: Path, tokens: list[bytes], at: int, count: int, props: list[list[str]]):
    """One element of an ASCII PLY from ``tokens[at:]``: scalar properties as columns, list properties
    as ``(count, n)`` arrays (every list of one property must have the same length ``n``)."""
    widths = []
    for prop in props:  # the row layout, from the first row's list lengths
        widths.append(1 + int(tokens[at + sum(widths)]) if prop[0] == "list" else 1)
    size = count * sum(widths)
    if at + size > len(tokens):
        raise ReconError(f"{path}: the file is shorter than its header says")
    try:
        table = np.asarray(tokens[at:at + size], dtype=np.float64).reshape(count, sum(widths))
    except ValueError:
        raise ReconError(f"{path}: a value in the PLY body is not a number") from None
    out, first = {}, 0
    for prop, width in zip(props, widths):
        if prop[0] == "list":
            if count and not (table[:, first] == width - 1).all():
                raise ReconError(f"{path}: the faces are not all triangles; lfrig's 3D view shows triangle meshes")
            out[prop[-1]] = table[:, first + 1:first + width]
        else:
            out[prop[-1]] = table[:, first]
        first += width
    return out, at + size


def _binary_lists(path: Path, data: bytes, at: int, count: int, props: list[list[str]]):
    """An element with list properties, read fast when every list has three entries (triangles)."""
    fields = []
    for p in props:
        if p[0] == "list":
            fields += [(p[-1] + "#n", "<" + _PLY_TYPES[p[1]]), (p[-1], "<" + _PLY_TYPES[p[2]], (3,))]
        else:
            fields.append((p[-1], "<" + _PLY_TYPES[p[0]]))
    dtype = np.dtype(fields)
    size = count * dtype.itemsize
    if at + size > len(data):
        raise ReconError(f"{path}: the file is shorter than its header says")
    block = np.frombuffer(data, dtype, count, at)
    for p in props:
        if p[0] == "list" and count and not (block[p[-1] + "#n"] == 3).all():
            raise ReconError(f"{path}: the faces are not all triangles; lfrig's 3D view shows triangle meshes")
    return {p[-1]: block[p[-1]] for p in props}, at + size


def cloud_model(depth_mm: np.ndarray, *, focal_px: float, principal_point_px=None, image: np.ndarray | None = None,
                keep: np.ndarray | None = None, confidence: np.ndarray | None = None,
                name: str = "points of the depth map") -> ViewerModel:
    """The back-projected pixels of ``(H, W)`` ``depth_mm`` (finite, positive and ``keep``) as a cloud.

    ``image``: ``(H, W, 3)`` uint8 RGB colours; ``confidence``: ``(H, W)`` in ``[0, 1]``.
    """
    from recon.cloud import depth_to_points, valid_depth

    points = depth_to_points(depth_mm, focal_px=focal_px, principal_point_px=principal_point_px)
    chosen = valid_depth(depth_mm, mask=keep)
    return ViewerModel(vertices_mm=points[chosen], triangles=None,
                       colours=None if image is None else np.asarray(image)[chosen],
                       confidence=None if confidence is None else np.asarray(confidence)[chosen], name=name)


# --------------------------------------------------------------------------------------------------
# decimation
# --------------------------------------------------------------------------------------------------


def decimate(model: ViewerModel, *, max_triangles: int = MAX_TRIANGLES, max_points: int = MAX_POINTS,
             seed: int = 0) -> ViewerModel:
    """A model small enough for a browser: at most ``max_triangles`` triangles or ``max_points`` points.

    A mesh is simplified by vertex clustering: vertices in one cube of side ``h`` mm become one, at
    their mean position (colour and confidence averaged too); triangles whose corners fall into fewer
    than three cubes, and repeated triangles, go. ``h`` starts at the median edge length times
    ``sqrt(M / max_triangles)`` and grows by 25 % until few enough triangles are left. A cloud keeps a
    random sample (``seed``). A model already small enough is returned as it is.
    """
    if model.triangles is None:
        count = len(model.vertices_mm)
        if count <= max_points:
            return model
        chosen = np.sort(np.random.default_rng(seed).choice(count, max_points, replace=False))
        return replace(model, vertices_mm=model.vertices_mm[chosen],
                       colours=None if model.colours is None else model.colours[chosen],
                       confidence=None if model.confidence is None else model.confidence[chosen])
    triangles = model.triangles
    if len(triangles) <= max_triangles:
        return model
    vertices = model.vertices_mm.astype(np.float64)
    edges = np.linalg.norm(vertices[triangles[:, 0]] - vertices[triangles[:, 1]], axis=-1)
    cell = float(np.median(edges)) * np.sqrt(len(triangles) / max_triangles)
    while True:
        out = _cluster(model, vertices, cell)
        if len(out.triangles) <= max_triangles:
            return out
        cell *= 1.25


def _cluster(model: ViewerModel, vertices: np.ndarray, cell: float) -> ViewerModel:
    keys = np.floor((vertices - vertices.min(axis=0)) / cell).astype(np.int64)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, label = np.unique(flat, return_inverse=True)
    groups = int(label.max()) + 1
    counts = np.bincount(label, minlength=groups).astype(np.float64)

    def mean(values: np.ndarray) -> np.ndarray:
        values = np.asarray(values, np.float64)
        if values.ndim == 1:
            return np.bincount(label, values, groups) / counts
        return np.stack([np.bincount(label, values[:, k], groups) for k in range(values.shape[1])], -1) / counts[:, None]

    triangles = label[model.triangles]
    whole = (triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]) & (triangles[:, 0] != triangles[:, 2])
    triangles = triangles[whole]
    _, first = np.unique(np.sort(triangles, axis=1), axis=0, return_index=True)
    triangles = triangles[np.sort(first)]
    used, triangles = np.unique(triangles, return_inverse=True)
    return replace(model, vertices_mm=mean(vertices)[used].astype(np.float32), triangles=triangles.reshape(-1, 3),
                   colours=None if model.colours is None else np.round(mean(model.colours)[used]).astype(np.uint8),
                   confidence=None if model.confidence is None else mean(model.confidence)[used].astype(np.float32))


# --------------------------------------------------------------------------------------------------
# the files for the browser
# --------------------------------------------------------------------------------------------------


def _b64(array: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()).decode("ascii")


def model_payload(model: ViewerModel) -> dict[str, Any]:
    """The JSON object ``model-data.js`` assigns to ``LFRIG_MODEL``.

    Keys: ``kind`` ("mesh" or "points"), ``name``, ``vertices``, ``triangles``, ``original``
    ([vertices, triangles] before decimation), ``positions`` (base64 little-endian float32, ``3N``),
    ``indices`` (base64 uint32, ``3M``, meshes only), ``colourings`` (``{name: {"rgb": base64 uint8
    3N, "legend": text}}`` for "image", "depth" and "confidence", those there are data for),
    ``depth_range_mm``.
    """
    vertices = model.vertices_mm
    depth = vertices[:, 2].astype(np.float64)
    colourings: dict[str, dict[str, str]] = {}
    if model.colours is not None:
        colourings["image"] = {"rgb": _b64(model.colours, "u1"), "legend": "colours of the centre view"}
    low = high = None
    if len(depth):
        low, high = (float(v) for v in np.percentile(depth, [1, 99]))
        high = high if high > low else low + 1.0
        outside = float(np.mean((depth < low) | (depth > high))) * 100.0
        rgb = colour_map(depth, low=low, high=high, lut="turbo_r")
        colourings["depth"] = {"rgb": _b64(rgb, "u1"), "legend": (
            f"depth, near red … far blue: {low:.1f} … {high:.1f} mm, clipped to the 1st–99th percentile "
            f"({outside:.1f} % of vertices outside)"), "lut": _lut_css("turbo_r")}
    if model.confidence is not None:
        rgb = colour_map(model.confidence, low=0.0, high=1.0, lut="viridis")
        colourings["confidence"] = {"rgb": _b64(rgb, "u1"), "legend": "confidence 0 (purple) … 1 (yellow), "
                                    "the full range, nothing clipped", "lut": _lut_css("viridis")}
    payload = {"kind": model.kind, "name": model.name, "vertices": int(len(vertices)),
               "triangles": 0 if model.triangles is None else int(len(model.triangles)),
               "original": [int(v) for v in model.original], "positions": _b64(vertices, "f4"),
               "colourings": colourings, "depth_range_mm": None if low is None else [low, high]}
    if model.triangles is not None:
        payload["indices"] = _b64(model.triangles, "u4")
    return payload


def _lut_css(lut: str) -> str:
    """A CSS linear gradient of a colour map, for the legend's bar."""
    table = LUTS[lut]()
    stops = ", ".join(f"rgb({r},{g},{b})" for r, g, b in table[::32].tolist() + [table[-1].tolist()])
    return f"linear-gradient(to right, {stops})"


def write_viewer_files(out_dir, model: ViewerModel) -> list[str]:
    """Write ``model-data.js`` for ``model`` and copy the library, its licence and ``viewer.js`` into
    ``out_dir``. Returns the scripts' names in the order the page loads them."""
    from recon.lf.imageio import write_bytes_atomic

    out = Path(out_dir)
    for name, source in ((LIBRARY_JS, _HERE / "vendor" / LIBRARY_JS), (LIBRARY_LICENCE, _HERE / "vendor" / LIBRARY_LICENCE),
                         (VIEWER_JS, _HERE / VIEWER_JS)):
        if not source.is_file():
            raise ReconError(f"{source}: the report's 3D viewer is missing from this installation; reinstall lfrig "
                             "(or run recon/report/vendor/build.sh)")
        write_bytes_atomic(out / name, source.read_bytes())  # whole or not at all; a link there is replaced
    text = "window.LFRIG_MODEL = " + json.dumps(model_payload(model), separators=(",", ":")) + ";\n"
    write_bytes_atomic(out / MODEL_JS, text.encode("ascii"))
    return [LIBRARY_JS, MODEL_JS, VIEWER_JS]
