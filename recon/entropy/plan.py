"""The estimator as a plan of steps: what each reads and writes, how far it reaches, where it runs.

A **step** is a function ``run(state)`` that reads and writes fields of one :class:`State` (the
centre view's maps and the few numbers they share), with its **reach**: how many pixels around a
pixel of its output it reads (``reach_px(options, reach) -> int``, :class:`Reach`). A **phase** is a
run of steps that is either *tile-local* (a pixel's result depends only on pixels within the steps'
reach, so a tile of the image with a halo of that many pixels gives the whole image's values in its
core) or *whole-image* (cheap steps that need the whole image: hole filling, the search range, the
TV refinement). :data:`PLAN` lists the phases in order; :func:`run_plan` runs them on one image and
:func:`recon.scale.tiles` runs the tile-local ones tile by tile (:func:`run_phase_on_tile`), with a
halo of :func:`halo_px`.

To add a step: write ``run`` and ``reach_px`` in a module of :mod:`recon.entropy`, wrap them in a
:class:`Step` there and put it at its place in :data:`PLAN`.
"""

from __future__ import annotations

import ctypes
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recon.entropy import steps
from recon.entropy.matching import disparity_candidates
from recon.entropy.options import EntropyOptions
from recon.entropy.regions import noise_sigma as centre_noise_sigma
from recon.entropy.state import Reach, State, Step
from recon.lf.lightfield import LightField
from recon.progress import ProgressCallback


@dataclass(frozen=True)
class Phase:
    """Steps run together: tile-local ones (``reads``: the whole-image maps they take from earlier
    phases, cut to the tile; ``writes``: the maps they give back, with their dtypes) or
    whole-image ones (``tile_local=False``). A name ``windows.KEY`` is the entry ``KEY`` of
    :attr:`State.windows`."""

    name: str
    steps: tuple[Step, ...]
    tile_local: bool
    reads: tuple[str, ...] = ()
    writes: dict[str, type] = field(default_factory=dict)


#: The estimator, phase by phase (``docs/entropy-method.md`` describes each step).
PLAN: tuple[Phase, ...] = (
    Phase("initial", (steps.FLAT, steps.INITIAL), tile_local=True,
          writes={"d0": np.float32, "ambiguity0": np.int32, "flat": bool}),
    Phase("layers", (steps.FILL_INITIAL, steps.SNAP_INITIAL, steps.NOISE_LIMITED, steps.SEARCH_RANGE,
                     steps.LAYER_ORIGIN), tile_local=False),
    Phase("matching", (steps.REGIONS, steps.WINDOWS, steps.VIEW_FILTERS, steps.LINE_SEARCH,
                       steps.CENTROID, steps.BOUNDARY), tile_local=True,
          reads=("d0", "ambiguity0", "flat", "noise_limited"),
          writes={"matched": np.float32, "labels": np.uint8, "ambiguity": np.int32, "cost": np.float32,
                  "windows.size": np.int64, "windows.shape": np.int64, "windows.set": np.int64,
                  "windows.entropy": np.float32}),
    Phase("refine", (steps.REFINE, steps.CONFIDENCE), tile_local=False),
)

#: The numbers a tile-local phase takes from the whole image besides its maps.
SHARED = ("noise_sigma", "initial_range", "disparity_range", "origin")


def start(lf: LightField, options: EntropyOptions, *, progress: ProgressCallback | None = None,
          shared: dict[str, Any] | None = None) -> State:
    """The state before the first step: the grey views (the light field's own array when it holds
    them, ``read_lightfield(grey=True)``), the noise sigma and the initial search's range
    (discovered by a coarse search when none is known), or the numbers of ``shared`` (a tile's,
    from :func:`shared_numbers` of the whole image)."""
    t = time.perf_counter()
    gray = np.ascontiguousarray(lf.gray(), dtype=np.float32)
    U, V = gray.shape[:2]
    shared = dict(shared or {})
    noise = shared.pop("noise_sigma", None)
    noise = float(centre_noise_sigma(gray[U // 2, V // 2])) if noise is None else float(noise)
    known = options.disparity_range or lf.disparity_range
    if "initial_range" in shared:
        initial_rng = tuple(shared.pop("initial_range"))
    elif known is not None:  # search a little beyond a known range: edges of the range are refined
        initial_rng = (known[0] - options.initial_step, known[1] + options.initial_step)
    elif options.discover_range:
        initial_rng = steps.unknown_range(gray, options=options, noise_sigma=noise)
    else:
        initial_rng = options.initial_range
    n_initial = len(disparity_candidates(initial_rng[0], initial_rng[1], options.initial_step))
    guess = known if known is not None else initial_rng
    reporter = Reporter(progress, n_initial, len(disparity_candidates(guess[0], guess[1], options.step)))
    state = State(options=options, source=lf, raw=gray, raw_centre=gray[U // 2, V // 2].copy(),
                  known=known, noise_sigma=noise,
                  hole_delta=steps.hole_tolerance(options, noise), initial_range=initial_rng,
                  reporter=reporter, _clock=t)
    for name, value in shared.items():
        setattr(state, name, value)
    state.lap("load")
    return state


def run_step(state: State, step: Step) -> None:
    """Run ``step`` on ``state``, then hand the memory its temporaries left free back to the
    system (:func:`release_free_memory`)."""
    step.run(state)
    release_free_memory()


def run_phase(state: State, phase: Phase) -> None:
    """Run the steps of ``phase`` on ``state``."""
    for step in phase.steps:
        run_step(state, step)


def _malloc_trim():
    try:
        return ctypes.CDLL(None).malloc_trim  # the C library the interpreter runs on
    except (OSError, AttributeError):  # not glibc: nothing to do
        return None


_TRIM = _malloc_trim()


def release_free_memory() -> None:
    """Return the free pages of the C heap to the system (glibc's ``malloc_trim``; nothing
    elsewhere). The maps a step keeps (a few MB each) and the temporaries it frees come from the
    same heap, so the freed ones stay resident between the kept ones; on the 1198x906 demo capture
    that was 100-190 MiB after the window selection, under the line search's peak."""
    if _TRIM is not None:
        _TRIM(0)


def run_plan(state: State, plan: tuple[Phase, ...] = PLAN) -> State:
    """Run every phase of ``plan`` on ``state`` (the whole image); returns it."""
    for phase in plan:
        run_phase(state, phase)
    return state


def halo_px(options: EntropyOptions, reach: Reach, plan: tuple[Phase, ...] = PLAN) -> int:
    """Pixels around a tile that its tile-local phases read: the sum of their steps' reaches (each
    step reads the previous one's output that far around)."""
    return sum(step.reach_px(options, reach) for phase in plan if phase.tile_local for step in phase.steps)


def shared_numbers(state: State) -> dict[str, Any]:
    """The numbers of :data:`SHARED` a tile takes from the whole image's ``state``."""
    return {name: getattr(state, name) for name in SHARED if getattr(state, name) is not None}


def run_phase_on_tile(crop: LightField, phase: Phase, maps: list[np.ndarray], *, options: EntropyOptions,
                      shared: dict[str, Any]) -> np.ndarray:
    """One tile-local ``phase`` on a tile's ``crop``: ``maps`` are the whole image's maps of
    ``phase.reads`` cut to the crop, ``shared`` the whole image's numbers (:func:`shared_numbers`).
    Returns ``phase.writes`` stacked, ``(len(writes), crop H, crop W)`` float32."""
    state = start(crop, options, shared=shared)
    for name, value in zip(phase.reads, maps):
        setattr(state, name, value)
    run_phase(state, phase)
    return np.stack([_get(state, name) for name in phase.writes]).astype(np.float32)


def take_tiles(state: State, phase: Phase, stitched: np.ndarray) -> None:
    """Set ``phase.writes`` on the whole image's ``state`` from the stitched
    ``(len(writes), H, W)`` float32 output of :func:`run_phase_on_tile` (exact: every map written
    is float32 or holds integers far below 2**24)."""
    for name, dtype, values in zip(phase.writes, phase.writes.values(), stitched):
        _set(state, name, values > 0.5 if dtype is bool else values.astype(dtype))


def _get(state: State, name: str) -> np.ndarray:
    """The map ``name`` of :attr:`Phase.writes` on ``state``."""
    if name.startswith("windows."):
        return state.windows[name.removeprefix("windows.")]
    return getattr(state, name)


def _set(state: State, name: str, value: np.ndarray) -> None:
    if name.startswith("windows."):
        state.windows[name.removeprefix("windows.")] = value
    else:
        setattr(state, name, value)


class Reporter:
    """Turns the estimator's steps into one overall fraction for ``progress`` (:mod:`recon.progress`).

    Each step has a weight in "initial-candidate units" (the time one candidate of the nine-view
    search takes): a candidate of the full line search costs :data:`MATCH_CANDIDATE_WEIGHT` of them
    (81 views and up to 77 windows against 9 views and 11), and the fixed steps a measured share
    (2-core machine, 512x512, backgammon: initial 2.5 s for 52 candidates, matching 10 s for 121,
    regions 0.2 s, windows 1.5 s, TV 1 s; the TV refinement compiled since: ~0.25 s with the
    confidence map). The fraction never goes back.
    """

    FIXED = {"regions": 4.0, "windows": 30.0, "refine": 5.0}

    def __init__(self, report, n_initial: int, n_matching: int) -> None:
        self.report = report
        self.weights = {"initial": float(n_initial), **self.FIXED,
                        "matching": MATCH_CANDIDATE_WEIGHT * n_matching}
        self.order = ["initial", "regions", "windows", "matching", "refine"]
        self.current = "initial"
        self.note = ""
        self.last = 0.0

    def set_matching(self, n_matching: int) -> None:
        self.weights["matching"] = MATCH_CANDIDATE_WEIGHT * n_matching

    def _emit(self, within: float) -> None:
        if self.report is None:
            return
        before = sum(self.weights[k] for k in self.order[:self.order.index(self.current)])
        total = sum(self.weights.values())
        fraction = min(max((before + within * self.weights[self.current]) / total, self.last), 1.0)
        self.last = fraction
        self.report(fraction, self.note)

    def step(self, name: str, message: str) -> None:
        self.current = name
        self.note = message
        self._emit(0.0)

    def within(self, fraction: float) -> None:
        self._emit(fraction)

    def done(self) -> None:
        self.current = self.order[-1]
        self.note = "done"
        self._emit(1.0)


#: Time of one full line-search candidate in units of one nine-view candidate (see ``Reporter``).
MATCH_CANDIDATE_WEIGHT = 1.8
