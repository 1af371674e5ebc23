"""GRBL wire protocol (pure encode/parse), the driver's exact bytes, and the fake controller's behaviour."""

from __future__ import annotations

import math

import pytest
import serial

from rig.errors import RigError
from rig.clock import VirtualClock
from rig.fakegrbl import FakeGrbl
from rig.urlhandler.protocol_fakegrbl import Serial as FakeGrblSerial, register, unregister
from rig.grbl import (
    Alarm,
    Error,
    GrblAlarmError,
    GrblCommandError,
    GrblConnectionError,
    GrblLimitError,
    GrblStage,
    Message,
    Ok,
    Setting,
    StartupLine,
    Unknown,
    Welcome,
    describe_alarm,
    describe_error,
    encode_dwell,
    encode_home,
    encode_line,
    encode_modes,
    encode_move,
    encode_output,
    encode_settings_query,
    encode_unlock,
    motion_time_s,
    open_port,
    parse_line,
    parse_status,
    feed_hold_time_s,
    homing_time_bound_s,
    step_grid_offsets_mm,
    travel_limits_mm,
    GrblProtocolError,
)

# -- encoding: exact bytes -------------------------------------------------------------------------


def test_exact_bytes_of_each_command():
    assert encode_move((-1.5, -2, -3)) == b"G53 G0 X-1.500 Y-2.000 Z-3.000\n"
    assert encode_move((0.0004, -0.0004, 12.3456), feed_mm_min=250) == b"G53 G1 X0.000 Y0.000 Z12.346 F250.0\n"
    assert encode_modes() == b"G90 G21\n"
    assert encode_dwell(0) == b"G4 P0\n"
    assert encode_dwell(0.25) == b"G4 P0.25\n"
    assert encode_home() == b"$H\n"
    assert encode_unlock() == b"$X\n"
    assert encode_settings_query() == b"$$\n"
    assert encode_output(True) == b"M8\n" and encode_output(False) == b"M9\n"


@pytest.mark.parametrize("bad", ["G0 X1?", "G0\nX1", "G0 X1!", "G0 X1~", "G0 X\x18", "G0 Xé", "G1 X" + "1" * 80])
def test_encode_line_refuses_what_grbl_would_misread(bad):
    with pytest.raises(ValueError):
        encode_line(bad)


def test_encode_move_refuses_nonsense():
    with pytest.raises(ValueError):
        encode_move((1, 2))
    with pytest.raises(ValueError):
        encode_move((1, 2, math.nan))
    with pytest.raises(ValueError):
        encode_move((1, 2, 3), feed_mm_min=0)


# -- parsing ---------------------------------------------------------------------------------------


def test_parse_status_mpos_and_fields():
    s = parse_status("<Run|MPos:-10.000,-2.500,-1.000|FS:600,0|Bf:14,127|Pn:XZ|Ov:100,100,100>")
    assert s.state == "Run" and s.substate is None
    assert s.mpos_mm == (-10.0, -2.5, -1.0)
    assert s.feed_mm_min == 600 and s.buffer == (14, 127) and s.pins == "XZ"
    assert s.wpos_mm is None  # no offset known yet


def test_parse_status_wpos_uses_wco_now_or_remembered():
    s = parse_status("<Idle|WPos:1.000,2.000,3.000|FS:0,0|WCO:-5.000,-5.000,-1.000>")
    assert s.mpos_mm == (-4.0, -3.0, 2.0) and s.wco_mm == (-5.0, -5.0, -1.0)
    later = parse_status("<Hold:1|WPos:1.000,2.000,3.000|F:10>", wco_mm=s.wco_mm)
    assert later.state == "Hold" and later.substate == 1 and later.mpos_mm == (-4.0, -3.0, 2.0)
    assert later.feed_mm_min == 10
    assert parse_status("<Idle|WPos:1.000,2.000,3.000>").mpos_mm is None


@pytest.mark.parametrize(
    "text, expected",
    [
        ("ok", Ok()),
        ("error:9", Error(9)),
        ("ALARM:2", Alarm(2)),
        ("Grbl 1.1h ['$' for help]", Welcome("1.1h")),
        ("[MSG:'$H'|'$X' to unlock]", Message("MSG", "'$H'|'$X' to unlock")),
        ("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", Message("GC", "G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0")),
        ("$110=600.000", Setting(110, 600.0)),
        ("<Idle|MPos:1.0,2.0>", Unknown("<Idle|MPos:1.0,2.0>")),  # garbled: only two axes
        ("<Idel|MPos:1,2,3>", Unknown("<Idel|MPos:1,2,3>")),
        ("<Idle|MPos:1,2,3|FS>", Unknown("<Idle|MPos:1,2,3|FS>")),
        ("error:x", Unknown("error:x")),
        (">G54:ok", StartupLine("G54", "ok")),  # a startup block ($N0) echoed after a reset
        (">G20 G91:error:20", StartupLine("G20 G91", "error:20")),
        ("ok\r", Ok()),
    ],
)
def test_parse_line(text, expected):
    assert parse_line(text) == expected


def test_error_and_alarm_exceptions_name_grbls_meaning():
    assert "locked out" in str(GrblCommandError(9, "G0 X1"))
    assert "home the stage first" in str(GrblCommandError(9, "G0 X1"))
    assert "error:20" in str(GrblCommandError(20, "G38.2 X1")) and "unsupported" in describe_error(20)
    message = str(GrblAlarmError(1, "/dev/ttyUSB0", "a move"))
    assert "ALARM:1" in message and "hard limit" in message and "/dev/ttyUSB0" in message
    assert "soft limit" in describe_alarm(2)
    assert "unknown" in describe_error(999) and "unknown" in describe_alarm(99)
    assert issubclass(GrblCommandError, RigError) and issubclass(GrblAlarmError, RigError)


def test_travel_limits_are_grbl_1_1h_machine_space_less_the_pull_off_at_the_switch():
    settings = {130: 100.0, 131: 80.0, 132: 50.0, 23: 0b010}
    assert travel_limits_mm(settings) == ((-100.0, 0.0), (-80.0, 0.0), (-50.0, 0.0))  # [-max, 0] whatever $23
    settings[27] = 1.5
    assert travel_limits_mm(settings) == ((-100.0, -1.5), (-78.5, 0.0), (-50.0, -1.5))
    assert travel_limits_mm({130: 1.0}) is None


def test_homing_and_feed_hold_times_follow_the_settings():
    settings = {130: 100.0, 131: 100.0, 132: 50.0, 25: 600.0, 24: 60.0, 27: 1.0, 26: 0.0,
                110: 6000.0, 111: 6000.0, 112: 6000.0, 120: 1e9, 121: 1e9, 122: 1e9}
    # search 1.5 x travel at 10 mm/s, two 1 mm pull-offs at 10 mm/s, locate 5 mm at 1 mm/s, per axis
    expected = sum(1.5 * t / 10.0 + 2 * 1.0 / 10.0 + 5.0 for t in (100.0, 100.0, 50.0))
    assert homing_time_bound_s(settings) == pytest.approx(expected, rel=1e-6)
    settings[25] = 300.0
    assert homing_time_bound_s(settings) > expected + 30  # slower seek: longer
    assert feed_hold_time_s(500.0, {120: 10.0, 121: 20.0, 122: 5.0}) == pytest.approx(500 / 60 / 5.0)
    assert feed_hold_time_s(0.0, {}) == 0.0


# -- the driver's bytes on the wire, against the fake --------------------------------------------


@pytest.fixture
def fake():
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock)
    url = register(controller)
    yield clock, controller, url
    unregister(url)


def wire_since(controller, mark):
    return bytes(controller.rx_log[mark:])


def test_driver_sends_exactly_these_bytes(fake):
    clock, controller, url = fake
    stage = GrblStage(url, clock=clock)
    # wake, status query (answered after the welcome of the reset on open), reset, settings, status
    assert wire_since(controller, 0) == b"\r\n\r\n?\x18$$\n?"
    assert stage.version == "1.1h" and stage.limits_mm() == ((-100.0, -1.0), (-100.0, -1.0), (-50.0, -1.0))
    assert stage.reset_seen and stage.open_state == "Alarm" and "reset when the port opened" in stage.machine_frame_doubt()
    mark = len(controller.rx_log)
    stage.home()
    assert wire_since(controller, mark) == b"$H\nG90 G21\n"
    assert stage.homed and stage.machine_frame_doubt() is None
    mark = len(controller.rx_log)
    stage.move_to((-10, -20.25, -5))
    assert wire_since(controller, mark) == b"G53 G0 X-10.000 Y-20.250 Z-5.000\n"
    mark = len(controller.rx_log)
    assert stage.wait_until_idle() == (-10.0, -20.25, -5.0)
    assert wire_since(controller, mark) == b"G4 P0\n?"
    mark = len(controller.rx_log)
    stage.move_to((-10.5, -20.25, -5), feed_mm_min=120)
    stage.wait_until_idle()
    assert wire_since(controller, mark) == b"G53 G1 X-10.500 Y-20.250 Z-5.000 F120.0\nG4 P0\n?"
    mark = len(controller.rx_log)
    stage.set_output(True)
    stage.set_output(False)
    assert wire_since(controller, mark) == b"M8\nM9\n"
    mark = len(controller.rx_log)
    stage.unlock()
    assert wire_since(controller, mark) == b"$X\nG90 G21\n"
    mark = len(controller.rx_log)
    stage.stop()
    sent = wire_since(controller, mark)
    assert sent.startswith(b"!") and sent.endswith(b"\x18")
    stage.close()


def test_move_outside_travel_is_not_sent(fake):
    clock, controller, url = fake
    with GrblStage(url, clock=clock) as stage:
        stage.home()
        mark = len(controller.rx_log)
        with pytest.raises(GrblLimitError, match=r"X=1\.000 mm is outside"):
            stage.move_to((1.0, -1.0, -1.0))
        assert wire_since(controller, mark) == b""


def test_move_before_homing_is_refused_with_error_9(fake):
    clock, controller, url = fake
    with GrblStage(url, clock=clock) as stage:
        with pytest.raises(GrblCommandError, match=r"error:9 \(G-code is locked out"):
            stage.move_to((-1.0, -1.0, -1.0))
        assert not controller.is_moving()


def test_soft_limit_alarm_from_the_controller(fake):
    """With the driver's own check bypassed, GRBL's soft limit raises ALARM:2 and waits for a reset."""
    clock, controller, url = fake
    with GrblStage(url, clock=clock) as stage:
        stage.home()
        with pytest.raises(GrblAlarmError, match=r"ALARM:2 .*soft limit"):
            stage.command("G0 X5")
        assert controller.critical
        controller.receive(b"?")
        assert controller.take_output() == b""  # no reports during a critical alarm
        stage.reset()
        assert stage.status()["state"] == "Alarm"
        stage.unlock()
        assert stage.status()["state"] == "Idle"


def test_pyserial_url_handler():
    controller = FakeGrbl()
    url = register(controller, "handler-test")
    try:
        port = serial.serial_for_url(url, timeout=0.1)
        assert isinstance(port, FakeGrblSerial) and port.controller is controller
        assert b"Grbl 1.1h" in port.read(100)
        port.close()
        with pytest.raises(GrblConnectionError, match="no fake GRBL controller is registered as 'nobody'"):
            open_port("fakegrbl://nobody")
        fresh = serial.serial_for_url("fakegrbl://?clock=virtual", timeout=0.1)
        assert fresh.controller is not controller
    finally:
        unregister(url)


# -- the fake controller's physics and state machine --------------------------------------------


def run_lines(controller, clock, *lines, wait_s=60.0):
    """Send lines one at a time (like the driver) and collect the replies."""
    replies = []
    for line in lines:
        controller.receive(line.encode() + b"\n")
        deadline = clock.monotonic() + wait_s
        buffer = controller.take_output()
        while b"ok" not in buffer and b"error" not in buffer and b"ALARM" not in buffer:
            event = controller.next_event_time()
            assert event is not None and event <= deadline, (line, buffer)
            clock.sleep(max(event - clock.monotonic(), 0))
            buffer += controller.take_output()
        replies.append(buffer.decode())
    return replies


def homed_controller(**kwargs):
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock, **kwargs)
    controller.power_on()
    controller.take_output()
    replies = run_lines(controller, clock, "$H")
    assert replies[-1].strip().endswith("ok")
    return clock, controller


def test_fake_motion_time_follows_feed_and_acceleration():
    clock, controller = homed_controller()
    t0 = clock.monotonic()
    run_lines(controller, clock, "G1 X-21 F300", "G4 P0")  # 20 mm at 5 mm/s, 50 mm/s^2
    expected = motion_time_s(20.0, rate_mm_min=300, accel_mm_s2=50.0)
    assert clock.monotonic() - t0 == pytest.approx(expected, rel=1e-9)
    assert controller.counter_position() == (-21.0, -1.0, -1.0)
    t0 = clock.monotonic()
    run_lines(controller, clock, "G0 X-21.2", "G4 P0")  # short move: triangular profile, rapid rate
    assert clock.monotonic() - t0 == pytest.approx(motion_time_s(0.2, rate_mm_min=600, accel_mm_s2=50.0))


def test_fake_ok_comes_at_planning_and_dwell_waits_for_the_motion():
    clock, controller = homed_controller()
    replies = run_lines(controller, clock, "G0 X-50")
    assert replies == ["ok\r\n"] and controller.is_moving()
    run_lines(controller, clock, "G4 P0")
    assert not controller.is_moving() and controller.counter_position()[0] == -50.0


def test_fake_positions_are_whole_steps():
    clock, controller = homed_controller()
    run_lines(controller, clock, "G0 X-10.0003 Y-10.0007", "G4 P0")
    x, y, _ = controller.counter_position()
    assert x * 800 == pytest.approx(round(x * 800)) and y * 800 == pytest.approx(round(y * 800))
    assert abs(x + 10.0003) <= 0.5 / 800 and abs(y + 10.0007) <= 0.5 / 800


def test_fake_feed_hold_resume_and_reset_in_motion():
    clock, controller = homed_controller()
    run_lines(controller, clock, "G0 X-60")
    clock.sleep(1.0)
    controller.receive(b"!")
    clock.sleep(0.001)
    controller.receive(b"?")
    assert controller.take_output().startswith(b"<Hold:1|")
    clock.sleep(1.0)
    controller.receive(b"?")
    report = controller.take_output()
    assert report.startswith(b"<Hold:0|")
    held = controller.counter_position()[0]
    assert -60.0 < held < -1.0
    controller.receive(b"~")
    run_lines(controller, clock, "G4 P0")
    assert controller.counter_position()[0] == -60.0
    run_lines(controller, clock, "G0 X-1")
    clock.sleep(0.5)
    controller.receive(b"\x18")
    out = controller.take_output()
    assert b"ALARM:3" in out and b"Grbl 1.1h" in out and controller.state == "Alarm"


def test_fake_g_code_errors_like_grbl():
    clock, controller = homed_controller()
    assert run_lines(controller, clock, "G1 X-2") == ["error:22\r\n"]  # no feed yet
    assert run_lines(controller, clock, "G0 G1 X-2") == ["error:21\r\n"]
    assert run_lines(controller, clock, "G0 X-2 X-3") == ["error:25\r\n"]
    assert run_lines(controller, clock, "G38.2 Z-5") == ["error:20\r\n"]
    assert run_lines(controller, clock, "G4") == ["error:28\r\n"]
    assert run_lines(controller, clock, "#0 X1") == ["error:1\r\n"]
    assert run_lines(controller, clock, "G0 X-1.2.3") == ["error:2\r\n"]
    assert run_lines(controller, clock, "$Q") == ["error:3\r\n"]
    assert run_lines(controller, clock, "g0 x-2 (comment) ; rest") == ["ok\r\n"]


def test_fake_report_in_work_coordinates():
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock, settings={10: 0})
    url = register(controller)
    try:
        with GrblStage(url, clock=clock) as stage:
            stage.home()
            assert stage.position() == (-1.0, -1.0, -1.0)
    finally:
        unregister(url)


def test_fake_garbled_reply_lines_are_ignored(fake):
    clock, controller, url = fake
    with GrblStage(url, clock=clock) as stage:
        stage.home()
        controller._out += b"<Idle|MPos:-1.0\xff\r\n"  # noise on the line before the real report
        assert stage.position() == (-1.0, -1.0, -1.0)


def test_homing_timeout_comes_from_travel_and_seek_rate():
    """A long, slow stage homes for longer than the 120 s the driver once allowed."""
    clock = VirtualClock()
    slow = {130: 1000.0, 131: 1000.0, 132: 500.0, 25: 100.0, 110: 1000.0, 111: 1000.0, 112: 1000.0}
    controller = FakeGrbl(clock=clock, settings=slow, start_mm=(-900.0, -900.0, -400.0))
    url = register(controller)
    try:
        with GrblStage(url, clock=clock) as stage:
            t0 = clock.monotonic()
            stage.home()
            assert clock.monotonic() - t0 > 600  # Z then X and Y at 100 mm/min
            assert stage.position() == (-1.0, -1.0, -1.0)
            assert stage.home_timeout_s > clock.monotonic() - t0
    finally:
        unregister(url)


def test_stop_waits_for_the_hold_at_slow_acceleration():
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock, settings={120: 5.0, 121: 5.0, 122: 5.0, 110: 600.0, 111: 600.0, 112: 600.0})
    url = register(controller)
    try:
        with GrblStage(url, clock=clock) as stage:
            stage.home()
            stage.move_to((-90.0, -1.0, -1.0))
            clock.sleep(4.0)  # cruising at 10 mm/s: 2 s to stop
            stage.stop()
            assert 3 not in controller.alarms and stage.homing_required is None
            assert stage.status()["state"] == "Idle"
    finally:
        unregister(url)


def test_fake_port_is_exclusive_like_a_tty(fake):
    clock, controller, url = fake
    with GrblStage(url, clock=clock):
        with pytest.raises(GrblConnectionError, match="in use by another program"):
            GrblStage(url, clock=clock)
    GrblStage(url, clock=clock).close()  # free again


def test_fake_work_offsets_g53_and_23(fake):
    clock, controller, url = fake
    controller.settings[23] = 0b001
    with GrblStage(url, clock=clock) as stage:
        stage.home()
        assert stage.position() == (-99.0, -1.0, -1.0)  # X homed to its minimum: -max + pull-off
        stage.command("G10 L2 P1 X5 Y6 Z7")
        stage.command("G0 X-20 Y-20 Z-20")  # work coordinates: offset applied
        stage.command("G4 P0", timeout_s=60)
        assert stage.position() == (-15.0, -14.0, -13.0)
        stage.move_to((-20.0, -20.0, -20.0))  # G53: machine coordinates
        assert stage.wait_until_idle() == (-20.0, -20.0, -20.0)
        assert Message("G54", "5.000,6.000,7.000") in stage.command("$#")


def test_step_grid_offsets_are_the_distance_to_grbls_nearest_step():
    settings = {100: 40.0, 101: 250.0, 102: 800.0}
    offsets = step_grid_offsets_mm((-9.69, -9.69, -9.69), settings)
    assert offsets == pytest.approx((0.010, 0.002, 0.0000), abs=1e-9)  # 0.025, 0.004, 0.00125 mm steps
    assert step_grid_offsets_mm((-9.7, 0.0, -1.0), settings) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert max(step_grid_offsets_mm((-1.2345, 2, 3), {})) == 0.0  # steps/mm unknown: nothing to say


def test_status_is_asked_again_after_a_garbled_report(fake, monkeypatch):
    clock, controller, url = fake
    with GrblStage(url, clock=clock) as stage:
        stage.home()
        real = controller._status_report
        garble = {"left": 2}

        def noisy() -> None:
            if garble["left"]:
                garble["left"] -= 1
                controller._emit("<Idle|MPos:-1.0#0,-1.000,-1.000|FS:0,0>")
            else:
                real()

        monkeypatch.setattr(controller, "_status_report", noisy)
        assert stage.position() == (-1.0, -1.0, -1.0)
        assert controller.rx_log.endswith(b"???")  # asked three times
        garble["left"] = GrblStage.STATUS_ATTEMPTS
        with pytest.raises(GrblProtocolError, match=r"garbled status reports in a row .*check the cable"):
            stage.position()


def test_fake_survives_resets_while_homing():
    clock = VirtualClock()
    controller = FakeGrbl(clock=clock)
    controller.power_on()
    controller.take_output()
    controller.receive(b"$H\n")
    clock.sleep(0.5)
    assert controller.state == "Home"
    controller.receive(b"\x18")  # Ctrl-C twice in `lfrig stage home`: a reset, then another
    controller.receive(b"\x18")
    out = controller.take_output().decode()
    assert "ALARM:6" in out and out.count("Grbl 1.1h") == 2 and controller.state == "Alarm"


def test_read_only_connection_sends_no_reset(fake):
    clock, controller, url = fake
    mark = len(controller.rx_log)
    with GrblStage(url, clock=clock, read_only=True) as stage:
        assert stage.status()["state"] == "Alarm" and stage.reset_seen  # the fake resets on open, like an Arduino
        assert stage.limits_mm() == ((-100.0, -1.0), (-100.0, -1.0), (-50.0, -1.0))
    assert b"\x18" not in wire_since(controller, mark) and b"!" not in wire_since(controller, mark)


def test_ctrl_c_while_homing_stops_the_cycle_by_a_reset():
    class CtrlCWhileHoming(VirtualClock):
        armed = True

        def sleep(self, seconds: float) -> None:
            super().sleep(seconds)
            if self.armed and controller.state == "Home" and self.monotonic() > homing_from + 1.0:
                self.armed = False
                raise KeyboardInterrupt

    clock = CtrlCWhileHoming()
    controller = FakeGrbl(clock=clock)
    url = register(controller)
    try:
        with GrblStage(url, clock=clock) as stage:
            homing_from = clock.monotonic()
            with pytest.raises(KeyboardInterrupt):
                stage.home()
            mark = len(controller.rx_log)
            done = stage.interrupt()
            assert wire_since(controller, mark) == b"\x18"  # no feed hold: GRBL ignores one while homing
            assert "homing stopped" in done and "ALARM:6" in done
            assert stage.homing_required and not stage.homed
            with pytest.raises(GrblAlarmError, match="home"):
                stage.move_to((-5.0, -5.0, -5.0))
    finally:
        unregister(url)
