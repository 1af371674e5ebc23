"""The matching-entropy disparity estimator (Shi et al.), see ``docs/entropy-method.md``."""
