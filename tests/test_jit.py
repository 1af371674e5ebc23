"""recon.jit: the estimator's numba kernels are made numba dispatchers at their first use, so a
process whose kernels are all C (recon/native) never imports numba; the kernels are numba's."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from recon.jit import Kernel, numba

ROOT = Path(__file__).resolve().parents[1]


def _fresh(code: str) -> object:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_the_estimator_and_the_baselines_kernels_imports_no_numba():
    assert _fresh("""
        import json, sys
        import numpy as np
        import recon.entropy.estimate, recon.entropy.outputs, recon.entropy.legacy_matching, recon.costvolume
        from recon.entropy.cost import window_reach
        assert window_reach(np.array([[-2, 3, -1, 1]])) == (2, 3)  # a kernel's py_func, run as Python
        print(json.dumps(sorted(m for m in ("numba", "llvmlite") if m in sys.modules)))
        """) == []


def test_a_kernel_becomes_numbas_dispatcher_at_its_first_use_with_its_callees():
    # recon.entropy.cost's _view_row calls recon.costvolume's helpers, imported into cost's names:
    # both modules' names are bound to the dispatchers when the first of their kernels is made.
    seen = _fresh("""
        import json, sys
        import numpy as np
        import recon.entropy.cost as cost
        import recon.costvolume as cv
        from recon.jit import Kernel
        before = [isinstance(cost._min_window_costs_kernel, Kernel), "numba" in sys.modules]
        dispatcher = cost._min_window_costs_kernel.dispatcher()
        from numba.core.registry import CPUDispatcher
        after = [isinstance(cost._min_window_costs_kernel, CPUDispatcher), cost._min_window_costs_kernel is dispatcher,
                 isinstance(cost.add_shifted_row_diff, CPUDispatcher), cost.add_shifted_row_diff is cv.add_shifted_row_diff,
                 cost.numba is sys.modules["numba"]]
        print(json.dumps([before, after]))
        """)
    assert seen == [[True, False], [True, True, True, True, True]]


@numba.njit(inline="always")
def _helper(x):
    return 2 * x


@numba.njit(parallel=True)
def _twice(a, out):
    for i in numba.prange(a.shape[0]):
        out[i] = _helper(a[i])


def test_a_deferred_kernel_computes_what_numba_computes_and_forwards_its_attributes():
    assert isinstance(_twice, Kernel) and isinstance(_helper, Kernel) and _twice.__name__ == "_twice"
    kernel = _twice
    a = np.arange(7.0)
    out = np.empty_like(a)
    kernel(a, out)
    assert np.array_equal(out, 2 * a)
    assert kernel.py_func.__name__ == "_twice" and len(kernel.overloads) == 1  # the dispatcher's attributes
    assert not isinstance(globals()["_helper"], Kernel)  # this module's names bound to the dispatchers
    assert numba.get_num_threads() >= 1  # other attributes are numba's


def test_njit_takes_keyword_options_or_a_bare_function():
    import recon.jit

    numba = recon.jit.numba  # (this module's own name is numba's by now: the kernel above was used)
    assert isinstance(numba.njit(lambda x: x), Kernel)
    with pytest.raises(TypeError, match="keyword options"):
        numba.njit("float64(float64)")


def test_the_baselines_command_imports_no_numba(tmp_path):
    # lfrig reconstruct as a user runs it, with the warm-up: the C sweep (recon/native/sweep.c)
    # and the deferred kernels of the modules it imports leave numba out of the process.
    from tests.conftest import require_native

    require_native("sweep")
    assert _fresh(f"""
        import json, sys
        from rig.main import main
        code = main(["reconstruct", {str(ROOT / "fixtures" / "tiny_capture")!r}, "-o", {str(tmp_path / "out")!r},
                     "--method", "baseline", "--quiet"])
        print(json.dumps([code, sorted(m for m in ("numba", "llvmlite") if m in sys.modules)]))
        """) == [0, []]


def test_every_kernel_of_a_default_estimate_has_a_c_twin():
    from recon.entropy.preload import C_TWINS, KERNELS

    assert {f"{module}.{name}" for module, name, _ in KERNELS} <= set(C_TWINS)


@pytest.mark.parametrize("scene", ["tiny_capture", "backgammon"])
def test_the_entropy_command_imports_no_numba(tmp_path, scene):
    # lfrig reconstruct (the entropy method) as a user runs it, with its warm-up: on a lab capture
    # (the range found by the coarse search) and on the benchmark scene (its range given), every
    # kernel runs its C twin (recon.entropy.preload.C_TWINS), and neither numba nor scipy (whose
    # filters and sparse solve recon.entropy.filters, regions.box_extreme and laplace stand in
    # for) ever enters the process.
    from recon.entropy.preload import C_TWINS
    from tests.conftest import require_hci_scene, require_native

    for name in sorted(set(C_TWINS.values())):
        require_native(name)
    source = ROOT / "fixtures" / "tiny_capture" if scene == "tiny_capture" else require_hci_scene()
    loaded = _fresh(f"""
        import json, sys
        from rig.main import main
        code = main(["reconstruct", {str(source)!r}, "-o", {str(tmp_path / "out")!r}, "--quiet"])
        from recon.methods import _WARM_UPS
        for thread in _WARM_UPS:
            thread.join()
        print(json.dumps([code, sorted(m for m in ("numba", "llvmlite", "scipy") if m in sys.modules)]))
        """)
    assert loaded == [0, []]
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["provenance"]["machine"]["kernels"] == dict.fromkeys(sorted(set(C_TWINS.values())), "C")
