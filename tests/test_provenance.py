"""How a result was made, recorded everywhere (issue 23): ``lfrig --version``, ``result.json``'s
``provenance``, the batch summary and the PLY header; and the camera checked before any work."""

from __future__ import annotations

import hashlib
import json
import shutil
from datetime import datetime
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from rig.main import main

TINY = Path(__file__).resolve().parents[1] / "fixtures" / "tiny_capture"
FLAGS = ["--method", "baseline", "--window", "5", "--quiet"]


def check_shape(made: dict) -> None:
    """The record the report footer reads: these keys, these types."""
    assert set(made) == {"lfrig_version", "command", "started_utc", "input", "timings_s", "machine"}
    assert isinstance(made["lfrig_version"], str) and made["lfrig_version"].startswith(metadata.version("lfrig"))
    assert isinstance(made["command"], list) and all(isinstance(part, str) for part in made["command"])
    assert datetime.fromisoformat(made["started_utc"]).utcoffset().total_seconds() == 0
    assert {"kind", "path"} <= set(made["input"])
    assert all(isinstance(v, float) and v >= 0 for v in made["timings_s"].values())
    machine = made["machine"]
    assert set(machine) == {"python", "platform", "cpus", "numba_threads", "kernels"}
    assert isinstance(machine["cpus"], int) and machine["cpus"] >= 1 and machine["numba_threads"] >= 1
    assert all(v == "C" or v.startswith("numba: ") for v in machine["kernels"].values())


def test_version_comes_from_the_package_metadata(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out.strip()
    version = metadata.version("lfrig")
    assert out == f"lfrig {version}" or out.startswith(f"lfrig {version}+g")
    if (Path(__file__).resolve().parents[1] / ".git").exists() and shutil.which("git"):
        import subprocess

        head = subprocess.run(["git", "-C", str(Path(__file__).parent), "rev-parse", "--short=7", "HEAD"],
                              capture_output=True, text=True).stdout.strip()
        assert out == f"lfrig {version}+g{head}"


def test_reconstruct_records_version_command_input_timings_and_machine(tmp_path):
    out = tmp_path / "out"
    argv = ["reconstruct", str(TINY), "-o", str(out), *FLAGS, "--ply", str(out / "model.ply")]
    assert main(argv) == 0
    record = json.loads((out / "result.json").read_text())
    made = record["provenance"]
    check_shape(made)
    assert made["command"] == ["lfrig", *argv]
    journal = hashlib.sha256((TINY / "manifest.jsonl").read_bytes()).hexdigest()
    assert made["input"] == {"kind": "capture", "path": str(TINY.resolve()), "journal_sha256": journal}
    assert set(made["timings_s"]) == {"read", "estimate", "write"}
    assert record["options"]["window"] == 5  # the options stay where they were
    from recon.native import library, unavailable  # the baseline's sweep: which kernel ran

    assert made["machine"]["kernels"]["sweep"] == ("C" if library("sweep") else f"numba: {unavailable('sweep')}")

    # the PLY the same command wrote says the same, and where it is and in which unit
    comments = ply_header(out / "model.ply")["comments"]
    assert f"lfrig_version {made['lfrig_version']}" in comments
    assert "command lfrig " + " ".join(argv) in comments
    assert f"source capture {TINY.resolve()}" in comments and f"source_journal_sha256 {journal}" in comments
    assert "units mm" in comments and any(c.startswith("frame centre camera") for c in comments)


def test_a_benchmark_folder_is_identified_by_its_files(tmp_path, monkeypatch):
    import recon.provenance
    from recon.lf import read_lightfield
    from recon.lf.imageio import write_png
    from recon.lf.params import parameters_for, write_parameters
    from recon.pipeline import reconstruct_to_folder
    from recon.provenance import input_identity

    lf = read_lightfield(TINY)
    bench = tmp_path / "bench"
    bench.mkdir()

    rows, cols = lf.grid_shape
    for u in range(rows):
        for v in range(cols):
            write_png(bench / f"input_Cam{u * cols + v:03d}.png", lf.views[u, v])
    write_parameters(bench / "parameters.cfg", parameters_for(grid=(rows, cols), image_shape=lf.image_shape,
                                                             pitch_mm=0.5, focal_px=1000.0))
    first = input_identity(bench)
    assert first["kind"] == "benchmark" and len(first["files_sha256"]) == 64
    hashed, file_sha256 = [], recon.provenance.file_sha256
    monkeypatch.setattr(recon.provenance, "file_sha256", lambda path: hashed.append(path.name) or file_sha256(path))
    folder = reconstruct_to_folder(bench, tmp_path / "out", method="baseline", options={"window": 5},
                                   command=["lfrig", "test"])
    assert folder.record.provenance["input"] == first and folder.record.provenance["command"] == ["lfrig", "test"]
    assert hashed == ["parameters.cfg"]  # the views were hashed as they were read, not read again
    monkeypatch.undo()
    # another view's content (same name, same size) is another input
    view = bench / "input_Cam004.png"
    write_png(view, 255 - lf.views[1, 1])
    assert input_identity(bench)["files_sha256"] != first["files_sha256"]


def test_the_batch_summary_records_the_batch_and_each_captures_input(tmp_path):
    from recon.scale.batch import SUMMARY, BatchRequest, prepare_batch, run_batch

    out = tmp_path / "results"
    plan = prepare_batch([], out, request=BatchRequest(method="baseline", options={"window": 5}))
    plan.command = ["lfrig", "batch", "reconstruct", "-o", str(out)]
    run_batch(None, plan)
    made = json.loads((out / SUMMARY).read_text())["provenance"]
    check_shape(made)
    assert made["command"] == plan.command
    assert made["input"] == {"kind": "batch", "path": str(out.resolve()), "captures": {}}
    assert set(made["timings_s"]) == {"total"}


# --------------------------------------------------------------------------------------------------
# the PLY, read back by open3d and by a plain parser


def ply_header(path: Path) -> dict:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    elements, properties, current = {}, {}, None
    for line in lines:
        parts = line.split()
        if parts[0] == "element":
            current = parts[1]
            elements[current] = int(parts[2])
            properties[current] = []
        elif parts[0] == "property":
            properties[current].append(parts[1:])
    return {"format": lines[1], "comments": [line[len("comment "):] for line in lines if line.startswith("comment ")],
            "elements": elements, "properties": properties, "body": data[end:]}


def read_plain_ply(path: Path) -> dict:
    """A PLY reader that knows nothing of lfrig: the header decides the layout."""
    head = ply_header(path)
    kinds = {"float": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4", "uint": "<u4"}
    vertex = np.dtype([(p[-1], kinds[p[0]]) for p in head["properties"]["vertex"]])
    count = head["elements"]["vertex"]
    if head["format"] == "format ascii 1.0":
        rows = head["body"].decode("ascii").splitlines()
        table = np.array([row.split() for row in rows[:count]], float)
        vertices = np.empty(count, vertex)
        for k, name in enumerate(vertex.names):
            vertices[name] = table[:, k]
        faces = np.array([row.split()[1:] for row in rows[count:]], int).reshape(-1, 3)
    else:
        vertices = np.frombuffer(head["body"], vertex, count=count)
        face = np.dtype([("n", "u1"), ("v", "<u4", 3)])
        faces = np.frombuffer(head["body"], face, count=head["elements"].get("face", 0), offset=vertex.itemsize * count)
        assert np.all(faces["n"] == 3)
        assert len(head["body"]) == vertex.itemsize * count + face.itemsize * len(faces)
        faces = faces["v"]
    return {**head, "vertices": vertices, "faces": faces}


@pytest.mark.parametrize("ascii", [False, True])
@pytest.mark.parametrize("kind", ["mesh", "points"])
def test_ply_is_float32_with_confidence_and_says_what_it_holds(tmp_path, kind, ascii):
    import open3d as o3d

    from recon.camera import Camera
    from recon.export import export_ply
    from recon.provenance import provenance

    rng = np.random.default_rng(2)
    disparity = (1.0 + 0.002 * rng.standard_normal((12, 14))).astype(np.float32)
    confidence = rng.uniform(0.5, 1.0, disparity.shape).astype(np.float32)
    image = rng.integers(0, 256, disparity.shape + (3,), dtype=np.uint8)
    made = provenance(input={"kind": "capture", "path": "/lab/cap é", "journal_sha256": "ab" * 32}, timings_s={},
                      command=["lfrig", "export", "R", "--ply", "x y.ply"])
    summary = export_ply(tmp_path / "m.ply", disparity_px=disparity, image=image, camera=Camera(focal_px=500.0, pitch_mm=2.0),
                         kind=kind, ascii=ascii, confidence=confidence, provenance=made)
    plain = read_plain_ply(summary.path)
    names = [p[-1] for p in plain["properties"]["vertex"]]
    assert names == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "confidence"]
    assert [p[0] for p in plain["properties"]["vertex"]] == ["float"] * 6 + ["uchar"] * 3 + ["float"]
    comments = plain["comments"]
    assert comments[0] == "Created by lfrig"
    assert "command lfrig export R --ply 'x y.ply'" in comments
    assert "source capture /lab/cap \\xe9" in comments  # one ASCII line, escaped
    assert any(c.startswith("confidence per-vertex confidence of the disparity in [0, 1]") for c in comments)
    assert "confidence_filter pixels below 0.5 left out" in comments
    assert any(c.startswith("mesh pixel grid, cut where") for c in comments) == (kind == "mesh")

    vertices = plain["vertices"]
    assert len(vertices) == summary.points == 12 * 14
    np.testing.assert_allclose(vertices["z"], 1000.0, rtol=0.01)  # 500 px * 2 mm / 1 px
    np.testing.assert_allclose(np.sort(vertices["confidence"]), np.sort(confidence.ravel()), rtol=1e-6)
    normals = np.stack([vertices[n] for n in ("nx", "ny", "nz")], axis=-1)
    points = np.stack([vertices[n] for n in ("x", "y", "z")], axis=-1)
    assert np.all(np.einsum("ij,ij->i", normals, points) < 0)  # facing the camera
    if kind == "mesh":
        assert len(plain["faces"]) == summary.triangles > 0

    read = o3d.io.read_triangle_mesh(str(summary.path)) if kind == "mesh" else o3d.io.read_point_cloud(str(summary.path))
    o3d_points = np.asarray(read.vertices if kind == "mesh" else read.points)
    np.testing.assert_allclose(o3d_points, points, rtol=1e-6)
    if kind == "points":
        np.testing.assert_allclose(np.asarray(read.normals), normals, atol=1e-6)
        np.testing.assert_allclose(np.asarray(read.colors) * 255, np.stack([vertices[c] for c in ("red", "green", "blue")], -1), atol=1e-3)


# --------------------------------------------------------------------------------------------------
# camera parameters checked before any work


def capture_without_camera(tmp_path: Path) -> Path:
    """The tiny capture with its focal length taken out of parameters.cfg."""
    bare = tmp_path / "bare"
    shutil.copytree(TINY, bare)
    cfg = bare / "parameters.cfg"
    text = cfg.read_text()
    text = "\n".join(line for line in text.splitlines() if not line.startswith(("focal_px", "focal_length_mm")))
    cfg.write_text(text + "\n")
    return bare


def test_reconstruct_ply_without_camera_is_refused_before_the_estimate(tmp_path, capsys, monkeypatch):
    import recon.pipeline as pipeline

    bare = capture_without_camera(tmp_path)
    ran = []
    monkeypatch.setattr(pipeline, "run_in_process", lambda *a: ran.append(a))
    out = tmp_path / "out"
    assert main(["reconstruct", str(bare), "-o", str(out), *FLAGS, "--ply", str(tmp_path / "m.ply"), "--no-verify"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("lfrig: error: ")
    assert "no focal_px" in err and "drop --ply" in err and "lfrig export" in err and "--focal-px" in err
    assert not ran and not (out / "disparity.pfm").exists()


def test_import_without_focal_length_warns_that_only_disparity_will_come(tmp_path, capsys):
    from recon.lf import read_lightfield
    from recon.lf.imageio import write_png

    plain = tmp_path / "plain"
    plain.mkdir()
    lf = read_lightfield(TINY)
    for u in range(3):
        for v in range(3):
            write_png(plain / f"view_{u}_{v}.png", lf.views[u, v])
    common = ["import", str(plain), "--pattern", "view_{u}_{v}.png", "--rows", "3", "--cols", "3", "--pitch-mm", "0.5",
              "--quiet"]
    assert main([*common, "-o", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "lfrig: warning:" in err and "only give disparity" in err and "--focal-px" in err
    assert main([*common, "-o", str(tmp_path / "b"), "--focal-px", "1000"]) == 0
    assert "warning" not in capsys.readouterr().err
