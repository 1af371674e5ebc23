"""The matching-entropy disparity estimator (Shi et al.), see ``docs/entropy-method.md``.

``estimate_disparity(lf, **options) -> EntropyResult``; ``write_outputs(result, out_dir)``;
``DEFAULTS`` / ``EntropyOptions`` list every option with its default and help text.
"""

from recon.entropy.estimate import EntropyResult, estimate_disparity
from recon.entropy.options import DEFAULTS, EntropyOptions, make_options
from recon.entropy.outputs import write_outputs

__all__ = ["DEFAULTS", "EntropyOptions", "EntropyResult", "estimate_disparity", "make_options",
           "write_outputs"]
