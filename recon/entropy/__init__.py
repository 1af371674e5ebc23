"""The matching-entropy disparity estimator (Shi et al.), see ``docs/entropy-method.md``.

``estimate_disparity(lf, **options) -> EntropyResult``; ``write_outputs(result, out_dir)``;
``DEFAULTS`` / ``EntropyOptions`` list every option with its default and help text
(:mod:`recon.entropy.options`, grouped by step); :mod:`recon.entropy.plan` is the estimator's phase
plan, :mod:`recon.entropy.steps` its steps.

**Twins.** Every compiled (numba) computation has a readable numpy twin that a test holds it to
(``tests/test_twins_<module>.py``, one per module). The naming rule: ``name`` is the compiled
function the estimator calls, ``name_reference`` its readable twin with the same arguments and
result, and ``_name_kernel`` (or another private ``_..._kernel``) the numba loop ``name`` runs.
:class:`recon.entropy.cost.WindowCost` is the compiled twin of
:func:`~recon.entropy.cost.window_cost_reference` (prepared once, called per candidate). Kernels the
estimator no longer calls live in :mod:`recon.entropy.legacy_matching` only while a test pins a
current kernel to them.

**Imports.** The options (:mod:`recon.entropy.options`, plain dataclasses) load with the package;
the estimator and its writers (numba, scipy) load when one of their names is first used, so that
the command line can build its flags from the options without compiling or loading any kernel.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from recon.entropy.options import DEFAULTS, EntropyOptions, make_options
from recon.lazy import lazy_names

if TYPE_CHECKING:
    from recon.entropy.estimate import EntropyResult, estimate_disparity
    from recon.entropy.outputs import write_outputs

__all__ = ["DEFAULTS", "EntropyOptions", "EntropyResult", "estimate_disparity", "make_options",
           "write_outputs"]

__getattr__ = lazy_names(__name__, {"EntropyResult": "recon.entropy.estimate",
                                    "estimate_disparity": "recon.entropy.estimate",
                                    "write_outputs": "recon.entropy.outputs"})
