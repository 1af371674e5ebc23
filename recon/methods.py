"""The reconstruction methods by name, with one calling convention for the CLI, benchmark and batch."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon.lightfield import LightField


@dataclass
class MethodResult:
    """``disparity`` ``(H, W)`` float32 of the centre view, plus whatever maps the method explains itself with."""

    disparity: np.ndarray
    extras: Any = None
    options: dict[str, Any] = field(default_factory=dict)


def _baseline(lf: LightField, progress: Callable[[int, int], None] | None, **options: Any) -> MethodResult:
    from recon.baseline import estimate_baseline

    result = estimate_baseline(lf, progress=progress, **options)
    return MethodResult(disparity=result.disparity, extras=result, options=options)


#: name -> (runner, one-line description)
METHODS: dict[str, tuple[Callable[..., MethodResult], str]] = {
    "baseline": (_baseline, "fixed square window, SAD over all views, parabolic sub-pixel refinement"),
}


def run_method(name: str, lf: LightField, *, progress: Callable[[int, int], None] | None = None,
               **options: Any) -> MethodResult:
    """Run the method ``name`` on ``lf`` with keyword ``options`` (the method's own defaults otherwise)."""
    try:
        runner = METHODS[name][0]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(sorted(METHODS))}") from None
    return runner(lf, progress, **options)
