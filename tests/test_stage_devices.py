"""The stage driver and capture sessions against two controllers on a serial device (a pty): the
real GRBL 1.1h firmware (``../shared/grbl-sim``, built once per test session, ``tests/conftest.py``)
and lfrig's fake.

Every test runs on both (``-k fake`` / ``-k firmware``) but the 81-view capture, on the firmware only
(the fake's is in ``tests/test_rig_session.py``). The fake was written from the same reading of
GRBL's documents as the driver; the firmware is the judge. Motion is real time on both: the
settings (``grbl_devices.FAST``) are a small, fast stage, written once into an EEPROM image each
firmware starts from. lfrig runs in this process (``main``) unless the scenario needs a process to
kill; Ctrl-C comes as a SIGINT at the moment in question, and the waits a dead controller makes lfrig
sit out are shortened (``short_waits``). Under CI (env ``CI`` set) a missing ``../shared/grbl-sim``
or a failed build fails the firmware half instead of skipping it.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pytest

from grbl_devices import FAST, FakeOnPty, Firmware
from rig.main import main
from rig.grbl import (GrblAlarmError, GrblConnectionError, GrblLimitError, GrblStage, encode_move, port_holders,
                      travel_limits_mm)
from rig.grid import GridSpec, plan_moves

pytestmark = pytest.mark.slow  # real-time motion

ROOT = Path(__file__).resolve().parents[1]
LFRIG = [sys.executable, "-m", "rig.main"]
CENTRE = (-10.0, -10.0, -5.0)
CAMERA = ["--camera", "fake", "--binning", "8", "--supersample", "1", "--settle-s", "0.02", "--quiet"]
TOL = 0.0041  # one step at 250 steps/mm, plus rounding


@pytest.fixture(params=["fake", "firmware"])
def make_device(request, tmp_path):
    """``make_device(settings=..., start_mm=...)``: a controller on a pty (stopped at teardown)."""
    made = []

    def make(settings: dict | None = None, start_mm=None, relay: bool = False):
        merged = {**FAST, **(settings or {})}
        if request.param == "firmware":
            exe, eeprom = request.getfixturevalue("firmware_exe"), request.getfixturevalue("firmware_eeprom")
            device = Firmware(exe, tmp_path / f"grbl{len(made)}", settings=merged, start_mm=start_mm, relay=relay,
                              eeprom=eeprom)
        else:
            device = FakeOnPty(settings=merged, start_mm=start_mm)
        made.append(device)
        return device

    yield make
    for device in made:
        device.close()


def close_to(a, b, tol=TOL) -> bool:
    return max(abs(x - y) for x, y in zip(a, b)) <= tol


def views_in(path: Path) -> list[dict]:
    manifest = path / "manifest.jsonl"
    if not manifest.is_file():
        return []
    records = []
    for line in manifest.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return [r for r in records if r.get("kind") == "view"]


def grid_of(args: list[str]):
    """The :class:`rig.grid.GridSpec` of a :func:`capture_args` command (pitch 0.5 mm)."""
    centre = args.index("--centre-mm")
    return GridSpec(rows=int(args[args.index("--rows") + 1]), cols=int(args[args.index("--cols") + 1]), pitch_mm=0.5,
                    centre_mm=tuple(float(c) for c in args[centre + 1:centre + 4]))


def capture_args(out: Path, device, *extra: str, rows: int = 9, cols: int = 9, centre=CENTRE) -> list[str]:
    return ["capture", str(out), "--stage", device.url, "--rows", str(rows), "--cols", str(cols),
            "--centre-mm", *(f"{c:g}" for c in centre), *CAMERA, *extra]


def start_capture(args: list[str]) -> subprocess.Popen:
    """``lfrig ARGS`` as a process of its own (for a scenario that kills it)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([*LFRIG, *args], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_views(process: subprocess.Popen, out: Path, n: int, timeout_s: float = 120) -> None:
    deadline = time.monotonic() + timeout_s
    while len(views_in(out)) < n:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the capture did not get going"
        time.sleep(0.01)


def check_views(out: Path, total: int) -> None:
    """Every view once, read back at its commanded machine position."""
    views = views_in(out)
    counts = Counter((v["u"], v["v"]) for v in views)
    assert len(counts) == total and set(counts.values()) == {1}, counts
    for v in views:
        assert close_to(v["readback_mm"], v["commanded_mm"]), v


def at_view(monkeypatch, out: Path, n: int, action=None) -> None:
    """Make the next ``lfrig capture`` in this process call ``action()`` once ``n`` views are journalled
    (once, the capture going on), or without an action stop cleanly then, as on a first Ctrl-C."""
    import rig.session

    real = rig.session.run_capture
    done = []

    def should_stop() -> bool:
        if len(views_in(out)) < n:
            return False
        if action is None:
            return True
        if not done:
            done.append(action())
        return False

    def run_capture(*args, **kwargs):
        monkeypatch.setattr(rig.session, "run_capture", real)  # once
        return real(*args, **kwargs, should_stop=should_stop)

    monkeypatch.setattr(rig.session, "run_capture", run_capture)


def stop_after(monkeypatch, out: Path, n: int) -> None:
    """Make the next ``lfrig capture`` in this process stop cleanly (as on a first Ctrl-C) once ``n``
    views are journalled."""
    at_view(monkeypatch, out, n)


def sigint_after_move(monkeypatch, line: str) -> None:
    """Send this process a SIGINT (lfrig's capture handles it as a Ctrl-C) right after the move
    ``line`` (as lfrig sends it) was accepted by GRBL, while the stage runs it."""
    real = GrblStage.move_to

    def move_to(self, position_mm, *, feed_mm_min=None):
        real(self, position_mm, feed_mm_min=feed_mm_min)
        if encode_move(position_mm, feed_mm_min=feed_mm_min).decode().strip() == line:
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(GrblStage, "move_to", move_to)


# -- status, move, unlock, homing -------------------------------------------------------------------


def test_status_unlock_move_and_the_power_up_lock(make_device, capsys):
    device = make_device()
    assert main(["stage", "status", "--stage", device.url]) == 0
    assert capsys.readouterr().out.startswith("Alarm  MPos X=0.000, Y=0.000, Z=0.000")  # $22=1: locked
    assert main(["stage", "move", "-2", "-3", "-1", "--stage", device.url]) == 2
    assert "error:9" in capsys.readouterr().err
    assert main(["stage", "unlock", "--stage", device.url]) == 0
    assert capsys.readouterr().out.startswith("Idle  MPos X=0.000")
    with GrblStage(device.path) as stage:
        stage.prepare()
        stage.move_to((-2.0, -3.0, -1.0))
        assert close_to(stage.wait_until_idle(), (-2.0, -3.0, -1.0))
    # with homing off ($22=0, GRBL's default) the controller starts unlocked
    device.configure({22: 0})
    assert main(["stage", "status", "--stage", device.url]) == 0
    assert capsys.readouterr().out.startswith("Idle  MPos X=0.000")


def test_homing_finds_the_switches_and_defines_the_frame(make_device):
    device = make_device()
    with GrblStage(device.path) as stage:
        assert stage.home_timeout_s < 60  # derived from $130-$132 and $25, not a fixed 120 s
        stage.home()
        assert close_to(stage.position(), (-1.0, -1.0, -1.0))  # switches at 0, pull-off $27
        assert close_to(device.carriage_mm(), (-1.0, -1.0, -1.0))
        stage.move_to((-12.0, -7.5, -4.0))
        assert close_to(stage.wait_until_idle(), (-12.0, -7.5, -4.0))
        assert close_to(device.carriage_mm(), (-12.0, -7.5, -4.0))


def test_homing_towards_the_minimum_with_23_3(make_device):
    """$23=3: X and Y home to their minimum; GRBL 1.1h keeps the travel at [-max, 0] all the same."""
    device = make_device({23: 3})
    with GrblStage(device.path) as stage:
        limits = stage.limits_mm()
        assert limits == ((-19.0, 0.0), (-19.0, 0.0), (-10.0, -1.0))  # pull-off kept from each switch
        stage.home()
        assert close_to(stage.position(), (-19.0, -19.0, -1.0))
        assert close_to(device.carriage_mm(), (-19.0, -19.0, -1.0))
        stage.move_to((-0.5, -15.0, -5.0))
        assert close_to(stage.wait_until_idle(), (-0.5, -15.0, -5.0))
        with pytest.raises(GrblLimitError, match=r"X=2\.000 mm is outside"):
            stage.move_to((2.0, -15.0, -5.0))


@pytest.mark.parametrize("report", [1, 0], ids=["MPos", "WPos"])
def test_work_offset_left_by_another_program_does_not_shift_moves(make_device, report):
    device = make_device({10: report})  # $10=0: reports in work coordinates, MPos = WPos + WCO
    device.raw(b"$X\n")
    device.raw(b"G10 L2 P1 X3 Y2 Z1\n")  # G54 offset (kept in EEPROM), like a CAM program leaves it
    device.raw(b"G55\n")
    device.raw(b"G10 L20 P2 X0 Y0 Z0\n")  # G55 = here, and selected
    with GrblStage(device.path) as stage:
        stage.home()
        stage.move_to((-6.0, -5.0, -2.0))
        assert close_to(stage.wait_until_idle(), (-6.0, -5.0, -2.0))
        assert close_to(device.carriage_mm(), (-6.0, -5.0, -2.0))


# -- limits -----------------------------------------------------------------------------------------


def test_soft_limits_refuse_a_grid_outside_the_travel(make_device, tmp_path, capsys):
    device = make_device()
    out = tmp_path / "cap"
    assert main(capture_args(out, device, rows=3, cols=3, centre=(2.0, -10, -5))) == 2
    assert "outside the stage's travel" in capsys.readouterr().err
    assert not out.exists()  # no folder, no lock, no journal: the corrected command starts afresh
    assert main(capture_args(out, device, rows=1, cols=2, centre=(-10, -10, -5))) == 0, capsys.readouterr().err
    check_views(out, 2)
    with GrblStage(device.path) as stage:
        stage.home()
        with pytest.raises(GrblAlarmError, match=r"ALARM:2 .*soft limit"):
            stage.command("G53 G0 X5")  # the driver's own check bypassed: GRBL refuses too


def test_hard_limit_raises_alarm_1(make_device):
    device = make_device({20: 0, 21: 1, 22: 0})  # no homing, no soft limits: only the switch
    with GrblStage(device.path) as stage:
        assert stage.limits_mm() is None
        start = device.carriage_mm()
        stage.prepare()
        stage.move_to((15.0, 0.0, 0.0))  # the carriage is mid-travel: its switch is 10 mm away
        with pytest.raises(GrblAlarmError, match=r"ALARM:1 .*hard limit"):
            stage.wait_until_idle()
    assert device.carriage_mm()[0] == pytest.approx(0.0, abs=0.05) and start[0] < -5


def test_travel_check_keeps_the_pull_off_from_the_switch(make_device):
    device = make_device({21: 1})
    with GrblStage(device.path) as stage:
        stage.home()
        assert stage.limits_mm() == ((-20.0, -1.0), (-20.0, -1.0), (-10.0, -1.0))
        with pytest.raises(GrblLimitError, match=r"X=0\.000 mm is outside"):
            stage.move_to((0.0, -5.0, -5.0))  # on the switch: ALARM:1 with $21=1
        stage.move_to((-1.0, -5.0, -5.0))
        assert close_to(stage.wait_until_idle(), (-1.0, -5.0, -5.0))
        assert stage.status()["state"] == "Idle"


def test_limit_formula_matches_grbl_1_1h():
    settings = {130: 100.0, 131: 80.0, 132: 50.0, 23: 0b010, 27: 2.0}
    assert travel_limits_mm(settings) == ((-100.0, -2.0), (-78.0, 0.0), (-50.0, -2.0))


# -- stopping, resetting, reconnecting --------------------------------------------------------------

SLOW = {110: 300, 111: 300, 112: 300, 120: 4, 121: 4, 122: 4}  # 5 mm/s, 4 mm/s^2: 1.25 s to stop


def test_stop_waits_for_the_feed_hold_to_end(make_device):
    device = make_device({**SLOW, 22: 0, 20: 0})
    before = device.carriage_mm()
    with GrblStage(device.path) as stage:
        stage.prepare()
        stage.move_to((-15.0, 0.0, 0.0))
        time.sleep(1.6)  # cruising at 5 mm/s
        stage.stop()
        status = stage.status()
        assert status["state"] == "Idle", status  # no ALARM:3: the reset came after Hold:0
        assert stage.homing_required is None
        assert -15.0 < status["mpos_mm"][0] < -5.0
    moved = [c - b for c, b in zip(device.carriage_mm(), before)]
    assert close_to(moved, status["mpos_mm"])  # no step lost


def test_reset_in_motion_reports_alarm_3_and_requires_homing(make_device):
    device = make_device({22: 1})
    with GrblStage(device.path) as stage:
        stage.home()
        stage.move_to((-19.0, -19.0, -9.0), feed_mm_min=300)  # 3.6 s at 5 mm/s
        time.sleep(0.3)
        stage.reset()
        assert stage.homing_required and "ALARM:3" in stage.homing_required
        with pytest.raises(GrblAlarmError, match=r"ALARM:3.*home"):
            stage.unlock()
        with pytest.raises(GrblAlarmError, match=r"ALARM:3.*home"):
            stage.move_to((-5.0, -5.0, -5.0))
        stage.home()
        assert stage.homing_required is None
        stage.move_to((-5.0, -5.0, -5.0))
        assert close_to(stage.wait_until_idle(), (-5.0, -5.0, -5.0))


def test_reconnect_during_a_move_lets_the_move_finish(make_device):
    """A process killed mid-move leaves GRBL moving: the next one must not abort that move (ALARM:3)."""
    device = make_device({**SLOW, 22: 0, 20: 0})
    with GrblStage(device.path) as stage:
        stage.prepare()
        stage.move_to((-6.0, 0.0, 0.0))  # about 1.8 s; the port is closed without stopping it
    with GrblStage(device.path) as stage:
        status = stage.status()
        assert status["state"] == "Idle", status
        assert close_to(status["mpos_mm"], (-6.0, 0.0, 0.0))
        assert stage.homing_required is None


def test_the_port_is_opened_exclusively(make_device):
    device = make_device()
    with GrblStage(device.path):
        with pytest.raises(GrblConnectionError, match="another program"):
            GrblStage(device.path)


# -- captures ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("make_device", ["firmware"], indirect=True)  # the fake's: tests/test_rig_session.py
def test_full_81_view_capture(make_device, tmp_path, capsys):
    device = make_device()
    out = tmp_path / "cap"
    start = time.perf_counter()
    assert main(capture_args(out, device)) == 0, capsys.readouterr().err
    elapsed = time.perf_counter() - start
    assert "81 of 81 views" in capsys.readouterr().out
    check_views(out, 81)
    print(f"81-view capture on the {device.kind}: {elapsed:.1f} s wall")


def test_sigint_then_resume_without_homing(make_device, tmp_path, capsys, monkeypatch):
    device = make_device()
    out = tmp_path / "cap"
    args = capture_args(out, device, rows=3, cols=3)
    third = [m for m in plan_moves(grid_of(args)) if m.view is not None][2]
    sigint_after_move(monkeypatch, encode_move(third.target_mm).decode().strip())  # Ctrl-C on the way to the 3rd view
    assert main(args) == 130, capsys.readouterr().err
    assert len(views_in(out)) == 3  # the view under way was finished
    # the carriage sits at the last view and nothing reset: the frame is proven, no homing needed
    assert main([*args, "--no-home"]) == 0, capsys.readouterr().err
    check_views(out, 9)
    assert close_to(device.carriage_mm(), views_in(out)[-1]["readback_mm"])


def test_kill_9_then_resume(make_device, tmp_path, capsys):
    device = make_device()
    out = tmp_path / "cap"
    process = start_capture(capture_args(out, device, rows=3, cols=3))
    wait_for_views(process, out, 3)
    process.kill()
    process.communicate(timeout=30)
    first = len(views_in(out))
    time.sleep(0.3)  # the move under way when the process died ends
    proven = close_to(device.carriage_mm(), views_in(out)[-1]["readback_mm"])
    code = main(capture_args(out, device, "--no-home", rows=3, cols=3))
    if not proven:  # killed during a move: the stage is not where the journal's last view was taken
        err = capsys.readouterr().err
        assert code == 2 and "last view was read back at" in err, err
        assert len(views_in(out)) == first
        code = main(capture_args(out, device, rows=3, cols=3))
    assert code == 0, capsys.readouterr().err
    check_views(out, 9)
    assert close_to(device.carriage_mm(), views_in(out)[-1]["readback_mm"])


@pytest.mark.parametrize("homing", [False, True], ids=["no-homing", "homing"])
def test_controller_restart_between_runs(make_device, tmp_path, capsys, monkeypatch, homing):
    """A reset between runs (power dip, Arduino reset on open) restarts GRBL's position at 0 where
    the carriage stands: a resume must re-home or refuse, never take views in a shifted frame."""
    device = make_device({22: 1} if homing else {22: 0, 20: 0})
    out = tmp_path / "cap"
    if homing:
        args = capture_args(out, device, rows=3, cols=3)
    else:  # the frame is wherever GRBL powered up: the lab's --no-home habit with $22=0
        args = capture_args(out, device, "--no-home", rows=3, cols=3, centre=(-3.0, -3.0, -2.0))
    stop_after(monkeypatch, out, 3)
    assert main(args) == 130, capsys.readouterr().err
    first = len(views_in(out))
    assert first == 3
    # power cycle with the carriage a little off (moved by hand while the controller was off)
    device.restart(start_mm=tuple(c + d for c, d in zip(device.carriage_mm(), (2.0, 1.5, -0.5))))
    code = main(args)
    err = capsys.readouterr().err
    if homing:
        assert code == 0, err
        check_views(out, 9)
        assert close_to(device.carriage_mm(), views_in(out)[-1]["readback_mm"])
    else:
        assert code == 2 and "cannot prove" in err, err
        assert len(views_in(out)) == first


def sigint_during(monkeypatch, method: str, *delays_s: float) -> None:
    """Send this process a SIGINT ``delays_s[0]`` s after the next call of ``GrblStage.<method>``
    begins, then one more after each further delay (from a thread, while the call runs)."""
    real = getattr(GrblStage, method)

    def wrapped(self, *args, **kwargs):
        monkeypatch.setattr(GrblStage, method, real)  # once

        def send() -> None:
            for delay in delays_s:
                time.sleep(delay)
                os.kill(os.getpid(), signal.SIGINT)

        threading.Thread(target=send, daemon=True).start()
        return real(self, *args, **kwargs)

    monkeypatch.setattr(GrblStage, method, wrapped)


def run_interrupted(args: list[str]) -> int:
    """``lfrig ARGS`` in this process with Ctrl-C as at a terminal (KeyboardInterrupt), whatever
    the test runner's own SIGINT disposition."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return main(args)
    except KeyboardInterrupt:
        pytest.fail("the Ctrl-C escaped lfrig")
    finally:
        signal.signal(signal.SIGINT, previous)


def test_ctrl_c_twice_during_a_long_slow_move(make_device, tmp_path, capsys, monkeypatch):
    device = make_device({**SLOW, 22: 0, 20: 0})
    out = tmp_path / "cap"
    # the first move runs 12 mm from the power-up position: 1.25 s up to 5 mm/s, cruise, 1.25 s down;
    # Ctrl-C while cruising (a feed hold needs 1.25 s), and again 0.2 s later
    sigint_during(monkeypatch, "move_to", 1.6, 0.2)
    assert run_interrupted(capture_args(out, device, "--no-home", rows=3, cols=3, centre=(-12.0, 0.0, 0.0))) == 130
    err = capsys.readouterr().err
    assert "second Ctrl-C" in err and "ALARM:3" not in err, err
    assert views_in(out) == []
    with GrblStage(device.path) as stage:
        status = stage.status()
    assert status["state"] == "Idle", status  # stopped by a feed hold, not an abort
    assert -12.6 < status["mpos_mm"][0] < -3.0  # short of the first target, x = -12.7


# -- the machine frame is part of a capture's identity ----------------------------------------------


def current_views(out: Path) -> list[dict]:
    """The view records after the journal's last new frame (the ones that count)."""
    records = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    frames = [i for i, r in enumerate(records) if r.get("kind") == "frame"]
    return [r for r in records[(frames[-1] + 1 if frames else 0):] if r.get("kind") == "view"]


def test_homing_a_capture_taken_without_homing_is_refused(make_device, tmp_path, capsys, monkeypatch):
    """#21.1: a capture with --no-home at $22=0, then "enable it and home" and resume: the homed frame
    is not the power-up frame, so the resume refuses; --retake-all takes every view again in it."""
    device = make_device({22: 0, 20: 0})
    out = tmp_path / "cap"
    no_home = capture_args(out, device, "--no-home", rows=3, cols=3, centre=(-3.0, -3.0, -2.0))
    homing = [a for a in no_home if a != "--no-home"]
    stop_after(monkeypatch, out, 3)
    assert main(no_home) == 130, capsys.readouterr().err
    assert len(views_in(out)) == 3
    device.configure({22: 1})  # enable homing: the controller restarts locked
    assert main(homing) == 2
    err = capsys.readouterr().err
    assert "captured without homing" in err and "--retake-all" in err, err
    assert main(["stage", "home", "--stage", device.url]) == 0  # homed by hand, then without homing
    assert main(no_home) == 2
    assert "cannot prove" in capsys.readouterr().err
    assert len(views_in(out)) == 3 and device.status().startswith("<Idle")
    assert main([*homing, "--retake-all"]) == 0, capsys.readouterr().err
    views = current_views(out)
    assert len(views) == 9 and len({(v["u"], v["v"]) for v in views}) == 9
    assert all(close_to(v["readback_mm"], v["commanded_mm"]) for v in views)
    assert close_to(device.carriage_mm(), views[-1]["readback_mm"])  # the switches' frame: carriage = MPos
    from recon.lf.capture import read_capture

    read = read_capture(out).metadata["views"]  # the reader takes the retaken views, not the old ones
    assert {(v["u"], v["v"]): v["sha256"] for v in read} == {(v["u"], v["v"]): v["sha256"] for v in views}


def test_a_changed_frame_setting_is_refused(make_device, tmp_path, capsys, monkeypatch):
    """#21.3: $100 250 -> 200 between runs put the resumed views at 0.8x their X; $23 and $130 move
    the homed origin. Each changed alone, then set back."""
    device = make_device()
    out = tmp_path / "cap"
    args = capture_args(out, device, rows=3, cols=3)
    stop_after(monkeypatch, out, 2)
    assert main(args) == 130, capsys.readouterr().err
    back: dict[int, float] = {}
    for (key, value) in ((100, 200), (23, 1), (130, 18)):
        device.configure({**back, key: value})  # the one before set back, this one changed: one restart
        back = {key: FAST[key]}
        for extra in ([], ["--no-home"]):
            assert main([*args, *extra]) == 2
            err = capsys.readouterr().err
            assert "settings that place a step" in err and f"${key} was " in err and f"now {value}" in err, err
            assert len(re.findall(r"\$\d+ was ", err)) == 1, err  # only this one differs
    device.configure(back)
    assert len(views_in(out)) == 2
    assert main(args) == 0, capsys.readouterr().err  # set back: the same frame, homed again
    check_views(out, 9)


def test_unlock_and_a_move_do_not_fake_the_frame_proof(make_device, tmp_path, capsys, monkeypatch):
    """#21.2: power cycle (carriage moved), `stage unlock` as error:9 advises, `stage move` to the
    last view's readback, then a --no-home resume: refused, because the alarm lock seen when the port
    opened is kept in the port's record; a homing clears it."""
    device = make_device()
    out = tmp_path / "cap"
    args = capture_args(out, device, rows=3, cols=3)
    stop_after(monkeypatch, out, 3)
    assert main(args) == 130, capsys.readouterr().err
    last = views_in(out)[-1]["readback_mm"]
    device.restart(start_mm=tuple(c + d for c, d in zip(device.carriage_mm(), (3.0, 2.5, 0.8))))
    assert main(["stage", "unlock", "--stage", device.url]) == 0
    assert "unlocked without homing" in capsys.readouterr().err
    assert main(["stage", "move", *(f"{c:g}" for c in last), "--stage", device.url]) == 0
    capsys.readouterr()
    assert main([*args, "--no-home"]) == 2
    err = capsys.readouterr().err
    assert "cannot prove" in err and "Alarm when the port opened" in err, err
    assert len(views_in(out)) == 3
    assert main(args) == 0, capsys.readouterr().err
    check_views(out, 9)
    assert close_to(device.carriage_mm(), views_in(out)[-1]["readback_mm"])


def test_a_power_cycle_nobody_saw_at_22_0_and_a_move_to_the_last_view_are_refused(make_device, tmp_path, capsys,
                                                                                   monkeypatch):
    """#21.2 with homing off ($22=0, no alarm lock after power-up): a power cycle while no lfrig
    listens restarts GRBL's position at 0, and `stage move` to the last view's readback puts the new
    frame's coordinates there. The port's record kept where lfrig left the stage, so the `--no-home`
    resume is refused."""
    device = make_device({22: 0, 20: 0})
    out = tmp_path / "cap"
    args = capture_args(out, device, "--no-home", rows=3, cols=3, centre=(-3.0, -3.0, -2.0))
    stop_after(monkeypatch, out, 3)
    assert main(args) == 130, capsys.readouterr().err
    last = views_in(out)[-1]["readback_mm"]
    device.restart()  # the carriage where it stands
    assert main(["stage", "move", *(f"{c:g}" for c in last), "--stage", device.url]) == 0
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "cannot prove" in err and "when lfrig last let go of it" in err, err
    assert len(views_in(out)) == 3
    assert main([*args, "--retake-all"]) == 0, capsys.readouterr().err  # the way forward
    assert len(current_views(out)) == 9


# -- Ctrl-C on the stage commands, resets on open, noise, other programs on the port, settings -----


def standing_still(device) -> tuple[float, float, float]:
    here = device.carriage_mm()
    time.sleep(0.5)
    assert device.carriage_mm() == here, "the carriage is still moving"
    return here


def test_ctrl_c_stops_a_stage_move_and_says_where(make_device, capsys, monkeypatch):
    device = make_device({22: 0, 20: 0})
    start = device.carriage_mm()
    # 15 mm at 1 mm/s from the power-up position, Ctrl-C after 2 s
    sigint_during(monkeypatch, "move_to", 2.0)
    assert run_interrupted(["stage", "move", "-15", "0", "0", "--feed-mm-min", "60", "--stage", device.url]) == 130
    err = capsys.readouterr().err
    assert "stopped by a feed hold" in err and "ALARM" not in err, err
    reported = float(re.search(r"MPos X=(-?[0-9.]+)", err)[1])
    moved = standing_still(device)[0] - start[0]
    assert -13.0 < moved < -0.5, moved  # stopped on the way
    assert abs(moved - reported) <= TOL, (moved, reported)  # and where it says


def test_ctrl_c_stops_stage_home_by_a_reset(make_device, capsys, monkeypatch):
    # seek at 2 mm/s from off the switches: Z 8 mm first (4 s), then X and Y 9 mm; Ctrl-C after 2.5 s
    device = make_device({25: 120}, start_mm=(-9.0, -9.0, -8.0))
    sigint_during(monkeypatch, "home", 2.5)
    assert run_interrupted(["stage", "home", "--stage", device.url]) == 130
    err = capsys.readouterr().err
    assert "homing stopped" in err and "ALARM:6" in err and "home it" in err, err
    here = standing_still(device)
    assert here[2] < -1.5, here  # Z, homed first, is short of its switch: the cycle did not go on


def test_stage_status_does_not_stop_a_homing_cycle(make_device, capsys, monkeypatch):
    """`stage status` only looks: a homing cycle left running by a process that died goes on."""
    device = make_device({25: 120}, start_mm=(-6.0, -6.0, -4.0))  # seek at 2 mm/s: about 5 s of homing
    os.write(device.slave, b"$H\n")  # sent by a process that then died
    time.sleep(0.2)
    short_waits(monkeypatch)
    assert main(["stage", "status", "--stage", device.url]) == 2
    err = capsys.readouterr().err
    assert "no status report" in err and "homing" in err and "nothing that would stop it" in err, err
    assert not close_to(device.carriage_mm(), (-1.0, -1.0, -1.0), tol=0.01)  # still on its way
    deadline = time.monotonic() + 40
    while not close_to(device.carriage_mm(), (-1.0, -1.0, -1.0), tol=0.01):
        assert time.monotonic() < deadline, device.carriage_mm()
        time.sleep(0.2)


def test_ctrl_c_during_a_backlash_take_up_still_resumes_without_homing(make_device, tmp_path, capsys, monkeypatch):
    """#21.5: a first Ctrl-C while a backlash take-up runs: the view it leads to is taken, so the stage
    stops on the journal's last view and a resume without homing is proven."""
    device = make_device()
    out = tmp_path / "cap"
    args = capture_args(out, device, rows=3, cols=3)
    moves = plan_moves(grid_of(args))
    index = next(i for i, m in enumerate(moves) if m.view is None and i > 0)  # the first take-up after a view
    views_before = sum(m.view is not None for m in moves[:index])
    sigint_after_move(monkeypatch, encode_move(moves[index].target_mm).decode().strip())
    assert main(args) == 130, capsys.readouterr().err
    assert len(views_in(out)) == views_before + 1  # the view the take-up led to was taken
    assert close_to(device.carriage_mm(), views_in(out)[-1]["readback_mm"])
    assert main(args + ["--no-home"]) == 0, capsys.readouterr().err
    check_views(out, 9)


@pytest.mark.parametrize("boot_s", [2.0, 2.8])
def test_a_reset_on_open_is_seen_however_long_the_board_boots(make_device, boot_s):
    device = make_device()
    device.power_cycle(boot_s=boot_s)  # like an Arduino whose bootloader runs when the port opens
    with GrblStage(device.path) as stage:
        assert stage.reset_seen
        assert "reset when the port opened" in stage.machine_frame_doubt()
        assert stage.status()["state"] == "Alarm"  # $22=1: locked after power-up


def test_garbled_status_reports_are_asked_again(make_device, tmp_path, capsys, monkeypatch, caplog):
    device = make_device(relay=True)
    out = tmp_path / "cap"
    # two reports in a row lose a digit on the way, from the third view on
    at_view(monkeypatch, out, 2, lambda: setattr(device, "garble_reports", 2))
    assert main(capture_args(out, device, rows=3, cols=3)) == 0, capsys.readouterr().err
    asked_again = [r for r in caplog.records if "garbled status report" in r.getMessage()]
    assert len(device.garbled) == 2 and len(asked_again) == 2, caplog.text
    check_views(out, 9)


def short_waits(monkeypatch, *, wake_s: float = 1.0) -> None:
    """Shorter waits for a test that waits them out (a controller that does not answer): the
    first status report after opening (5 s) and a move's margin (5 s); a reply's own 2 s: 1 s."""
    import rig.grbl

    monkeypatch.setattr(rig.grbl, "WAKE_S", wake_s)
    monkeypatch.setattr(rig.grbl, "MOVE_TIMEOUT_MARGIN_S", 1.0)
    monkeypatch.setattr(rig.grbl, "REPLY_TIMEOUT_S", 1.0)


def test_a_controller_that_dies_mid_capture_is_named_as_the_cause(make_device, tmp_path, capsys, monkeypatch):
    device = make_device()
    out = tmp_path / "cap"
    short_waits(monkeypatch)
    at_view(monkeypatch, out, 2, device.power_off)
    assert main(capture_args(out, device, rows=3, cols=3)) == 2
    err = capsys.readouterr().err
    assert "does not answer a status query either" in err or "stopped answering" in err, err
    assert "last report" not in err and "Ctrl-C" not in err, err
    assert len(views_in(out)) == 2
    assert main(["stage", "status", "--stage", device.url]) == 2  # read-only: says what may be wrong
    err = capsys.readouterr().err
    assert "no status report within 1 s" in err and "off" in err, err


def test_the_port_is_closed_to_other_programs_while_lfrig_holds_it(make_device):
    device = make_device()
    os.chmod(device.path, 0o666)  # open to every user, as a udev rule opens a USB serial adapter
    cat = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "timeout", "1", "cat", device.path]
    with GrblStage(device.path) as stage:
        done = subprocess.run(cat, capture_output=True, text=True, timeout=30)
        assert done.returncode == 1 and "busy" in done.stderr.lower(), (done.returncode, done.stderr)
        assert stage.status()["state"] == "Alarm"
    done = subprocess.run(cat, capture_output=True, text=True, timeout=30)
    # lfrig let go: cat opens it and reads (to the end: pyserial leaves VMIN=0, or to the timeout)
    assert done.returncode in (0, 124) and not done.stderr, (done.returncode, done.stderr)


def test_a_program_that_reads_the_port_is_named(make_device, capsys, caplog, monkeypatch):
    device = make_device()
    cat = subprocess.Popen(["cat", device.path], stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 10
        while (cat.pid, "cat") not in port_holders(device.path):
            assert time.monotonic() < deadline, port_holders(device.path)
            time.sleep(0.02)
        short_waits(monkeypatch)
        code = main(["stage", "status", "--stage", device.url])
        err = capsys.readouterr().err
        # named when the port opens; then whichever reads a reply first takes it: lfrig gets its
        # report, or names the program again in the error
        warned = [r.getMessage() for r in caplog.records if "also has the port open" in r.getMessage()]
        assert warned and f"process {cat.pid} (cat)" in warned[0], caplog.text
        assert code == 0 or f"process {cat.pid} (cat)" in err, err
    finally:
        cat.kill()
        cat.wait()


def test_a_reply_taken_by_another_reader_is_named_as_the_cause(make_device, tmp_path, capsys, monkeypatch):
    """#21.7: a program the exclusive mode does not keep out (root's) reads the `ok` of a move: GRBL
    is Idle with nothing left to run, so the error says the reply went to another reader, not that an
    axis may be stalled."""
    device = make_device(relay=True)
    out = tmp_path / "cap"
    short_waits(monkeypatch)
    at_view(monkeypatch, out, 2, lambda: setattr(device, "take_oks", 1))  # the next move's `ok`
    assert main(capture_args(out, device, rows=3, cols=3)) == 2
    err = capsys.readouterr().err
    assert len(device.taken) == 1, device.taken
    assert "Idle with nothing left to run" in err and "another program read it" in err and "fuser" in err, err
    assert "stalled" not in err, err
    assert len(views_in(out)) == 2


def test_a_settings_listing_with_lines_taken_is_refused(make_device, capsys):
    """#21.7: another reader took `$130=` out of the `$$` listing: no travel check or frame is built
    on what is left."""
    device = make_device(relay=True)
    device.take_lines = [b"$130="]
    assert main(["stage", "move", "-5", "-5", "-2", "--stage", device.url]) == 2
    err = capsys.readouterr().err
    assert device.taken and "without $130" in err and "another program reading the port" in err, err


#: A second reader of the port that keeps reading whatever the port's settings (``cat`` sees the end
#: of its input once lfrig sets the port up, VMIN=0, and exits).
READER = """
import os, select, sys
fd = os.open(sys.argv[1], os.O_RDONLY | os.O_NOCTTY)
while True:
    select.select([fd], [], [])
    os.read(fd, 4096)
"""


def test_a_capture_with_another_reader_on_the_port_names_it(make_device, tmp_path, capsys, monkeypatch):
    """#21.7 with a real second reader: a program that opened the port before lfrig (so the exclusive
    mode cannot keep it out) takes whatever replies it reads first: the capture stops, naming it."""
    device = make_device()
    reader = subprocess.Popen([sys.executable, "-c", READER, device.path])
    try:
        deadline = time.monotonic() + 10
        while reader.pid not in [pid for pid, _ in port_holders(device.path)]:
            assert time.monotonic() < deadline, port_holders(device.path)
            time.sleep(0.02)
        name = dict(port_holders(device.path))[reader.pid]
        short_waits(monkeypatch)
        assert main(capture_args(tmp_path / "cap", device, rows=3, cols=3)) == 2
        err = capsys.readouterr().err
        assert f"process {reader.pid} ({name})" in err, err
    finally:
        reader.kill()
        reader.wait()


def test_inch_reports_are_refused(make_device, tmp_path, capsys):
    device = make_device({13: 1})
    assert main(capture_args(tmp_path / "cap", device, "--dry-run", rows=3, cols=3)) == 2
    assert "set $13=0" in capsys.readouterr().err
    before = device.carriage_mm()
    assert main(["stage", "move", "-5", "-5", "-2", "--home", "--stage", device.url]) == 2
    assert "set $13=0" in capsys.readouterr().err
    assert device.carriage_mm() == before


def test_targets_between_motor_steps_are_refused_before_anything_moves(make_device, tmp_path, capsys):
    device = make_device({100: 40})  # 0.025 mm steps on X
    out = tmp_path / "cap"
    assert main(capture_args(out, device, "--dry-run", "--pitch-mm", "0.31", rows=3, cols=3)) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "$100=40 steps/mm" in err, err
    assert main(capture_args(out, device, "--pitch-mm", "0.31", rows=3, cols=3)) == 2
    err = capsys.readouterr().err
    assert "$100=40 steps/mm" in err and "home it" not in err, err
    assert views_in(out) == []
    on_grid = tmp_path / "on-grid"
    assert main(capture_args(on_grid, device, "--pitch-mm", "0.3", rows=3, cols=3)) == 0, capsys.readouterr().err
    check_views(on_grid, 9)
