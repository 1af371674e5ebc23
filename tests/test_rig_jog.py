"""``lfrig stage jog`` through a pseudo-terminal: keys in, the controller's reported position out, on
the fake stage and on the real GRBL 1.1h firmware (``../shared/grbl-sim``, built once per test
session by ``tests/conftest.py``'s fixture), whose own carriage report is the judge."""

from __future__ import annotations

import os
import re
import select
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from grbl_devices import FakeOnPty, Firmware
from rig.jog import JogSettings, decode_keys

ROOT = Path(__file__).resolve().parents[1]
RIGHT, LEFT, UP, DOWN, PGUP, PGDN = b"\x1b[C", b"\x1b[D", b"\x1b[A", b"\x1b[B", b"\x1b[5~", b"\x1b[6~"
POSITION = re.compile(rb"X\s+(-?\d+\.\d{3})\s+Y\s+(-?\d+\.\d{3})\s+Z\s+(-?\d+\.\d{3}) mm\s+(\w+)")


class Session:
    """``lfrig stage jog`` on the slave side of a pty; the test types on the master side."""

    def __init__(self, *args: str) -> None:
        self.master, self.slave = os.openpty()
        self.before = termios.tcgetattr(self.slave)
        self.output = b""
        self.proc = subprocess.Popen([sys.executable, "-m", "rig.main", "stage", "jog", *args], cwd=ROOT,
                                     stdin=self.slave, stdout=self.slave, stderr=self.slave)
        self.read_until(b"q: quit", timeout_s=60)

    def read_until(self, pattern: bytes | re.Pattern, *, timeout_s: float = 20) -> re.Match:
        regex = pattern if isinstance(pattern, re.Pattern) else re.compile(re.escape(pattern))
        deadline = time.monotonic() + timeout_s
        start = len(self.output)
        while True:
            match = regex.search(self.output, start)
            if match:
                return match
            if time.monotonic() > deadline or self.proc.poll() is not None and not self._pending():
                raise AssertionError(f"{pattern!r} not seen; output: {self.output[-2000:]!r}")
            self._read(0.1)

    def _pending(self) -> bool:
        return bool(select.select([self.master], [], [], 0.2)[0])

    def _read(self, timeout_s: float) -> None:
        if select.select([self.master], [], [], timeout_s)[0]:
            try:
                self.output += os.read(self.master, 65536)
            except OSError:
                pass

    def keys(self, *keys: bytes) -> None:
        for key in keys:
            os.write(self.master, key)
            time.sleep(0.05)

    def position(self, expected: tuple[float, float, float], *, timeout_s: float = 20) -> tuple[float, ...]:
        """Wait until the status line shows the stage standing still at ``expected`` (mm)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._read(0.2)
            shown = POSITION.findall(self.output)
            if shown:
                *xyz, state = shown[-1]
                here = tuple(float(c) for c in xyz)
                if state == b"Idle" and max(abs(a - b) for a, b in zip(here, expected)) < 0.0041:
                    return here
        raise AssertionError(f"never Idle at {expected}; last lines {self.output[-600:]!r}")

    def finish(self, *, timeout_s: float = 30) -> tuple[int, str]:
        deadline = time.monotonic() + timeout_s
        while self.proc.poll() is None and time.monotonic() < deadline:
            self._read(0.1)
        if self.proc.poll() is None:
            self.proc.kill()
            raise AssertionError(f"jog did not quit; output {self.output[-1000:]!r}")
        while self._pending():
            self._read(0.1)
        after = termios.tcgetattr(self.slave)
        os.close(self.master)
        os.close(self.slave)
        assert after == self.before, "the terminal's settings were not restored"
        return self.proc.returncode, self.output.decode("utf-8", "replace")


def test_keys_are_decoded_also_when_a_sequence_is_split():
    keys, rest = decode_keys(b"\x1b[C\x1bOAq+\x1b[6~\x1b[")
    assert (keys, rest) == (["right", "up", "quit", "step+", "pgdn"], b"\x1b[")
    keys, rest = decode_keys(rest + b"5~ x\x1b[15~c")  # F5 (unknown) is skipped, not read as keys
    assert (keys, rest) == (["pgup", "stop", "centre"], b"")
    settings = JogSettings.nearest(step_mm=0.12, feed_mm_min=480)
    assert (settings.step_mm, settings.feed_mm_min) == (0.1, 500.0)
    for _ in range(20):
        settings.change("step+")
    assert settings.step_mm == 10.0


@pytest.fixture(params=["fake", "firmware"])
def device(request, tmp_path):
    if request.param == "firmware":
        made = Firmware(request.getfixturevalue("firmware_exe"), tmp_path / "grbl",
                        eeprom=request.getfixturevalue("firmware_eeprom"))
    else:
        made = FakeOnPty()
    yield made
    made.close()


def test_jog_moves_by_steps_sets_the_centre_and_quits_cleanly(device):
    session = Session("--stage", device.url, "--home", "--step-mm", "0.1", "--feed-mm-min", "1000")
    session.position((-1.0, -1.0, -1.0))  # homed: pull-off 1 mm from the switches
    session.keys(LEFT, LEFT, LEFT, DOWN, PGDN)
    session.position((-1.3, -1.1, -1.1))
    session.keys(b"+", DOWN, b"-", PGUP)  # step 0.5, then 0.1 again (steps of 1/250 mm: 0.05 is no whole step)
    session.position((-1.3, -1.6, -1.0))
    session.keys(b"c")
    session.read_until(b"grid centre: --centre-mm -1.300 -1.600 -1.000")
    session.keys(b"+", b"+", b"+", b"+", b"+", RIGHT)  # a 10 mm step would leave the travel: refused, not moved
    session.read_until(b"beyond the travel: not moved")
    session.keys(b"q")
    status, text = session.finish()
    assert status == 0, text
    assert "grid centre for lfrig capture: --centre-mm -1.300 -1.600 -1.000" in text
    assert max(abs(a - b) for a, b in zip(device.carriage_mm(), (-1.3, -1.6, -1.0))) < 0.0041


def test_quitting_mid_jog_stops_the_motion(device):
    session = Session("--stage", device.url, "--home", "--step-mm", "10", "--feed-mm-min", "50")
    session.position((-1.0, -1.0, -1.0))
    session.keys(LEFT)  # 10 mm at 50 mm/min: 12 s; quit after about 0.5 s, so it stops far short of -11
    session.read_until(re.compile(rb"Jog"))
    time.sleep(0.5)
    started = time.monotonic()
    session.keys(b"\x03")  # Ctrl-C arrives as a key: stop and quit
    status, text = session.finish()
    assert status == 0 and time.monotonic() - started < 5, text
    stopped = re.findall(r"stopped at X\s+(-?\d+\.\d+)", text)
    x = device.carriage_mm()[0]
    assert -6.0 < x < -1.05 and abs(float(stopped[-1]) - x) < 0.0041, (x, text)
    time.sleep(1.0)
    assert abs(device.carriage_mm()[0] - x) < 0.0041  # and it stays stopped


def test_jog_without_a_terminal_is_a_one_line_error():
    done = subprocess.run([sys.executable, "-m", "rig.main", "stage", "jog"], cwd=ROOT, stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "lfrig: error: stage jog reads keys from a terminal, and its input is not one; run it in a terminal "
        "(over SSH: ssh -t), or move with lfrig stage move X Y Z"]


def test_jog_on_the_command_lines_fake_stage():
    """``--stage fake``: the simulated controller in the same process, moving in real time."""
    session = Session("--stage", "fake", "--home", "--step-mm", "1", "--feed-mm-min", "2000")
    session.position((-1.0, -1.0, -1.0), timeout_s=60)
    session.keys(LEFT, LEFT, PGDN, b"c")
    session.read_until(b"grid centre: --centre-mm -3.000 -1.000 -2.000")
    session.keys(b"q")
    status, text = session.finish()
    assert status == 0 and "grid centre for lfrig capture: --centre-mm -3.000 -1.000 -2.000" in text, text


def test_jog_lines_are_answered_as_the_firmware_answers_them(device):
    """Wire level: the jog line lfrig sends, and GRBL's replies to jogs lfrig never sends (the fake
    must answer them as the firmware does)."""
    from rig.grbl import encode_jog

    assert encode_jog((0.1, 0, -0.05), feed_mm_min=500) == b"$J=G91 G21 X0.100 Z-0.050 F500.0\n"
    with pytest.raises(ValueError, match="non-zero step"):
        encode_jog((0.0004, 0, 0), feed_mm_min=500)
    # (the firmware's power-up message may come before the first reply: the last line is the reply)
    assert device.raw(b"$H\n", until=r"ok|error:\d+", timeout_s=30).strip().splitlines()[-1] == "ok"
    replies = [device.raw(line, until=r"ok|error:\d+").strip().splitlines()[-1] for line in (
        b"$J=G91 X1\n", b"$J=G0 G91 X1 F100\n", b"$J=G91 F100\n", b"$J=G91 X50 F100\n", b"$J=G91 M8 X1 F100\n",
        encode_jog((-0.5, 0, 0), feed_mm_min=3000))]
    assert replies == ["error:22", "error:16", "ok", "error:15", "error:16", "ok"]
