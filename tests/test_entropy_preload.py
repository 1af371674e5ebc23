"""The entropy method's warm-up loads every kernel a default estimate calls, with the argument types
it calls them with (``recon.entropy.preload``): the estimate then loads or compiles nothing itself."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from numba.core import types

from recon.entropy.preload import KERNELS, argument_types

ROOT = Path(__file__).resolve().parents[1]

# A fresh process: what the warm-up loaded, then what the estimate added (kernel -> signatures).
PROBE = """
import json, sys
from numba.core.registry import CPUDispatcher
from recon.methods import warm_in_background
from recon.synthetic import occluding_square_scene
from recon.entropy import estimate_disparity

def signatures():  # every kernel of lfrig's modules
    kernels = {f"{k.py_func.__module__}.{k.py_func.__name__}": k for module in list(sys.modules.values())
               if getattr(module, "__name__", "").startswith("recon.")
               for k in vars(module).values() if isinstance(k, CPUDispatcher)}
    return {name: sorted(str(s) for s in k.signatures) for name, k in kernels.items() if k.signatures}

warm_in_background("entropy").join()
warmed = signatures()
lf, _ = occluding_square_scene(40, seed=2, back=-0.5, front=1.0)
estimate_disparity(lf)
print(json.dumps({"warmed": warmed, "after": signatures()}))
"""


def test_the_estimate_adds_no_kernel_signature_after_the_warm_up():
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, check=True)
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    added = {name: sorted(set(sigs) - set(seen["warmed"].get(name, []))) for name, sigs in seen["after"].items()}
    assert {name: sigs for name, sigs in added.items() if sigs} == {}
    # and the warm-up loaded each listed kernel with the listed types (the first phase's only
    # where their C twins do not load: the estimate does not call them)
    from recon.entropy.preload import without_c_twins

    for module, name, tokens in without_c_twins(KERNELS):
        assert str(argument_types(tokens)) in seen["warmed"][f"{module}.{name}"]


def test_argument_types_reads_scalars_arrays_and_read_only_arrays():
    assert argument_types("int64 bool float32:3 int64:2:ro") == (
        types.int64, types.boolean, types.Array(types.float32, 3, "C"),
        types.Array(types.int64, 2, "C", readonly=True))
    assert not argument_types("uint8:1:ro")[0].mutable


def test_the_first_warm_up_freezes_what_its_imports_made_without_collecting_meanwhile():
    # recon.methods.warm_in_background: the collector is off during the first warm() of a process
    # (no full collection walks the new modules' objects) and they are frozen when it ends, before
    # the estimate may start.
    probe = ("import gc, json\n"
             "from recon.methods import warm_in_background\n"
             "full = gc.get_stats()[2]['collections']\n"
             "warming = warm_in_background('entropy')\n"
             "warming.wait()\n"
             "print(json.dumps([gc.get_stats()[2]['collections'] - full, gc.get_freeze_count() > 10000,"
             " gc.isenabled()]))\n"
             "warming.join()")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [0, True, True]


PHASES_PROBE = ("import json, sys\n"
                "from recon.methods import METHODS\n"
                "from recon.entropy.preload import FIRST_PHASE_KERNELS, KERNELS, load_kernels\n"
                "METHODS['entropy'].warm()\n"
                "scipy = sorted(m for m in ('scipy.ndimage', 'scipy.sparse', 'scipy.linalg') if m in sys.modules)\n"
                "first = load_kernels(KERNELS[:FIRST_PHASE_KERNELS])\n"
                "METHODS['entropy'].warm_later()\n"
                "print(json.dumps([scipy, first, load_kernels(), 'scipy.ndimage' in sys.modules,"
                " 'scipy.sparse' in sys.modules]))")


def test_the_warm_up_before_the_estimate_loads_the_first_phase_without_scipy():
    # What the estimate waits for (Method.warm) loads numba, the estimator's modules and the first
    # phase's kernels, not scipy; the later kernels load beside the estimate (warm_later), and
    # scipy.ndimage with them, which the estimate calls where the C filters do not load. Here
    # without the C kernels (LFRIG_NATIVE=0), whose first phase is numba's. SuperLU loads alone.
    import os

    out = subprocess.run([sys.executable, "-c", PHASES_PROBE], cwd=ROOT, capture_output=True, text=True, check=True,
                         env={**os.environ, "LFRIG_NATIVE": "0"})
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [[], 0, 0, True, False]


def test_with_the_first_phases_c_kernels_the_warm_up_before_the_estimate_loads_no_numba_kernel():
    # With them (recon/native/initial.c), what the estimate waits for is the estimator's modules:
    # none of the first phase's four numba kernels is loaded (the estimate calls their C twins), so
    # numba's start-up comes with the later kernels, beside the first phase.
    from tests.conftest import require_native

    from recon.entropy.preload import FIRST_PHASE_KERNELS, without_c_twins

    require_native("initial")
    out = subprocess.run([sys.executable, "-c", PHASES_PROBE], cwd=ROOT, capture_output=True, text=True, check=True)
    # the later kernels with a C twin are not loaded either (the estimate calls the C ones), nor scipy
    later_twins = len(KERNELS) - FIRST_PHASE_KERNELS - len(without_c_twins(KERNELS[FIRST_PHASE_KERNELS:]))
    assert later_twins >= 2
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [[], 4, later_twins, False, False]


# Kernels that take a while to "compile" and log when they start and end (the probe's LOG).
SLOW_KERNELS = """
import time
LOG = None

class Slow:
    def __init__(self, name, seconds):
        self.name, self.seconds, self.overloads = name, seconds, {}

    def compile(self, signature):
        with open(LOG, "a") as log:
            log.write(f"start {self.name}\\n")
        time.sleep(self.seconds)
        with open(LOG, "a") as log:
            log.write(f"end {self.name}\\n")
        self.overloads[signature] = None

first, second, third = Slow("first", 0.0), Slow("second", 0.0), Slow("third", 0.0)
later, last = Slow("later", 2.0), Slow("last", 2.0)
"""


def test_the_exit_waits_for_the_kernel_the_warm_up_is_loading_and_loads_no_other(tmp_path):
    # recon.methods._finish_warm_ups. A kernel that numba compiles (none in its cache: a new machine)
    # spends seconds in LLVM without the interpreter lock; a process that exited meanwhile would tear
    # LLVM down under it: `lfrig reconstruct` would write its result, then die of a segmentation
    # fault or an LLVM assertion. Here the command's work ends while the warm-up loads `later`.
    (tmp_path / "slow_kernels.py").write_text(SLOW_KERNELS)
    log = tmp_path / "log.txt"
    probe = ("import sys, time\n"
             f"sys.path.insert(0, {str(tmp_path)!r})\n"
             "import slow_kernels\n"
             f"slow_kernels.LOG = {str(log)!r}\n"
             "import recon.entropy.preload as preload\n"
             "preload.KERNELS = tuple(('slow_kernels', name, 'int64') for name in "
             "('first', 'second', 'third', 'later', 'last'))\n"
             "preload.FIRST_PHASE_KERNELS = 3\n"
             "from recon.methods import warm_in_background\n"
             "warming = warm_in_background('entropy')\n"
             "warming.wait()\n"
             "import os\n"
             "while not os.path.exists(slow_kernels.LOG) or 'start later' not in open(slow_kernels.LOG).read():\n"
             "    time.sleep(0.01)\n"
             "print('done')\n")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert (out.returncode, out.stdout.strip()) == (0, "done"), out.stderr
    assert log.read_text().split("\n")[-3:] == ["start later", "end later", ""]
    assert "waiting for numba to finish compiling" in out.stderr  # a wait of over a second says why


def test_a_long_wait_for_the_warm_up_says_what_it_waits_for_and_a_short_one_says_nothing():
    import threading

    from recon.methods import SLOW_WARM_UP, Warming

    for ready_after, expected in ((0.0, []), (0.5, [(0.0, SLOW_WARM_UP)])):
        ready = threading.Event()
        thread = threading.Timer(ready_after, ready.set)
        thread.start()
        said = []
        Warming(thread, ready).wait(lambda fraction, message="": said.append((fraction, message)), note_after_s=0.2)
        assert ready.is_set() and said == expected
    Warming(thread, ready).wait()  # no callback: nothing to say


def test_the_later_warm_up_begins_only_when_the_caller_lets_it(monkeypatch):
    # recon.methods.Warming.begin_later: scipy's import waits until the views are read (it would take
    # the interpreter's lock from the decoding threads); wait() and join() let it begin too.
    import threading

    import recon.methods as methods

    for opener in ("begin_later", "wait", "join"):
        began = threading.Event()
        monkeypatch.setitem(methods.METHODS, "probe", methods.Method(
            run=None, check=lambda options: None, description="probe", warm=lambda: None, warm_later=began.set))
        warming = methods.warm_in_background("probe")
        warming.ready.wait(10)
        assert not began.wait(0.2), "warm_later began before the caller let it"
        getattr(warming, opener)()
        assert began.wait(10), opener
        warming.join()
