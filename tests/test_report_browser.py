"""The report's 3D view in a real browser: Debian's headless chromium driven by selenium.

The page is opened from ``file://`` (as a user opens a report folder), WebGL runs on SwiftShader. The
checks: no console errors, the 3D canvas is drawn (read back through ``toDataURL``), recolouring
changes the picture, and the page says so when the library or the model's data is missing. A
screenshot of the canvas is kept at ``tests/artifacts/report-3d.png`` (not in git).
"""

from __future__ import annotations

import base64
import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.camera import Camera
from recon.report import write_report
from recon.report.model import LIBRARY_JS, MODEL_JS, read_ply

pytestmark = pytest.mark.slow  # a browser start and WebGL on the CPU: tens of seconds

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
CAMERA = Camera(focal_px=120.0, pitch_mm=1.0)


def _browser_or_skip():
    if not (CHROMIUM.is_file() and CHROMEDRIVER.is_file()):
        message = "Debian's chromium and chromedriver are not installed (./setup.sh --tests installs them)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for argument in ("--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                     "--window-size=1200,1600", "--disable-gpu-sandbox"):
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)


@pytest.fixture(scope="module")
def browser():
    driver = _browser_or_skip()
    yield driver
    driver.quit()


def _scene(height=60, width=80):
    """A slanted wall with a box in front of it, its disparity and a textured centre view."""
    ys, xs = np.indices((height, width))
    depth = 900.0 + 2.0 * xs + 1.0 * ys
    depth[15:40, 20:50] = 700.0
    rng = np.random.default_rng(3)
    image = np.stack([(xs * 3) % 256, (ys * 4) % 256, rng.integers(0, 255, (height, width))], -1).astype(np.uint8)
    confidence = np.clip(0.3 + xs / width, 0, 1).astype(np.float32)
    return CAMERA.disparity_px(depth), image, confidence


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """A report whose 3D view shows a mesh exported to PLY by lfrig's export (through open3d)."""
    from recon.export import export_ply

    folder = tmp_path_factory.mktemp("report")
    disparity, image, confidence = _scene()
    ply = folder / "mesh.ply"
    export_ply(ply, disparity_px=disparity, image=image, camera=CAMERA, confidence=confidence, min_confidence=0.0)
    return write_report(folder / "report", centre_view=image, disparity_px=disparity, camera=CAMERA,
                        truth_disparity_px=disparity, confidence=confidence, model=read_ply(ply), border_px=0)


def _open(driver, page: Path, *, timeout_s: float = 60.0) -> tuple[str | None, list[dict]]:
    """Load the page; wait until the 3D view says it is drawn (or the time is up). Returns its state
    and the console messages."""
    driver.get_log("browser")  # drop what an earlier page left
    driver.get(page.resolve().as_uri())
    deadline = time.monotonic() + timeout_s
    state = None
    while time.monotonic() < deadline:
        state = driver.execute_script("var b = document.getElementById('lfrig-3d'); return b && b.getAttribute('data-state');")
        if state == "drawn":
            break
        time.sleep(0.2)
    return state, driver.get_log("browser")


def _canvas_pixels(driver) -> np.ndarray:
    """The 3D canvas as ``(H, W, 4)`` RGBA uint8, read back by the page itself."""
    url = driver.execute_script("return document.querySelector('#lfrig-3d canvas').toDataURL('image/png');")
    data = base64.b64decode(url.split(",", 1)[1])
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def _drawn(rgba: np.ndarray) -> tuple[float, int]:
    """Share of canvas pixels with something drawn (the background is transparent) and how many
    distinct colours they have."""
    drawn = rgba[..., 3] > 0
    colours = np.unique(rgba[drawn][:, :3], axis=0) if drawn.any() else np.zeros((0, 3))
    return float(drawn.mean()), len(colours)


def test_the_3d_view_draws_the_exported_mesh_without_errors(browser, report, capsys):
    state, log = _open(browser, report)
    severe = [entry for entry in log if entry.get("level") == "SEVERE"]
    assert not severe, f"console errors: {severe}"
    assert state == "drawn"
    rgba = _canvas_pixels(browser)
    share, colours = _drawn(rgba)
    assert share > 0.05 and colours > 200, f"canvas nearly blank: {share:.1%} drawn, {colours} colours"

    from selenium.webdriver.common.by import By

    canvas = browser.find_element(By.CSS_SELECTOR, "#lfrig-3d canvas")
    browser.execute_script("arguments[0].scrollIntoView()", canvas)
    ARTIFACTS.mkdir(exist_ok=True)
    shot = ARTIFACTS / "report-3d.png"
    canvas.screenshot(str(shot))
    with capsys.disabled():  # into the test log, also when output is captured
        print(f"\nscreenshot of the report's 3D view: {shot}")

    browser.find_element(By.CSS_SELECTOR, "#lfrig-3d button[data-colour='depth']").click()
    by_depth = _canvas_pixels(browser)
    assert (by_depth[..., 3] > 0).mean() == pytest.approx(share, abs=0.01), "recolouring keeps the shape"
    assert np.mean(np.any(by_depth[..., :3] != rgba[..., :3], axis=-1)) > 0.03, "colour by depth changed nothing"
    legend = browser.find_element(By.CSS_SELECTOR, "#lfrig-3d .legend3d").text
    assert "clipped to the 1st–99th percentile" in legend and "mm" in legend


@pytest.mark.parametrize("missing", [LIBRARY_JS, MODEL_JS])
def test_the_page_shows_when_the_library_or_the_data_is_missing(browser, report, tmp_path, missing):
    import shutil

    folder = tmp_path / "copy"
    shutil.copytree(report.parent, folder)
    (folder / missing).unlink()
    state, log = _open(browser, folder / report.name, timeout_s=8.0)
    assert state != "drawn"
    assert any(entry.get("level") == "SEVERE" for entry in log), log
    assert _drawn(_canvas_pixels(browser))[0] == 0.0
    status = browser.execute_script("return document.querySelector('#lfrig-3d .status').textContent")
    assert missing in status or "WebGL" in status
