"""The vocabulary of the estimator's steps: :class:`State` (what they read and write),
:class:`Step` (one step and its reach) and :class:`Reach` (what a reach depends on)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon.entropy.options import EntropyOptions
from recon.lf.lightfield import view_shift_px


@dataclass(frozen=True)
class Reach:
    """What a step's reach depends on besides its options: the grid of views and the disparity
    range searched (``(min, max)`` px/view)."""

    grid_shape: tuple[int, int]
    disparity_range: tuple[float, float]

    def view_px(self, options: EntropyOptions) -> int:
        """How far (pixels) a view is sampled from a pixel over the initial search's range (one
        ``initial_step`` beyond the range), plus one for the bilinear neighbour."""
        lo, hi = self.disparity_range
        return view_shift_px((lo - options.initial_step, hi + options.initial_step), self.grid_shape) + 1


@dataclass(frozen=True)
class Step:
    """A step of the estimator: ``run(state)`` and its ``reach_px(options, reach)`` in pixels."""

    name: str
    run: Callable[[State], None]
    reach_px: Callable[[EntropyOptions, Reach], int]


@dataclass
class State:
    """What the steps read and write. Maps are ``(H, W)`` over the centre view unless said;
    disparities in px/view."""

    options: EntropyOptions
    #: The light field the grey views were read from.
    source: Any
    #: ``(U, V, H, W)`` float32 grey views in ``[0, 1]`` as read (never written: the line search
    #: filters copies of their rows, :func:`recon.entropy.steps.filtered_views`); ``None`` after
    #: the boundary step, the last that reads them.
    raw: np.ndarray | None
    #: ``(H, W)`` float32 centre view of :attr:`raw` as read (:attr:`centre`).
    raw_centre: np.ndarray
    #: The range given by the options or the light field, or ``None``.
    known: tuple[float, float] | None
    #: The centre view's noise sigma in ``[0, 1]`` grey units.
    noise_sigma: float
    #: How far above a cost curve's least value a candidate is still in its valley (cost units).
    hole_delta: float
    #: The initial search's range.
    initial_range: tuple[float, float]
    reporter: Any
    timings: dict[str, float] = field(default_factory=dict)
    #: ``(noise, weak)``: the ``(H, W)`` bool centre-view pixels where the line search's views are
    #: filtered with ``noise_filter`` and with ``weak_texture_filter`` (``None``: not filtered;
    #: :func:`recon.entropy.steps.view_filters_step`).
    view_filters: tuple = (None, None)
    disparity_range: tuple[float, float] | None = None
    origin: float | None = None
    flat: np.ndarray | None = None
    d0: np.ndarray | None = None
    ambiguity0: np.ndarray | None = None
    holes0: np.ndarray | None = None
    noise_limited: np.ndarray | None = None
    labels: np.ndarray | None = None
    region_info: dict = field(default_factory=dict)
    windows: dict = field(default_factory=dict)
    matched: np.ndarray | None = None
    cost: np.ndarray | None = None
    ambiguity: np.ndarray | None = None
    refined: np.ndarray | None = None
    holes: np.ndarray | None = None
    confidence: np.ndarray | None = None
    _clock: float = field(default_factory=time.perf_counter)

    @property
    def centre(self) -> np.ndarray:
        """The centre view as read, ``(H, W)`` (:attr:`raw_centre`; unchanged by the view filters)."""
        return self.raw_centre

    def lap(self, name: str) -> None:
        """Record the seconds since the last lap as ``timings[name]``."""
        now = time.perf_counter()
        self.timings[name] = now - self._clock
        self._clock = now
