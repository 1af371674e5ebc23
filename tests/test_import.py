"""``lfrig import``: views from another tool's folder become an lfrig capture; bad input writes nothing."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.lf import read_lightfield
from recon.lf.importer import ViewImportError, capture_order, import_views, natural_key, parse_pattern
from recon.lf.pfm import read_pfm, write_pfm
from rig.main import main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
TINY = FIXTURES / "tiny_capture"
FAST = ["--method", "baseline", "--disparity-range", "-1", "1.5", "--step", "0.25", "--quiet"]


def write_image(path: Path, image: np.ndarray) -> None:
    """Write as another tool would: OpenCV's encoder, BGR order on disk."""
    assert cv2.imwrite(str(path), image[:, :, ::-1] if image.ndim == 3 else image)


def export_plain(lf, folder: Path, name_of) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rows, cols = lf.grid_shape
    for u in range(rows):
        for v in range(cols):
            write_image(folder / name_of(u, v), lf.views[u, v])


def nothing_written(tmp_path: Path, target: Path) -> bool:
    return not target.exists() and not any(p.name.startswith(f".{target.name}.import") for p in tmp_path.iterdir())


def one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("lfrig:")]
    assert len(err) == 1, err
    return err[0]


# --------------------------------------------------------------------------------------------------
# Round trips


def test_capture_exported_to_tiffs_and_imported_back_reconstructs_identically(tmp_path, capsys):
    original = read_lightfield(TINY)
    plain = tmp_path / "plain"
    export_plain(original, plain, lambda u, v: f"img_{v:02d}-{u:02d}.tif")
    out = tmp_path / "imported"
    assert main(["import", str(plain), "-o", str(out), "--pattern", "img_{v:02d}-{u:02d}.tif", "--rows", "3",
                 "--cols", "3", "--pitch-mm", str(original.pitch_mm), "--focal-px", str(original.focal_px),
                 "--quiet"]) == 0
    assert "imported from" in capsys.readouterr().out
    back = read_lightfield(out)
    assert np.array_equal(back.views, original.views)
    assert (back.pitch_mm, back.focal_px) == (original.pitch_mm, original.focal_px)
    for lf_dir, rec in ((TINY, tmp_path / "rec_a"), (out, tmp_path / "rec_b")):
        assert main(["reconstruct", str(lf_dir), "-o", str(rec), *FAST]) == 0
    assert np.array_equal(read_pfm(tmp_path / "rec_a" / "disparity.pfm"), read_pfm(tmp_path / "rec_b" / "disparity.pfm"))
    # the journal records both checksums of every view, and the import settings
    lines = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert lines[0]["imported"]["pattern"] == "img_{v:02d}-{u:02d}.tif"
    views = [r for r in lines if r.get("kind") == "view"]
    assert len(views) == 9 and all(len(r["sha256"]) == 64 and len(r["source_sha256"]) == 64 for r in views)
    assert {r["source"] for r in views} == {p.name for p in plain.iterdir()}
    assert lines[-1]["kind"] == "complete"


@pytest.mark.parametrize("order", ["serpentine", "raster"])
def test_files_in_capture_order(tmp_path, order):
    original = read_lightfield(TINY)
    plain = tmp_path / "plain"
    plain.mkdir()
    for i, (u, v) in enumerate(capture_order(3, 3, order=order), start=1):
        write_image(plain / f"frame{i}.png", original.views[u, v])  # frame1 .. frame9: natural order matters
    (plain / "notes.txt").write_text("not an image")
    out = tmp_path / "cap"
    import_views(plain, out, order=order, rows=3, cols=3, pitch_mm=0.5)
    assert np.array_equal(read_lightfield(out).views, original.views)
    # the same through an {i} pattern with indices from 1
    out2 = tmp_path / "cap2"
    import_views(plain, out2, order=order, rows=3, cols=3, pitch_mm=0.5, pattern="frame{i}.png", index_base=1)
    assert np.array_equal(read_lightfield(out2).views, original.views)


def test_benchmark_layout_keeps_its_parameters(tmp_path):
    original = read_lightfield(TINY)
    bench = tmp_path / "bench"
    export_plain(original, bench, lambda u, v: f"input_Cam{u * 3 + v:03d}.png")
    (bench / "parameters.cfg").write_text((TINY / "parameters.cfg").read_text())
    out = tmp_path / "cap"
    seen = []
    import_views(bench, out, principal_point_px=(15.0, 16.5), progress=lambda f, m="": seen.append((f, m)))
    assert seen[0] == (0.4, "checking the order") and seen[-1][0] == 1.0  # a line before the check, not after
    back = read_lightfield(out)
    assert np.array_equal(back.views, original.views)
    assert back.focal_px == original.focal_px and back.pitch_mm == original.pitch_mm
    assert back.disparity_range == original.disparity_range and back.principal_point_px == (15.0, 16.5)


@pytest.mark.hci
@pytest.mark.slow
def test_the_benchmark_scene_imports(tmp_path, hci_scene_dir):
    scene = hci_scene_dir
    out = tmp_path / "backgammon"
    import_views(scene, out)
    original, back = read_lightfield(scene), read_lightfield(out)
    assert np.array_equal(back.views, original.views)
    assert back.focal_px == pytest.approx(original.focal_px) and back.pitch_mm == original.pitch_mm
    assert back.disparity_offset == pytest.approx(original.disparity_offset)


def test_capture_order_is_the_rigs_scan_order():
    from rig.grid import scan_order

    for rows, cols in ((1, 1), (2, 3), (3, 2), (9, 9), (4, 5)):
        for order in ("serpentine", "raster"):
            assert capture_order(rows, cols, order=order) == scan_order(rows, cols, order=order)


# --------------------------------------------------------------------------------------------------
# Patterns


def test_pattern_matching_is_exact():
    p = parse_pattern("img_{v:02d}-{u:02d}.tif")
    assert p.match("img_03-11.tif") == {"u": 11, "v": 3}
    assert p.match("img_3-11.tif") is None  # not how the pattern writes 3
    assert p.match("img_03-11.tiff") is None
    assert parse_pattern("r{row}c{col}.png").match("r2c10.png") == {"u": 2, "v": 10}
    assert parse_pattern("f{i:04d}.png").match("f0012.png") == {"i": 12}


@pytest.mark.parametrize("text,message", [
    ("view_{q}_{r}.png", "unknown field {q}"),
    ("view_{u}.png", "needs both {u} and {v}"),
    ("view_{u}_{u}_{v}.png", "appears twice"),
    ("view_{u}_{v:.2f}.png", "must be a whole number"),
    ("sub/view_{u}_{v}.png", "without folders"),
    ("view_{u}_{v.png", "write fields as"),
])
def test_bad_patterns(text, message):
    with pytest.raises(ViewImportError, match=message.replace("{", r"\{").replace("}", r"\}")):
        parse_pattern(text)


def test_natural_order():
    names = ["img10.png", "img2.png", "img1.png", "img20.png"]
    assert sorted(names, key=natural_key) == ["img1.png", "img2.png", "img10.png", "img20.png"]


# --------------------------------------------------------------------------------------------------
# Bad input: one line naming the file, nothing written


@pytest.fixture
def plain(tmp_path) -> Path:
    folder = tmp_path / "plain"
    export_plain(read_lightfield(TINY), folder, lambda u, v: f"view_{u}_{v}.png")
    return folder


def run_import(plain: Path, target: Path, *extra: str) -> int:
    return main(["import", str(plain), "-o", str(target), "--pattern", "view_{u}_{v}.png", "--rows", "3", "--cols", "3",
                 "--pitch-mm", "0.5", "--quiet", *extra])


def test_missing_view(plain, tmp_path, capsys):
    (plain / "view_1_2.png").unlink()
    assert run_import(plain, tmp_path / "cap") == 2
    assert "1 of 9 views missing (view_1_2.png)" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_mixed_sizes(plain, tmp_path, capsys):
    write_image(plain / "view_2_1.png", np.zeros((30, 32, 3), np.uint8))
    assert run_import(plain, tmp_path / "cap") == 2
    line = one_error_line(capsys)
    assert "view_2_1.png: image is 32x30 RGB 8-bit but view_0_0.png is 32x32 RGB 8-bit" in line
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_mixed_bit_depths(plain, tmp_path, capsys):
    write_image(plain / "view_0_1.png", np.zeros((32, 32, 3), np.uint16))
    assert run_import(plain, tmp_path / "cap") == 2
    assert "view_0_1.png: image is 32x32 RGB 16-bit but view_0_0.png is 32x32 RGB 8-bit" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_mixed_colour(plain, tmp_path, capsys):
    write_image(plain / "view_2_2.png", np.zeros((32, 32), np.uint8))
    assert run_import(plain, tmp_path / "cap") == 2
    assert "view_2_2.png: image is 32x32 grey 8-bit" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_float_tiff(tmp_path, capsys):
    folder = tmp_path / "plain"
    folder.mkdir()
    for u in range(2):
        for v in range(2):
            assert cv2.imwrite(str(folder / f"view_{u}_{v}.tif"), np.full((8, 8), 0.5, np.float32))
    assert main(["import", str(folder), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.tif", "--rows", "2",
                 "--cols", "2", "--pitch-mm", "1", "--quiet"]) == 2
    assert "view_0_0.tif: float32 pixels; lfrig views are 8- or 16-bit integers" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_corrupt_file(plain, tmp_path, capsys):
    (plain / "view_1_1.png").write_bytes(b"\x89PNG not really")
    assert run_import(plain, tmp_path / "cap") == 2
    assert "view_1_1.png: not a readable image" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_view_outside_the_grid(plain, tmp_path, capsys):
    write_image(plain / "view_3_0.png", np.zeros((32, 32, 3), np.uint8))
    assert run_import(plain, tmp_path / "cap") == 2
    assert "view_3_0.png: grid position (u=3, v=0) is outside the 3x3 grid" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_wrong_count_in_capture_order(plain, tmp_path, capsys):
    assert main(["import", str(plain), "-o", str(tmp_path / "cap"), "--order", "serpentine", "--rows", "3", "--cols",
                 "4", "--pitch-mm", "0.5", "--quiet"]) == 2
    assert "9 image files, but a 3x4 grid has 12 views" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_missing_flags_and_occupied_target(plain, tmp_path, capsys):
    assert main(["import", str(plain), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png", "--rows", "3",
                 "--cols", "3", "--quiet"]) == 2
    assert "give the grid pitch with --pitch-mm" in one_error_line(capsys)
    assert main(["import", str(plain), "-o", str(tmp_path / "cap"), "--pattern", "view_{u}_{v}.png",
                 "--pitch-mm", "0.5", "--quiet"]) == 2
    assert "give the grid size with --rows and --cols" in one_error_line(capsys)
    assert main(["import", str(plain), "-o", str(tmp_path / "cap"), "--pitch-mm", "0.5", "--quiet"]) == 2
    assert "say which file is which view" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "keep.txt").write_text("mine")
    assert run_import(plain, occupied) == 2
    assert "occupied: exists and is not empty" in one_error_line(capsys)
    assert [p.name for p in occupied.iterdir()] == ["keep.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert run_import(plain, empty) == 0  # an empty folder made for it is fine
    assert read_lightfield(empty).grid_shape == (3, 3)


def test_a_failure_while_writing_leaves_nothing(plain, tmp_path, monkeypatch):
    """Atomic: an error in the middle of writing removes the temporary folder; the target never appears."""
    import recon.lf.capture as capture

    calls = 0
    real = capture.write_png

    def failing(path, image):
        nonlocal calls
        calls += 1
        if calls == 5:
            raise OSError("disk full")
        return real(path, image)

    monkeypatch.setattr(capture, "write_png", failing)
    with pytest.raises(OSError, match="disk full"):
        import_views(plain, tmp_path / "cap", pattern="view_{u}_{v}.png", rows=3, cols=3, pitch_mm=0.5)
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_index_base_and_mode_mistakes(plain, tmp_path, capsys):
    # names start at 0, told 1: the views at 0 lie below the first index
    assert run_import(plain, tmp_path / "cap", "--index-base", "1") == 2
    assert "view_0_0.png: row 0, column 0 is below the first index 1; pass the index your names start at" in one_error_line(capsys)
    # a running index without an order
    assert main(["import", str(plain), "-o", str(tmp_path / "cap"), "--pattern", "view_{i}.png", "--pitch-mm", "0.5",
                 "--rows", "3", "--cols", "3", "--quiet"]) == 2
    assert "numbers the views in capture order: give --order" in one_error_line(capsys)
    # a position pattern with an order
    assert run_import(plain, tmp_path / "cap", "--order", "raster") == 2
    assert "places each view by its row and column; --order is for files in capture order" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")


@pytest.mark.parametrize("linked", ["gt_disp_lowres.pfm", "input_Cam004.png"])
def test_benchmark_layout_refuses_a_file_linked_from_outside(tmp_path, capsys, linked):
    original = read_lightfield(TINY)
    bench = tmp_path / "bench"
    export_plain(original, bench, lambda u, v: f"input_Cam{u * 3 + v:03d}.png")
    (bench / "parameters.cfg").write_text((TINY / "parameters.cfg").read_text())
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    if linked.endswith(".pfm"):
        write_pfm(outside / linked, np.zeros(original.views.shape[2:4], np.float32))
    else:
        (bench / linked).rename(outside / linked)
    (bench / linked).symlink_to(outside / linked)
    assert main(["import", str(bench), "-o", str(tmp_path / "cap"), "--quiet"]) == 2
    line = one_error_line(capsys)
    assert linked in line and "outside" in line
    assert nothing_written(tmp_path, tmp_path / "cap")


def test_benchmark_grid_size_is_checked(tmp_path, capsys):
    original = read_lightfield(TINY)
    bench = tmp_path / "bench"
    export_plain(original, bench, lambda u, v: f"input_Cam{u * 3 + v:03d}.png")
    (bench / "parameters.cfg").write_text((TINY / "parameters.cfg").read_text())
    assert main(["import", str(bench), "-o", str(tmp_path / "cap"), "--rows", "9", "--cols", "9", "--quiet"]) == 2
    assert "the benchmark folder holds a 3x3 grid, not 9x9" in one_error_line(capsys)
    assert nothing_written(tmp_path, tmp_path / "cap")
