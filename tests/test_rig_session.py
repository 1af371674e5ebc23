"""Capture sessions against the fake GRBL on a virtual clock, with a stand-in camera.

The stand-in camera writes the stage's *physical* position (from the fake controller, not from the
driver) into each frame and counts triggers, so the tests can check that each view was taken once,
at its grid position, and never while the stage moved.
"""

from __future__ import annotations

import json
import os
import signal
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from recon.errors import CaptureLayoutError
from rig.clock import VirtualClock
from rig.fakegrbl import FakeGrbl
from rig.urlhandler.protocol_fakegrbl import register, unregister
from rig.grbl import (
    GrblAlarmError,
    GrblCommandError,
    GrblConnectionError,
    GrblStage,
    GrblTimeoutError,
    encode_move,
)
from rig.grid import GridError, GridSpec, plan_moves, view_position
from recon.lf.capture import read_capture
from rig.session import CaptureAborted, CaptureInterrupted, FrameNotProvenError, run_capture

CENTRE = (-50.0, -50.0, -10.0)
SHAPE = (6, 8)


class PositionCamera:
    """Stand-in camera: row 0 holds the physical position in 10 um steps (+ offset) and a serial."""

    def __init__(self, controller: FakeGrbl, *, on_trigger=None) -> None:
        self.controller = controller
        self.triggers = 0
        self.moving_triggers = 0
        self.on_trigger = on_trigger

    def trigger(self) -> np.ndarray:
        self.triggers += 1
        if self.on_trigger is not None:
            self.on_trigger(self.triggers)
        if self.controller.is_moving():
            self.moving_triggers += 1
        x, y, z = self.controller.physical_position()
        image = np.zeros(SHAPE, np.uint16)
        image[0, :3] = [round((c + 200.0) * 100.0) for c in (x, y, z)]
        image[0, 3] = self.triggers
        return image

    def settings(self) -> dict:
        return {"driver": "stand-in", "shape": list(SHAPE)}

    def close(self) -> None:
        pass


def decode(image: np.ndarray) -> tuple[np.ndarray, int]:
    return image[0, :3].astype(float) / 100.0 - 200.0, int(image[0, 3])


@pytest.fixture
def rig():
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock)
    url = register(controller)
    yield clock, controller, url
    unregister(url)


def open_stage(url: str, clock: VirtualClock) -> GrblStage:
    return GrblStage(url, clock=clock)


def view_lines(path: Path) -> list[dict]:
    lines = [json.loads(l) for l in (path / "manifest.jsonl").read_text().splitlines() if l.strip()]
    return [l for l in lines if l["kind"] == "view"]


def check_capture(path: Path, spec: GridSpec) -> None:
    """Every view exactly once in the journal, at its grid position, from distinct triggers."""
    views = view_lines(path)
    counts = Counter((v["u"], v["v"]) for v in views)
    assert sorted(counts) == [(u, v) for u in range(spec.rows) for v in range(spec.cols)]
    assert set(counts.values()) == {1}
    lf = read_capture(path)
    assert lf.views.shape[:2] == (spec.rows, spec.cols)
    serials = []
    for u in range(spec.rows):
        for v in range(spec.cols):
            position, serial = decode(lf.views[u, v])
            np.testing.assert_allclose(position, view_position(spec, u, v), atol=0.011)
            serials.append(serial)
    assert (path / "parameters.cfg").is_file()
    lines = (path / "manifest.jsonl").read_text().splitlines()
    assert json.loads(lines[-1])["kind"] == "complete"


def ctrl_c_twice_at(view: int):
    """A camera trigger hook that presses Ctrl-C twice (two SIGINTs) at trigger number ``view``."""

    def on_trigger(n):
        if n == view:
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)

    return on_trigger


def test_full_81_view_session_on_virtual_clock(rig, tmp_path):
    clock, controller, url = rig
    spec = GridSpec(centre_mm=CENTRE)
    camera = PositionCamera(controller)
    start = time.perf_counter()
    with open_stage(url, clock) as stage:
        result = run_capture(tmp_path / "cap", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    wall = time.perf_counter() - start
    assert result.complete and not result.interrupted and result.taken == 81
    assert camera.triggers == 81 and camera.moving_triggers == 0
    check_capture(tmp_path / "cap", spec)
    # virtual time: homing plus 81 moves with settling takes minutes of simulated time
    assert result.elapsed_s > 81 * 0.2
    log = (tmp_path / "cap" / "session.log").read_text()
    assert "capture complete" in log and "'$H'" in log
    print(f"81 views: {result.elapsed_s:.1f} s simulated, {wall:.2f} s wall")


def test_every_view_is_approached_moving_in_plus_direction(rig, tmp_path):
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=3, centre_mm=CENTRE)
    with open_stage(url, clock) as stage:
        run_capture(tmp_path / "c", stage=stage, camera=PositionCamera(controller), grid=spec, clock=clock, progress=None)
    moves = [l for l in controller.lines_received if l.startswith("G0")]
    positions = [tuple(float(w[1:]) for w in m.split()[1:]) for m in moves]
    targets = {view_position(spec, u, v) for u in range(3) for v in range(3)}
    previous = None
    for p in positions:
        if p in targets and previous is not None:
            assert all(b - a >= -1e-9 for a, b in zip(previous, p)), (previous, p)
        previous = p


def test_resume_with_other_settings_is_refused(rig, tmp_path):
    clock, controller, url = rig
    spec = GridSpec(rows=2, cols=2, centre_mm=CENTRE)
    with open_stage(url, clock) as stage:
        run_capture(tmp_path / "c", stage=stage, camera=PositionCamera(controller), grid=spec, clock=clock,
                    progress=None, should_stop=lambda: True)
        with pytest.raises(CaptureLayoutError, match="pitch_mm|grid"):
            run_capture(tmp_path / "c", stage=stage, camera=PositionCamera(controller),
                        grid=GridSpec(rows=2, cols=2, pitch_mm=1.0, centre_mm=CENTRE), clock=clock, progress=None)


def test_grid_outside_travel_is_refused_before_anything_moves(rig, tmp_path):
    clock, controller, url = rig
    spec = GridSpec(centre_mm=(-1.0, -50.0, -10.0))  # +x half of the grid is on or beyond the switch side
    with open_stage(url, clock) as stage:  # travel ends 1 mm ($27 pull-off) before the switch at 0
        with pytest.raises(GridError, match=r"view \(0, 5\) needs x = -0\.500 mm, outside .*-1\.000\]"):
            run_capture(tmp_path / "c", stage=stage, camera=PositionCamera(controller), grid=spec, clock=clock,
                        progress=None)
    assert b"$H" not in controller.rx_log and b"G0" not in controller.rx_log


def test_stop_request_finishes_the_view_then_resume_completes(rig, tmp_path):
    clock, controller, url = rig
    spec = GridSpec(rows=4, cols=5, centre_mm=CENTRE)
    camera = PositionCamera(controller)
    with open_stage(url, clock) as stage:
        result = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None,
                             should_stop=lambda: camera.triggers >= 7)
    assert result.interrupted and result.completed == 7 and camera.triggers == 7
    with open_stage(url, clock) as stage:
        result = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    assert result.complete and result.taken == 13 and camera.triggers == 20
    check_capture(tmp_path / "c", spec)


def test_first_sigint_finishes_current_view_and_stops(rig, tmp_path):
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=4, centre_mm=CENTRE)

    def on_trigger(n):
        if n == 5:
            os.kill(os.getpid(), signal.SIGINT)

    camera = PositionCamera(controller, on_trigger=on_trigger)
    with open_stage(url, clock) as stage:
        result = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    assert result.interrupted and result.completed == 5 and camera.triggers == 5
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with open_stage(url, clock) as stage:
        run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    assert camera.triggers == 12
    check_capture(tmp_path / "c", spec)


def test_second_sigint_sends_feed_hold_and_reset(rig, tmp_path):
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=4, centre_mm=CENTRE)

    camera = PositionCamera(controller, on_trigger=ctrl_c_twice_at(3))
    with open_stage(url, clock) as stage:
        before = len(controller.rx_log)
        with pytest.raises(CaptureInterrupted, match="second Ctrl-C"):
            run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
        tail = bytes(controller.rx_log[before:])
        assert b"!" in tail and tail.rindex(b"\x18") > tail.rindex(b"!")
    with open_stage(url, clock) as stage:
        run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    check_capture(tmp_path / "c", spec)
    assert len(view_lines(tmp_path / "c")) == 12


FAULT_CASES = [
    ("lost_ok", GrblTimeoutError, r"did not answer 'G53 G0 X.*not sent again"),
    ("garbled", GrblCommandError, r"error:1 \(a G-code word has no letter"),
    ("alarm_mid_move", GrblAlarmError, r"ALARM:1 .*hard limit"),
    ("stall", GrblTimeoutError, r"did not finish its move.*stalled"),
    ("disconnect", GrblConnectionError, r"lost the connection"),
]


@pytest.mark.parametrize("kind, error_type, message", FAULT_CASES, ids=[c[0] for c in FAULT_CASES])
def test_fault_gives_clear_error_and_resume_completes(rig, tmp_path, kind, error_type, message):
    clock, controller, url = rig
    spec = GridSpec(rows=5, cols=5, centre_mm=CENTRE)
    camera = PositionCamera(controller)
    controller.arm_fault(kind, after=12)
    with open_stage(url, clock) as stage:
        with pytest.raises(CaptureAborted) as caught:
            run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    assert isinstance(caught.value.__cause__, error_type)
    assert caught.value.__cause__ is not None
    import re

    assert re.search(message, str(caught.value)), str(caught.value)
    assert "run the same command again to resume" in str(caught.value)
    first = camera.triggers
    assert 0 < first < 25
    with open_stage(url, clock) as stage:  # reconnecting resets the controller, like an Arduino
        result = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    assert result.complete and result.taken == 25 - first
    assert camera.triggers == 25 and camera.moving_triggers == 0  # no frame lost or taken twice
    check_capture(tmp_path / "c", spec)


def test_resume_without_homing_needs_the_same_machine_frame(rig, tmp_path):
    """An Arduino resets when its port opens and GRBL restarts its position at 0 where the carriage
    stands: a resume without homing after that must refuse, not take shifted views."""
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=4, centre_mm=CENTRE)
    camera = PositionCamera(controller)
    with open_stage(url, clock) as stage:
        first = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None,
                            should_stop=lambda: camera.triggers >= 5)
        assert first.interrupted and camera.triggers == 5
        # same connection, homed, standing at the last view: the frame is proven
        second = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None,
                             home=False, should_stop=lambda: camera.triggers >= 8)
        assert second.taken == 3
    with open_stage(url, clock) as stage:  # reset on open
        with pytest.raises(FrameNotProvenError, match="cannot prove .* reset when the port opened"):
            run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None, home=False)
        assert camera.triggers == 8 and not controller.is_moving()
    with open_stage(url, clock) as stage:
        stage.unlock()  # unlocked, but the frame is still the one GRBL powered up in
        with pytest.raises(FrameNotProvenError, match="cannot prove"):
            run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None, home=False)
        stage.home()  # homed since power-up: proven, wherever the stage now stands
        result = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None,
                             home=False)
    assert result.complete and camera.triggers == 12
    check_capture(tmp_path / "c", spec)


def test_resume_without_homing_after_a_reset_with_homing_disabled(tmp_path):
    """$22=0 (GRBL's default): no lock after the reset on open, so nothing but the driver's evidence
    of the reset stops a resume in a frame shifted by wherever the carriage stood."""
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock, settings={22: 0, 20: 0})
    url = register(controller)
    try:
        spec = GridSpec(rows=3, cols=4, centre_mm=CENTRE)
        camera = PositionCamera(controller)
        with open_stage(url, clock) as stage:
            first = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None,
                                home=False, should_stop=lambda: camera.triggers >= 5)
            assert first.interrupted
        with open_stage(url, clock) as stage:  # the reset on open re-zeroes GRBL where the carriage stands
            assert stage.status()["state"] == "Idle"
            with pytest.raises(FrameNotProvenError, match="restarted at 0 wherever the carriage stood"):
                run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None,
                            home=False)
        assert camera.triggers == 5 and len(view_lines(tmp_path / "c")) == 5
    finally:
        unregister(url)


def test_third_sigint_while_stopping_does_not_abort_the_stop(rig, tmp_path, capsys):
    """#13: a third Ctrl-C during the feed hold + soft reset raised _HardStop out of stage.stop():
    a traceback, and no soft reset sent. Now it is ignored (with a word) and the stop completes."""
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=4, centre_mm=CENTRE)

    camera = PositionCamera(controller, on_trigger=ctrl_c_twice_at(3))
    with open_stage(url, clock) as stage:
        original_stop = stage.stop

        def impatient_stop():
            os.kill(os.getpid(), signal.SIGINT)  # the third Ctrl-C, while stopping
            original_stop()

        stage.stop = impatient_stop
        before = len(controller.rx_log)
        with pytest.raises(CaptureInterrupted, match="second Ctrl-C"):
            run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
        tail = bytes(controller.rx_log[before:])
        assert b"!" in tail and tail.rindex(b"\x18") > tail.rindex(b"!")
    assert "already stopping the stage" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_frame_losing_alarm_is_journalled_and_only_homing_answers_it(rig, tmp_path):
    """#21: the doubt an abort leaves is kept in the capture folder, so a resume without homing
    refuses even where its own connection saw nothing (here: a controller that does not reset on
    open, unlocked by another program and moved back to the last view); a resume that homes answers it."""
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=3, centre_mm=CENTRE)
    camera = PositionCamera(controller)
    controller.arm_fault("alarm_mid_move", after=4)
    with open_stage(url, clock) as stage:
        with pytest.raises(CaptureAborted, match="ALARM:1"):
            run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    records = [json.loads(line) for line in (tmp_path / "c" / "manifest.jsonl").read_text().splitlines()]
    doubts = [r for r in records if r["kind"] == "doubt"]
    assert len(doubts) == 1 and "ALARM:1" in doubts[0]["reason"], records
    taken = len(view_lines(tmp_path / "c"))
    last = view_lines(tmp_path / "c")[-1]["readback_mm"]
    with open_stage(url, clock) as stage:
        stage.reset_seen, stage.open_state = False, "Idle"  # what a controller that does not reset would show
        stage.command("$X")
        stage.prepare()
        stage.move_to(last)
        stage.wait_until_idle()
        with pytest.raises(FrameNotProvenError, match="journal records it: GRBL raised ALARM:1"):
            run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None, home=False)
        assert len(view_lines(tmp_path / "c")) == taken
        result = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None)
    assert result.complete
    kinds = [json.loads(line)["kind"] for line in (tmp_path / "c" / "manifest.jsonl").read_text().splitlines()]
    assert kinds.index("homed") > kinds.index("doubt")
    check_capture(tmp_path / "c", spec)


def test_the_port_record_is_never_read_or_written_through_a_link(tmp_path):
    """The per-port record (rig.frames.PortRecord) lives under $XDG_STATE_HOME (a folder of its own
    per test, tests/conftest.py); a link planted there is neither followed nor written through."""
    import shutil

    from rig.frames import PortRecord, PortStateError, state_folder

    record = PortRecord.open("/dev/ttyLFRIGTEST0")
    assert json.loads(record.file.read_text())["epoch"] == record.epoch
    victim = tmp_path / "victim"
    victim.write_text("keep")
    record.file.unlink()
    record.file.symlink_to(victim)
    with pytest.raises(PortStateError, match="symbolic link"):
        PortRecord.open("/dev/ttyLFRIGTEST0")
    record.note_doubt("a test")  # replaces the link (atomically), never writes through it
    assert victim.read_text() == "keep" and not record.file.is_symlink()
    assert json.loads(record.file.read_text())["event"].startswith("a test")
    shutil.rmtree(state_folder())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    state_folder().symlink_to(elsewhere)
    with pytest.raises(PortStateError, match="symbolic link"):
        PortRecord.open("/dev/ttyLFRIGTEST0")
    assert list(elsewhere.iterdir()) == []


def test_a_stop_during_a_backlash_take_up_finishes_its_view(rig, tmp_path, monkeypatch):
    """Stopping on the take-up's overshoot would leave the stage 0.2 mm off the journal's last view,
    where a resume without homing looks for it."""
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=3, centre_mm=CENTRE)
    camera = PositionCamera(controller)
    take_ups = {encode_move(m.target_mm).decode().strip() for m in plan_moves(spec) if m.view is None}

    asked = []
    receive = controller.receive

    def receive_and_ask_to_stop(data: bytes) -> None:  # a Ctrl-C the moment a take-up line arrives
        receive(data)
        if camera.triggers >= 3 and controller.lines_received and controller.lines_received[-1] in take_ups:
            asked.append(controller.lines_received[-1])

    monkeypatch.setattr(controller, "receive", receive_and_ask_to_stop)

    def after_a_take_up() -> bool:
        return bool(asked)

    with open_stage(url, clock) as stage:
        result = run_capture(tmp_path / "c", stage=stage, camera=camera, grid=spec, clock=clock, progress=None,
                             should_stop=after_a_take_up)
        # (0, 2) -> (1, 2) goes +y only; (1, 1), reached going -x, is the first view after a take-up
        assert result.interrupted and result.completed == 5
        assert (view_lines(tmp_path / "c")[-1]["u"], view_lines(tmp_path / "c")[-1]["v"]) == (1, 1)
        last = view_lines(tmp_path / "c")[-1]["readback_mm"]
        assert max(abs(a - b) for a, b in zip(stage.position(), last)) <= 0.005


def test_the_session_log_takes_a_line_from_a_signal_handler_mid_write(tmp_path):
    """A Ctrl-C whose handler logs while a line is being written must not re-enter the buffered file
    (RuntimeError: reentrant call): its line is written right after the one in progress."""
    from rig.session import SessionLog

    log = SessionLog(tmp_path / "session.log")
    real_write = log._file.write
    fired = []

    def write_and_be_interrupted(text):
        if not fired:
            fired.append(True)
            log("from the handler")  # what the SIGINT handler does
        return real_write(text)

    log._file.write = write_and_be_interrupted
    log("a view")
    log.close()
    lines = (tmp_path / "session.log").read_text().splitlines()
    assert [line.split("  ", 1)[1] for line in lines] == ["a view", "from the handler"]


def test_the_stage_stops_writing_to_the_session_log_when_the_capture_ends(rig, tmp_path):
    # The stage outlives the capture (the command still asks it where it stands when it lets go of
    # the port): a line it reads then must not go to the capture's closed session.log.
    clock, controller, url = rig
    spec = GridSpec(rows=3, cols=3, centre_mm=CENTRE)
    lines = []
    with open_stage(url, clock) as stage:
        stage.on_line = lambda direction, text: lines.append((direction, text))
        result = run_capture(tmp_path / "cap", stage=stage, camera=PositionCamera(controller), grid=spec,
                             clock=clock, progress=None)
        assert result.complete
        seen = len(lines)
        stage.on_line("<", "[MSG:a line after the capture]")
        assert lines[seen:] == [("<", "[MSG:a line after the capture]")]
    log = (tmp_path / "cap" / "session.log").read_text()
    assert "capture complete" in log and "after the capture" not in log
