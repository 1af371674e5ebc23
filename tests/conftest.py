"""Shared fixtures.

``hci_scene_dir`` is the benchmark scene in ``../shared``. It is licensed data that never enters the
repository; tests that need it skip on a developer machine without it, but FAIL under CI (where the
variable ``CI`` is set), so a CI run can never pass by silently skipping them.
"""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

import pytest

# The tests of Ctrl-C and hang-up handling expect the signals as a terminal delivers them. A suite
# started in the background of a script (where SIGINT comes ignored) or under nohup (SIGHUP) would
# hand those ignored dispositions to every process it starts, and lfrig rightly leaves an ignored
# signal ignored: reset them here, for the suite and its children.
signal.signal(signal.SIGINT, signal.default_int_handler)
signal.signal(signal.SIGHUP, signal.SIG_DFL)

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
HCI_BACKGAMMON = SHARED / "data" / "hci" / "stratified" / "backgammon"


def require_hci_scene(path: Path = HCI_BACKGAMMON) -> Path:
    """Return the scene folder, or fail under CI / skip elsewhere when it is missing."""
    if (path / "input_Cam040.png").is_file() and (path / "gt_disp_lowres.pfm").is_file():
        return path
    message = f"benchmark scene not found at {path} (it must sit in ../shared beside the checkout)"
    if os.environ.get("CI"):
        pytest.fail(message)
    pytest.skip(message)


def require_native(name: str) -> None:
    """Fail under CI / skip elsewhere when the C kernels of ``recon/native/NAME.c`` cannot be built
    or loaded here (:func:`recon.native.library` says why)."""
    from recon.native import library, unavailable

    if library(name) is not None:
        return
    message = f"the compiled kernels of recon/native/{name}.c are not available: {unavailable(name)}"
    if os.environ.get("CI"):
        pytest.fail(message)
    pytest.skip(message)


def use_native_build(name: str, monkeypatch, tmp_path: Path, *, flags: tuple[str, ...] = (),
                     source: Path | None = None) -> None:
    """Build ``recon/native/NAME.c`` (or ``source``, a file that includes it) with lfrig's flags and
    ``flags`` (``-mno-avx512f``: as for a CPU without AVX-512) into ``tmp_path``, and make it the
    loaded library ``name`` for the rest of the test: the kernels' plain paths, tested on this CPU."""
    import ctypes

    import recon.native as native

    target = tmp_path / f"{name}-variant.so"
    run = subprocess.run([native.compiler(), *native.CFLAGS, *flags, "-o", str(target),
                          str(source or native.HERE / f"{name}.c")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    lib = ctypes.CDLL(str(target))
    for function, types in native.SIGNATURES[name].items():
        getattr(lib, function).argtypes = [native._CTYPES[t] for t in types.split()]
        getattr(lib, function).restype = ctypes.c_int
    monkeypatch.setitem(native._loaded, name, lib)


@pytest.fixture
def hci_scene_dir() -> Path:
    return require_hci_scene()


@pytest.fixture(autouse=True)
def _own_state_home(tmp_path_factory, monkeypatch):
    """lfrig keeps a small record per serial port under ``$XDG_STATE_HOME`` (``rig.frames``): each
    test gets its own, so no test sees another's ports (pty paths are reused) or the user's."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("state")))


@pytest.fixture(scope="session")
def firmware_exe(tmp_path_factory) -> Path:
    """GRBL 1.1h built with ``../shared/grbl-sim``, once per test session for every module that
    needs it (``tests/grbl_devices.py``); skipped without the simulator, but a failure under CI."""
    from grbl_devices import GRBL_SIM, build_firmware

    if not (GRBL_SIM / "build.sh").is_file():
        message = f"GRBL simulator not found at {GRBL_SIM} (it must sit in ../shared beside the checkout)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    try:
        return build_firmware(tmp_path_factory.mktemp("grbl-sim"))
    except (OSError, RuntimeError, subprocess.SubprocessError) as error:
        pytest.fail(f"building the GRBL simulator failed: {error}")


@pytest.fixture(scope="session")
def firmware_eeprom(firmware_exe, tmp_path_factory) -> Path:
    """An EEPROM image with ``grbl_devices.FAST`` written, for ``Firmware(eeprom=...)``."""
    from grbl_devices import fast_eeprom

    return fast_eeprom(firmware_exe, tmp_path_factory.mktemp("grbl-eeprom"))


def stop_process_group(process: subprocess.Popen) -> None:
    """End a process we started and everything it started (its own session), by its id."""
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=10)
