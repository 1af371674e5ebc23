"""``lfrig camera preview`` in a real browser: Debian's headless Chromium through selenium
(``/usr/bin/chromium`` + ``/usr/bin/chromedriver``, installed by ``./setup.sh --tests``), against the
fake camera and Aravis's simulated GenICam camera ``Fake_1``; and Ctrl-C (SIGINT) on the running
command. Tests that need the browser skip on a machine without it but FAIL under CI (env ``CI`` set)."""

from __future__ import annotations

import json
import os
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from rig.main import main
from tests.test_rig_aravis import require_aravis

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"


def start_preview(*args: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "rig.main", "camera", "preview", *args, "--port", "0"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    line = ""
    while time.monotonic() < deadline and proc.poll() is None:
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        if ready:
            line = proc.stdout.readline()
            break
    m = re.search(r"on (http://127\.0\.0\.1:\d+/) \(Ctrl-C stops it\)", line)
    if not m:
        proc.kill()
        raise AssertionError(f"no address printed: {line!r} {proc.stderr.read()}")
    return proc, m.group(1)


def stop(proc: subprocess.Popen) -> tuple[int, str]:
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    return proc.returncode, err


def get_json(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=10) as reply:
        return json.load(reply)


def wait_for_frames(url: str, n: int, timeout_s: float = 60) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        stats = get_json(url + "stats.json")
        assert stats["error"] is None, stats["error"]
        if stats["frame"] >= n:
            return stats
        time.sleep(0.2)
    raise AssertionError(f"fewer than {n} frames in {timeout_s} s")


@pytest.fixture
def browser():
    if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
        message = "Debian's chromium and chromedriver are not installed; ./setup.sh --tests installs them"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1100,700"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def check_page(driver, url: str, tmp_path: Path, name: str) -> np.ndarray:
    """Load the page, see frames arrive, the focus number and the histogram shown, drag a focus region;
    returns the displayed image as the browser drew it."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get(url)
    wait = WebDriverWait(driver, 60, poll_frequency=0.2)
    wait.until(lambda d: d.find_element(By.ID, "frame").text.isdigit())
    first = int(driver.find_element(By.ID, "frame").text)
    wait.until(lambda d: int(d.find_element(By.ID, "frame").text) >= first + 2)  # frames keep arriving
    wait.until(lambda d: d.execute_script("return document.getElementById('view').naturalWidth") > 0)
    focus = float(driver.find_element(By.ID, "focus").text)
    assert focus > 0
    lit = driver.execute_script(
        "const c = document.getElementById('hist'); const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        "let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n / (c.width * c.height);")
    assert lit > 0.02  # the histogram is drawn (Fake_1 fills every bin: a full box there)
    stats = get_json(url + "stats.json")
    assert driver.find_element(By.ID, "size").text.startswith(f"{stats['width']} x {stats['height']} px")
    view = driver.find_element(By.ID, "view")
    shot = cv2.imdecode(np.frombuffer(view.screenshot_as_png, np.uint8), cv2.IMREAD_COLOR)
    assert shot.std() > 5  # the image has content, not a blank or broken-image box

    # drag a region on the image: the focus measure follows it
    w, h = view.size["width"], view.size["height"]
    ActionChains(driver).move_to_element_with_offset(view, -w // 4, -h // 4).click_and_hold() \
        .move_by_offset(w // 4, h // 4).release().perform()
    wait.until(lambda d: d.find_element(By.ID, "region").text.startswith("x "))
    roi = get_json(url + "stats.json")["roi"]
    scale = stats["width"] / w
    assert roi is not None and abs(roi[0] - w / 4 * scale) <= 2 * scale + 1 and abs(roi[2] - w / 4 * scale) <= 2 * scale + 1
    driver.save_screenshot(str(tmp_path / f"{name}.png"))
    errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors
    return shot


def test_preview_of_the_fake_camera_in_chromium(browser, tmp_path):
    proc, url = start_preview("fake", "--binning", "4", "--supersample", "1", "--fps-max", "5")
    try:
        check_page(browser, url, tmp_path, "fake")
    finally:
        status, err = stop(proc)
    assert status == 130 and "preview stopped" in err, err


def test_preview_of_aravis_fake_1_in_chromium(browser, tmp_path):
    require_aravis()
    proc, url = start_preview("aravis:Fake_1", "--roi", "0", "0", "512", "384", "--fps-max", "5")
    try:
        check_page(browser, url, tmp_path, "aravis")
        # Fake_1's pattern moves from frame to frame: the stream shows new images, not one image again
        jpegs = set()
        for _ in range(3):
            with urllib.request.urlopen(url + "frame.jpg", timeout=10) as reply:
                jpegs.add(reply.read())
            time.sleep(0.5)
        assert len(jpegs) >= 2
    finally:
        status, err = stop(proc)
    assert status == 130 and "preview stopped" in err, err


def test_ctrl_c_stops_cleanly_and_frees_the_port(tmp_path):
    proc, url = start_preview("fake", "--binning", "8", "--supersample", "1")
    port = int(url.rsplit(":", 1)[1].strip("/"))
    try:
        wait_for_frames(url, 1)
        stream = urllib.request.urlopen(url + "stream.mjpg", timeout=10)  # a client still watching
        assert stream.headers["Content-Type"].startswith("multipart/x-mixed-replace")
        assert stream.read(64).startswith(b"--lfrigframe\r\nContent-Type: image/jpeg")
        assert (proc.returncode, proc.poll()) == (None, None)
    except BaseException:
        proc.kill()
        raise
    for host, allowed in (("127.0.0.1:9000", True), ("localhost", True), ("[::1]:80", True),
                          ("evil.example:8000", False), ("127.0.0.1.evil.example", False)):
        request = urllib.request.Request(url + "stats.json", headers={"Host": host})
        try:
            with urllib.request.urlopen(request, timeout=10) as reply:
                answered = reply.status == 200
        except urllib.error.HTTPError as error:
            answered = error.code != 403
        assert answered == allowed, host
    status, err = stop(proc)
    stream.close()
    assert status == 130
    assert err.strip().splitlines() == [f"lfrig: preview stopped (Ctrl-C); camera closed, port {port} freed"]
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
    with socket.socket() as again:  # the port can be taken again (as any server takes it: SO_REUSEADDR)
        again.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        again.bind(("127.0.0.1", port))


def test_bad_preview_input_is_one_line(capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["camera", "preview", "fake", "--port", str(port), "--binning", "8"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"lfrig: error: --port {port}: already in use on 127.0.0.1; choose another port "
                       "(--port 0 picks a free one)"]
    for argv, words in [
        (["--host", "0.0.0.0"], "listens on 127.0.0.1 only"),
        (["--focus-roi", "0", "0", "2", "10"], "at least 3 px"),
        (["--port", "70000"], "70000"),
    ]:
        assert main(["camera", "preview", "fake", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("lfrig: error:") and words in err[0], err
    assert main(["camera", "preview", "nocam"]) == 2
    assert "expected 'fake'" in capsys.readouterr().err


def test_a_camera_that_stops_ends_the_preview_with_one_error_and_frees_the_port():
    """The fake camera refuses frames while its stage moves: after 3 frames the stage 'starts moving'."""
    from rig.errors import RigError
    from rig.fakecam import FakeCamera
    from rig.preview import Preview

    camera = FakeCamera(None, binning=8, supersample=1, is_moving=lambda: camera.frames_taken >= 3)
    preview = Preview(camera, fps_max=50)
    server = preview.bind(host="127.0.0.1", port=0)
    port = server.server_address[1]
    raised: list[BaseException] = []

    def run() -> None:
        try:
            preview.serve(server, on_ready=lambda url: None)
        except BaseException as error:  # noqa: BLE001 (checked below)
            raised.append(error)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout=15)
    if thread.is_alive():
        server.shutdown()
        raise AssertionError("the preview kept serving after the camera stopped")
    assert len(raised) == 1 and isinstance(raised[0], RigError), raised
    assert str(raised[0]).startswith("the camera stopped delivering frames: fake camera triggered while the stage is moving")
    assert preview.frame_number == 3
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()


def test_a_request_failing_as_the_viewer_leaves_or_the_preview_stops_prints_no_traceback(capsys, caplog):
    """socketserver prints a traceback for any failed request; a viewer that goes away, or a request
    cut short by Ctrl-C, is no error (the Ctrl-C test met one as a stray traceback on stderr)."""
    import threading
    from types import SimpleNamespace

    from rig.preview import _Server

    class Server(_Server):
        owner = SimpleNamespace(stop_event=threading.Event())

    server = Server.__new__(Server)  # handle_error needs no socket
    for error, stopping in ((ConnectionResetError(104, "reset by peer"), False), (ValueError("I/O on closed file"), True)):
        Server.owner.stop_event.clear()
        if stopping:
            Server.owner.stop_event.set()
        try:
            raise error
        except Exception:
            server.handle_error(None, ("127.0.0.1", 5000))
    assert capsys.readouterr().err == "" and caplog.records == []
    Server.owner.stop_event.clear()
    try:
        raise ValueError("a real fault")
    except ValueError:
        server.handle_error(None, ("127.0.0.1", 5000))
    assert "Traceback" not in capsys.readouterr().err
    assert [r.getMessage() for r in caplog.records] == ["preview: a request from 127.0.0.1 failed: a real fault"]
