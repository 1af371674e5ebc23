"""Two GRBL controllers on a pseudo-terminal, for the stage suite (``tests/test_stage_devices.py``).

- :class:`Firmware`: the real GRBL 1.1h firmware, built for the host from ``../shared/grbl-sim``
  (never copied into the project) and run as a process whose standard input/output is the master
  side of a pty pair; lfrig opens the slave side's path like a USB serial port.
- :class:`FakeOnPty`: ``rig.fakegrbl.FakeGrbl`` on the wall clock, served on a pty pair by a thread.

Both look the same to lfrig (a device path, 115200 baud) and to the tests: ``restart`` power-cycles
the controller with its carriage where it stands (or at ``start_mm``), ``carriage_mm`` is where the
carriage physically is in the machine frame homing defines (the firmware's ``%`` debug report, the
fake's physical position), ``raw`` talks to the controller directly while lfrig does not hold it.
Neither resets when the port opens (a real Arduino does: ``fakegrbl://`` models that).

Three faults of the world between them, on both: ``power_cycle(boot_s=...)`` restarts the controller
like a board whose bootloader runs first (bytes sent meanwhile are lost, the welcome line comes after
``boot_s``), ``garble_reports = N`` corrupts the next N status reports on their way to lfrig, and
``take_oks = N`` (or ``take_lines``, by prefix) takes the next N ``ok`` replies away, as another
reader of the port would (the firmware's output then passes through a relay thread:
``make(relay=True)``).

The test process keeps the slave side open (in raw mode) for the controller's whole life, so the
controller never sees a hang-up between two lfrig runs; pyserial flushes what arrived meanwhile when
it opens the port, as it does with a USB serial adapter.
"""

from __future__ import annotations

import os
import re
import select
import shutil
import signal
import subprocess
import threading
import time
import tty
from pathlib import Path
from typing import Sequence

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
GRBL_SIM = SHARED / "grbl-sim"

#: A small, fast stage for tests: 20 x 20 x 10 mm travel, 250 steps/mm, 3000 mm/min, 500 mm/s^2,
#: homing on (seek 1500, locate 300 mm/min, pull-off 1 mm), soft limits on, hard limits off, MPos reports.
FAST: dict[int, float] = {
    10: 1, 20: 1, 21: 0, 22: 1, 23: 0, 24: 300, 25: 1500, 26: 5, 27: 1,
    100: 250, 101: 250, 102: 250, 110: 3000, 111: 3000, 112: 3000,
    120: 500, 121: 500, 122: 500, 130: 20, 131: 20, 132: 10,
}


def build_firmware(dest: Path) -> Path:
    """Build GRBL 1.1h with grbl-sim into ``dest``; returns the executable."""
    script = GRBL_SIM / "build.sh"
    if not script.is_file():
        raise FileNotFoundError(f"{script} not found: the GRBL simulator must sit in ../shared beside the checkout")
    done = subprocess.run(["bash", str(script), str(dest)], capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"building {script} failed:\n{done.stderr[-3000:]}")
    exe = Path(done.stdout.strip().splitlines()[-1])
    if not exe.is_file():
        raise RuntimeError(f"{script} printed {exe}, which does not exist")
    return exe


def fast_eeprom(exe: Path, folder: Path) -> Path:
    """An EEPROM image holding :data:`FAST`, made once by booting the firmware in ``folder``: a
    :class:`Firmware` started from it (``eeprom=``) writes only the settings that differ and boots
    once instead of twice (the simulator waits 1 s of its own time before it reads input)."""
    Firmware(exe, folder).close()
    image = folder / EEPROM
    if not image.is_file():
        raise RuntimeError(f"grbl_sim.exe wrote no {EEPROM} in {folder}")
    return image


#: The simulator's EEPROM file, in the folder it runs in.
EEPROM = "EEPROM.DAT"


class _PtyDevice:
    """The part both controllers share: the pty pair, raw I/O on the slave side, settings."""

    kind = ""

    def __init__(self, settings: dict[int, float]) -> None:
        self.settings = dict(settings)
        self.garble_reports = 0
        self.garbled: list[bytes] = []
        self.take_oks = 0
        self.take_lines: list[bytes] = []
        self.taken: list[bytes] = []
        self._out_line = b""
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo: the controller must not read back its own output
        self.path = os.ttyname(self.slave)

    @property
    def url(self) -> str:
        return f"grbl://{self.path}"

    def raw(self, data: bytes, *, until: bytes | str = b"ok\r\n", timeout_s: float = 5.0) -> str:
        """Write ``data`` on the port and read until ``until`` (bytes, or a regex) or the timeout."""
        self.drain()
        os.write(self.slave, data)
        out = b""
        deadline = time.monotonic() + timeout_s
        pattern = re.compile(until.encode()) if isinstance(until, str) else None
        while time.monotonic() < deadline:
            if (pattern.search(out) if pattern else until in out):
                return out.decode("ascii", "replace")
            ready, _, _ = select.select([self.slave], [], [], 0.02)
            if ready:
                out += os.read(self.slave, 4096)
        raise TimeoutError(f"{self.kind}: no {until!r} after {data!r} within {timeout_s} s; got {out!r}")

    def _garble(self, data: bytes) -> bytes:
        """What reaches lfrig of ``data`` from the controller: whole lines, the next
        ``garble_reports`` status reports with a digit of their position replaced by ``#``, and
        without the next ``take_oks`` ``ok`` lines and the next line that starts with each of
        ``take_lines`` (read by another program, kept in ``taken``)."""
        self._out_line += data
        *lines, self._out_line = self._out_line.split(b"\n")
        out = b""
        for line in lines:
            if self.take_oks and line.strip() == b"ok":
                self.take_oks -= 1
                self.taken.append(line)
                continue
            taken = next((prefix for prefix in self.take_lines if line.startswith(prefix)), None)
            if taken is not None:
                self.take_lines.remove(taken)
                self.taken.append(line)
                continue
            if self.garble_reports and line.startswith(b"<") and b"Pos:" in line:
                self.garble_reports -= 1
                at = line.index(b"Pos:") + 5
                line = line[:at] + b"#" + line[at + 1:]
                self.garbled.append(line)
            out += line + b"\n"
        return out

    def drain(self) -> bytes:
        out = b""
        while select.select([self.slave], [], [], 0)[0]:
            out += os.read(self.slave, 4096)
        return out

    def configure(self, settings: dict[int, float], *, start_mm: Sequence[float] | None | str = "keep") -> None:
        """Write ``$N=value`` settings (kept across restarts), then power-cycle so they all apply
        (the carriage at ``start_mm``: ``"keep"`` where it is, ``None`` mid-travel)."""
        self.settings.update(settings)
        for key, value in sorted(settings.items(), key=lambda kv: (kv[0] != 22, kv[0])):  # $20 needs $22
            reply = self.raw(f"${key}={value:g}\n".encode(), until="ok\r\n|error:")
            assert "ok" in reply, (key, value, reply)
        self.restart(start_mm=start_mm)

    def status(self) -> str:
        return self.raw(b"?", until=r"<[^>]*>")

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class Firmware(_PtyDevice):
    """The real GRBL 1.1h firmware in grbl-sim, on a pty."""

    kind = "firmware"

    def __init__(self, exe: Path, workdir: Path, settings: dict[int, float] = FAST,
                 start_mm: Sequence[float] | None = None, relay: bool = False, eeprom: Path | None = None) -> None:
        """``eeprom``: an image of :data:`FAST` (:func:`fast_eeprom`) to start from; only the settings
        that differ from it are written (one boot when none do)."""
        super().__init__({})
        self.exe = exe
        self.workdir = workdir
        self.relay = relay
        self._relay_thread: threading.Thread | None = None
        workdir.mkdir(parents=True, exist_ok=True)
        self.process: subprocess.Popen | None = None
        changes = dict(settings)
        if eeprom is not None:
            shutil.copyfile(eeprom, workdir / EEPROM)
            self.settings = dict(FAST)
            changes = {k: v for k, v in settings.items() if FAST.get(k) != v}
            if not changes:
                self._start(start_mm)
                return
        self._start(None)
        self.configure(changes, start_mm=start_mm)

    def _start(self, start_mm: Sequence[float] | None, *, wait: bool = True) -> None:
        command = [str(self.exe), "-n", "-s", "/dev/null", "-b", "/dev/null"]
        if start_mm is not None:
            command += ["-p", ",".join(f"{c:.4f}" for c in start_mm)]
        stdout = subprocess.PIPE if self.relay else self.master
        self.process = subprocess.Popen(command, cwd=self.workdir, stdin=self.master, stdout=stdout,
                                        stderr=subprocess.DEVNULL, start_new_session=True)
        if self.relay:
            self._relay_thread = threading.Thread(target=self._relay, args=(self.process,), daemon=True)
            self._relay_thread.start()
        if not wait:
            return
        out = b""
        deadline = time.monotonic() + 10
        while b"['$' for help]" not in out:
            assert self.process.poll() is None, f"grbl_sim.exe exited with {self.process.returncode}"
            assert time.monotonic() < deadline, f"no welcome line from grbl_sim.exe: {out!r}"
            if select.select([self.slave], [], [], 0.05)[0]:
                out += os.read(self.slave, 4096)
        self.drain()

    def _relay(self, process: subprocess.Popen) -> None:
        """The firmware's output to the port, through :meth:`_garble`."""
        pipe = process.stdout
        assert pipe is not None
        while True:
            data = os.read(pipe.fileno(), 4096)
            if not data:
                return
            out = self._garble(data)
            if out:
                os.write(self.master, out)

    def power_cycle(self, *, boot_s: float) -> None:
        """Power off now and on again ``boot_s`` later with the carriage where it is, like a board that
        resets when its port opens and runs its bootloader first: what the port sends meanwhile is
        lost. Returns at once (lfrig may open the port meanwhile)."""
        start_mm = self.carriage_mm()
        self._stop()

        def boot() -> None:
            time.sleep(boot_s)
            while select.select([self.master], [], [], 0)[0]:
                os.read(self.master, 4096)  # the bootloader swallows it
            self._start(start_mm, wait=False)

        self._boot_thread = threading.Thread(target=boot, daemon=True)
        self._boot_thread.start()

    def power_off(self) -> None:
        """Switch the controller off (the port stays, silent), until :meth:`restart`."""
        self._stop()

    def _stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            os.kill(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout=10)
        if self._relay_thread is not None:
            self._relay_thread.join(timeout=5)
            self._relay_thread = None
        self.process = None
        time.sleep(0.05)
        self.drain()

    def restart(self, *, start_mm: Sequence[float] | None | str = "keep") -> None:
        """Power-cycle: the carriage stays where it is (``"keep"``), goes mid-travel (``None``) or to
        ``start_mm`` (machine coordinates as homing defines them)."""
        if start_mm == "keep":
            start_mm = self.carriage_mm()
        self._stop()
        self._start(start_mm)

    def steps(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """(carriage steps, GRBL's step counts) from the simulator's ``%`` report."""
        text = self.raw(b"%\n", until=r"\[SIM:[^\]]*\]")
        match = re.search(r"carriage steps (-?\d+),(-?\d+),(-?\d+)\|grbl steps (-?\d+),(-?\d+),(-?\d+)", text)
        assert match, text
        values = tuple(int(g) for g in match.groups())
        time.sleep(0.05)
        self.drain()  # GRBL's reply to the '%' line
        return values[:3], values[3:]

    def carriage_mm(self) -> tuple[float, float, float]:
        carriage, _ = self.steps()
        return tuple(s / self.settings.get(100 + i, 250.0) for i, s in enumerate(carriage))  # type: ignore[return-value]

    def close(self) -> None:
        thread = getattr(self, "_boot_thread", None)
        if thread is not None:
            thread.join(timeout=30)
        self._stop()
        super().close()


class FakeOnPty(_PtyDevice):
    """``FakeGrbl`` on the wall clock, served on a pty by a thread."""

    kind = "fake"

    def __init__(self, settings: dict[int, float] = FAST, start_mm: Sequence[float] | None = None) -> None:
        from rig.fakegrbl import FakeGrbl
        from rig.clock import SystemClock

        super().__init__(dict(settings))
        travel = [float(self.settings.get(130 + i, 100.0)) for i in range(3)]
        start = tuple(start_mm) if start_mm is not None else tuple(-t / 2 for t in travel)
        self.controller = FakeGrbl(clock=SystemClock(), settings=dict(settings), start_mm=start)
        self.start_mm = start
        self.lock = threading.Lock()
        self._boot_at: float | None = None
        self._stopped = threading.Event()
        self.controller.power_on()
        self.controller.take_output()
        self._thread = threading.Thread(target=self._serve, name="fakegrbl-pty", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stopped.is_set():
            try:
                ready, _, _ = select.select([self.master], [], [], 0.002)
                data = os.read(self.master, 4096) if ready else b""
            except OSError:
                if self._stopped.is_set():
                    return
                time.sleep(0.01)
                continue
            with self.lock:
                if self._boot_at is not None:
                    if time.monotonic() < self._boot_at:
                        continue  # powered off, then the bootloader: what arrives is lost
                    self._boot_at = None
                    self.controller.power_on()
                if data:
                    self.controller.receive(data)
                out = self._garble(self.controller.take_output())
            if out:
                os.write(self.master, out)

    def restart(self, *, start_mm: Sequence[float] | None | str = "keep") -> None:
        if start_mm is None:
            start_mm = tuple(-float(self.settings.get(130 + i, 100.0)) / 2 for i in range(3))
        with self.lock:
            self._boot_at = None  # on again (after power_off or during a power_cycle's boot)
            self.controller.power_on(start_mm=None if start_mm == "keep" else start_mm)
            out = self.controller.take_output()
        os.write(self.master, out)
        time.sleep(0.05)
        self.drain()

    def power_off(self) -> None:
        """Switch the controller off: it hears and says nothing until :meth:`restart`."""
        with self.lock:
            self._boot_at = float("inf")

    def power_cycle(self, *, boot_s: float) -> None:
        """As :meth:`Firmware.power_cycle`: off now, on with the welcome line ``boot_s`` later."""
        with self.lock:
            self.controller.advance()
            self._boot_at = time.monotonic() + boot_s

    def carriage_mm(self) -> tuple[float, float, float]:
        with self.lock:
            return self.controller.physical_position()

    def close(self) -> None:
        self._stopped.set()
        self._thread.join(timeout=5)
        super().close()
