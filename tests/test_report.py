"""The HTML report: the page, its figures, and the drawing helpers behind them."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from recon.camera import Camera
from recon.colour import colour_map
from recon.report import write_report
from recon.report.figures import REGION_COLOURS, colourbar_figure, line_plot, nice_ticks, region_picture

CAMERA = Camera(focal_px=300.0, pitch_mm=2.0, disparity_offset=0.0)


def scene(height=48, width=64):
    rng = np.random.default_rng(5)
    ys, xs = np.indices((height, width))
    depth = np.full((height, width), 1000.0) + 2.0 * xs
    depth[10:30, 20:40] = 700.0
    truth = CAMERA.disparity_px(depth)
    estimate = truth + 0.01 * rng.standard_normal(truth.shape)
    estimate[12:28, 19] += 0.5  # a fat edge
    estimate[0, :5] = np.nan
    image = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
    labels = np.full((height, width), 2, np.uint8)
    labels[:, 18:20] = 0
    labels[40:, :] = 3
    window = np.where(labels == 3, 15, 5)
    return image, estimate, truth, labels, window


def page_images(page) -> list[str]:
    return re.findall(r'<img src="([^"]+)"', page.read_text())


def test_full_report_writes_every_figure(tmp_path):
    image, estimate, truth, labels, window = scene()
    page = write_report(tmp_path / "report", centre_view=image, disparity_px=estimate, truth_disparity_px=truth,
                        camera=CAMERA, region_map=labels, window_size_px=window, rows=[20, 44],
                        title="test <scene>", scores={"seconds": 1.5}, info={"method": "entropy"})
    assert page.name == "index.html"
    names = page_images(page)
    for expected in ("centre_view.png", "disparity.png", "depth.png", "error.png", "badpix.png",
                     "regions.png", "window_size.png", "profile_row20.png", "profile_row44.png"):
        assert expected in names
    for name in names:  # every figure the page shows exists and decodes
        picture = cv2.imread(str(page.parent / name))
        assert picture is not None and picture.shape[0] > 50 and picture.shape[1] > 100, name
    text = page.read_text()
    assert "test &lt;scene&gt;" in text and "<scene>" not in text
    assert "BadPix 0.07" in text and "median depth error" in text
    for region in ("occluding", "occluded", "texture", "smooth"):
        assert region in text
    assert "http" not in text.replace("http-equiv", "")  # self-contained: no network needed


def test_confidence_with_a_truth_shows_its_reliability_sparsification_and_kept_share(tmp_path):
    image, estimate, truth, labels, window = scene()
    confidence = np.where(np.abs(estimate - truth) <= 0.07, 0.9, 0.2)  # the fat edge is unsure
    confidence[:, :4] = 0.45  # right, but under the cut
    page = write_report(tmp_path / "r", centre_view=image, disparity_px=estimate, truth_disparity_px=truth,
                        confidence=confidence, min_confidence=0.5, border_px=0)
    names = page_images(page)
    assert {"confidence.png", "reliability.png", "sparsification.png"} <= set(names)
    for name in ("reliability.png", "sparsification.png"):
        assert cv2.imread(str(page.parent / name)) is not None
    kept = 100.0 * np.mean(confidence >= 0.5)
    assert f"kept by the export (confidence ≥ 0.5)" in page.read_text()
    assert f"{kept:.1f} %" in page.read_text()
    without = write_report(tmp_path / "n", centre_view=image, disparity_px=estimate, confidence=confidence,
                           min_confidence=0.5)
    assert not {"reliability.png", "sparsification.png"} & set(page_images(without))  # no truth: no figures


def test_report_without_truth_or_camera_shows_what_it_has(tmp_path):
    image, estimate, *_ = scene()
    page = write_report(tmp_path, centre_view=image[..., 0], disparity_px=estimate)
    names = page_images(page)
    assert "disparity.png" in names and "centre_view.png" in names
    assert not {"error.png", "badpix.png", "depth.png", "regions.png"} & set(names)
    assert any(name.startswith("profile_row") for name in names)
    assert "Scores against the truth" not in page.read_text()


def test_scores_on_the_page_match_the_benchmark_scores(tmp_path):
    from recon.evaluate import score

    image, estimate, truth, *_ = scene()
    page = write_report(tmp_path, centre_view=image, disparity_px=estimate, truth_disparity_px=truth, border_px=4)
    expected = score(estimate.astype(np.float32), truth.astype(np.float32), border=4)
    assert f"{expected['badpix_0.07']:.2f} %" in page.read_text()


def test_shape_mismatch_is_refused(tmp_path):
    image, estimate, truth, *_ = scene()
    with pytest.raises(ValueError, match="centre_view"):
        write_report(tmp_path, centre_view=image[:10], disparity_px=estimate)
    with pytest.raises(ValueError, match="truth_disparity_px"):
        write_report(tmp_path, centre_view=image, disparity_px=estimate, truth_disparity_px=truth[:, :5])


def test_region_picture_uses_the_papers_colours():
    labels = np.array([[0, 1], [2, 3]])
    picture = region_picture(labels)
    assert tuple(picture[0, 0]) == REGION_COLOURS["occluding"] == (255, 0, 0)
    assert tuple(picture[0, 1]) == REGION_COLOURS["occluded"] == (0, 0, 255)
    assert tuple(picture[1, 0]) == REGION_COLOURS["texture"] == (255, 255, 0)
    assert tuple(picture[1, 1]) == REGION_COLOURS["smooth"]


@pytest.mark.parametrize("low, high", [(0.0, 1.0), (-1.7, 0.7), (812.0, 1418.0), (3.0, 15.0), (-0.2, 0.2)])
def test_nice_ticks_are_round_evenly_spaced_and_inside(low, high):
    ticks = nice_ticks(low, high)
    assert 3 <= len(ticks) <= 8
    assert ticks.min() >= low - 1e-9 and ticks.max() <= high + 1e-9
    steps = np.diff(ticks)
    np.testing.assert_allclose(steps, steps[0])
    mantissa = steps[0] / 10 ** np.floor(np.log10(steps[0]))
    assert min(abs(mantissa - m) for m in (1, 2, 2.5, 5)) < 1e-9


def test_colour_map_ends_and_missing_values():
    values = np.array([[0.0, 1.0, np.nan, 5.0]])
    picture = colour_map(values, low=0.0, high=1.0, lut="diverging")
    np.testing.assert_array_equal(picture[0, 1], picture[0, 3])  # clipped at the top
    assert tuple(picture[0, 0]) != tuple(picture[0, 1])
    assert picture[0, 2, 0] == picture[0, 2, 1] == picture[0, 2, 2]  # grey for no value


def test_colourbar_and_plot_have_the_promised_sizes():
    picture = colour_map(np.linspace(0, 1, 40 * 30).reshape(30, 40), low=0, high=1)
    figure = colourbar_figure(picture, low=0, high=1, lut="turbo", label="x", scale=2.0)
    assert figure.shape[0] >= 60 and figure.shape[1] > 80  # the picture plus the bar
    plot = line_plot(np.arange(10), [("a", np.arange(10.0), (0, 0, 255))], xlabel="x", ylabel="y", size=(300, 150))
    assert plot.shape == (150, 300, 3)
    assert (plot == (0, 0, 255)).all(axis=-1).any(), "the line is drawn"


def test_shaded_relief_lights_planes_evenly_and_marks_holes():
    from recon.colour import NO_VALUE
    from recon.report.figures import shaded_relief

    depth = np.full((20, 30), 1000.0)
    x_over_f = (np.arange(15, 30) - 14.5) / 100.0
    depth[:, 15:] = 1000.0 / (1.0 - 2.0 * x_over_f)  # the plane Z = 1000 + 2 X, turned away from the light
    depth[3, 3] = np.nan
    picture = shaded_relief(depth, focal_px=100.0, smooth_px=0)
    assert tuple(picture[3, 3]) == NO_VALUE
    flat, slanted = picture[10, 2:12, 0], picture[10, 18:28, 0]
    assert np.ptp(flat) == 0 and np.ptp(slanted) <= 1
    assert flat[0] != slanted[0]


def test_truth_as_depth_gives_the_same_page_numbers(tmp_path):

    image, estimate, truth, *_ = scene()
    by_disparity = write_report(tmp_path / "a", centre_view=image, disparity_px=estimate,
                                truth_disparity_px=truth, camera=CAMERA).read_text()
    by_depth = write_report(tmp_path / "b", centre_view=image, disparity_px=estimate,
                            truth_depth_mm=CAMERA.depth_mm(truth), camera=CAMERA).read_text()
    badges = lambda text: re.findall(r'<div class="value">([^<]+)</div>', text)  # noqa: E731
    assert badges(by_disparity) == badges(by_depth) and len(badges(by_depth)) >= 4
    with pytest.raises(ValueError, match="camera"):
        write_report(tmp_path / "c", centre_view=image, disparity_px=estimate, truth_depth_mm=truth)


def _captions(text: str) -> dict[str, str]:
    return dict(re.findall(r"<figcaption><b>([^<]+)</b> — (.*?)</figcaption>", text))


def test_depth_error_in_mm_and_every_colour_bar_says_whether_it_clips(tmp_path):
    image, estimate, truth, labels, window = scene()
    confidence = np.clip(np.linspace(0, 1, estimate.size).reshape(estimate.shape), 0, 1)
    page = write_report(tmp_path, centre_view=image, disparity_px=estimate, truth_disparity_px=truth, camera=CAMERA,
                        region_map=labels, window_size_px=window, confidence=confidence, min_confidence=0.4,
                        border_px=4)
    text = page.read_text()
    assert "depth_error.png" in page_images(page)
    captions = _captions(text)
    error_mm = CAMERA.depth_mm(estimate) - CAMERA.depth_mm(truth)
    median = np.nanmedian(np.abs(error_mm))
    assert f"median |error| {median:.4g} mm" in captions["Depth error in mm"]
    # the map is clipped at a round number >= the 95th percentile, and says how much lies beyond
    limit = float(re.search(r"clipped to ±([0-9.]+) mm", captions["Depth error in mm"])[1])
    p95 = np.nanpercentile(np.abs(error_mm), 95)
    assert p95 <= limit <= 5 * p95
    beyond = 100 * np.mean(np.abs(error_mm[np.isfinite(error_mm)]) > limit)
    assert f"({beyond:.1f} % of pixels outside)" in captions["Depth error in mm"]
    for title in ("Disparity", "Depth", "Disparity error", "Depth error in mm", "Confidence", "Window size"):
        assert "clipped to" in captions[title] or "nothing clipped" in captions[title], title
    assert "clipped to the 1st–99th percentile" in captions["Depth"]
    assert "nothing clipped" in captions["Confidence"] and "nothing clipped" in captions["Window size"]


def test_settings_are_grouped_tables_and_the_footer_shows_provenance(tmp_path):
    image, estimate, *_ = scene()
    options = {"disparity_range": [-1, 2], "step": 0.04, "window_sizes": [3, 5], "gamma": 0.2, "tv_iterations": 300,
               "boundary_snap": True, "noise_gate": "auto", "layer_gap": 0.5, "something_new": 1}
    provenance = {"lfrig_version": "9.8.7", "command": ["lfrig", "reconstruct", "my scene", "-o", "out"],
                  "started_utc": "2026-01-02T03:04:05Z",
                  "input": {"kind": "capture", "path": "/data/scene", "journal_sha256": "ab" * 32},
                  "timings_s": {"estimate": 12.5}, "machine": {"python": "3.12.1", "cpus": 2}}
    page = write_report(tmp_path, centre_view=image, disparity_px=estimate,
                        info={"method": "entropy", "options": options}, provenance=provenance)
    text = page.read_text()
    tables = dict(re.findall(r"<caption>([^<]+)</caption><tbody>(.*?)</tbody>", text))
    assert set(tables) == {"disparity range and sampling", "occlusion layers", "windows and matching entropy",
                           "refinement and holes", "noise and weak texture", "object boundaries", "other"}
    assert "gamma" in tables["refinement and holes"] and "tv_iterations" in tables["refinement and holes"]
    assert "boundary_snap" in tables["object boundaries"] and "something_new" in tables["other"]
    assert "window_sizes" in tables["windows and matching entropy"]
    footer = text[text.index("<footer>"):]
    for expected in ("9.8.7", "lfrig reconstruct &#x27;my scene&#x27; -o out", "capture /data/scene", "abababab",
                     "estimate 12.5 s", "python 3.12.1"):
        assert expected in footer, expected
    older = write_report(tmp_path / "old", centre_view=image, disparity_px=estimate).read_text()
    assert "not recorded" in older[older.index("<footer>"):]


def test_report_for_result_shows_the_exported_ply_in_3d(tmp_path):
    import json

    from recon.export import export_ply
    from recon.lf.pfm import write_pfm
    from recon.report import report_for_result
    from recon.result import read_result

    image, estimate, truth, *_ = scene()
    folder = tmp_path / "run"
    folder.mkdir()
    write_pfm(folder / "disparity.pfm", estimate.astype(np.float32))
    cv2.imwrite(str(folder / "centre_view.png"), image[..., ::-1])
    (folder / "result.json").write_text(json.dumps({**CAMERA.as_dict(), "provenance": {"lfrig_version": "1.2.3"}}))
    result = read_result(folder)
    summary = export_ply(tmp_path / "m.ply", disparity_px=estimate, image=image, camera=CAMERA)
    page = report_for_result(result, tmp_path / "report", ply=tmp_path / "m.ply")
    text = page.read_text()
    assert f"m.ply: a mesh of {summary.points:,} vertices and {summary.triangles:,} triangles" in text
    for name in ("three.viewer.min.js", "model-data.js", "viewer.js"):
        assert f'<script src="{name}"></script>' in text and (page.parent / name).is_file()
    assert (page.parent / "LICENSE-three.txt").read_text().startswith("The MIT License")
    assert "1.2.3" in text[text.index("<footer>"):]
    # without a PLY the view shows the points the export keeps
    text = report_for_result(result, tmp_path / "report2").read_text()
    assert "the points lfrig export keeps" in text and "model-data.js" in text
