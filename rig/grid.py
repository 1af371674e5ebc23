"""The scan grid as pure functions: positions, visiting order, backlash-free approach, limit checks.

A grid has ``rows x cols`` views at ``pitch_mm`` spacing around a centre machine position. View
``(u, v)`` (``u`` the row, ``v`` the column, ``docs/conventions.md``) sits at::

    centre_mm + (u - u0) * pitch_mm * row_axis + (v - v0) * pitch_mm * col_axis,   (u0, v0) = (rows // 2, cols // 2)

``row_axis`` and ``col_axis`` are unit stage directions: by default ``+y`` and ``+x``, so that the
camera moves down the image as ``u`` grows and right as ``v`` grows when the stage's x and y axes
are mounted along the camera's x and y (flip them with ``-x``/``-y`` when they are not).

Backlash: the lead screws' play makes the position depend on the direction of the last motion. Every
view is therefore reached by a final motion in the same direction on every axis (``approach``, +1 or
-1 per axis): when the straight move to a view would end going the other way on some axis, the plan
first goes ``backlash_mm`` past the view on that axis and then comes back. The first view is always
approached that way on all axes.

Nothing here touches hardware: :func:`plan_moves` gives the whole list of moves, which a dry run
prints and :func:`check_limits` checks against the travel before anything moves.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

from rig.errors import RigError

AXES = "xyz"


class GridError(RigError):
    """A grid that cannot be scanned: bad size or pitch, or positions outside the stage's travel."""


def parse_axis(text: str) -> tuple[float, float, float]:
    """``"+x"``, ``"-y"``, ``"z"`` ... as a unit vector ``(x, y, z)``."""
    t = text.strip().lower()
    sign = -1.0 if t.startswith("-") else 1.0
    name = t.lstrip("+-")
    if name not in ("x", "y", "z"):
        raise GridError(f"axis {text!r} is not one of +x, -x, +y, -y, +z, -z")
    vector = [0.0, 0.0, 0.0]
    vector[AXES.index(name)] = sign
    return tuple(vector)  # type: ignore[return-value]


def axis_name(vector: Sequence[float]) -> str:
    """The inverse of :func:`parse_axis` for unit axis vectors."""
    for i, c in enumerate(vector):
        if c:
            return ("+" if c > 0 else "-") + AXES[i]
    raise ValueError(f"{vector!r} is not an axis vector")


@dataclass(frozen=True)
class GridSpec:
    """What defines a scan. All lengths in mm, positions as machine coordinates ``(x, y, z)``."""

    rows: int = 9
    cols: int = 9
    pitch_mm: float = 0.5
    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    row_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    col_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    order: str = "serpentine"
    approach: tuple[int, int, int] = (1, 1, 1)
    backlash_mm: float = 0.2

    def __post_init__(self) -> None:
        if not (isinstance(self.rows, int) and isinstance(self.cols, int) and self.rows >= 1 and self.cols >= 1):
            raise GridError(f"grid size must be at least 1x1; got {self.rows}x{self.cols}")
        if not (math.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise GridError(f"pitch must be positive (mm); got {self.pitch_mm!r}")
        if self.order not in ORDERS:
            raise GridError(f"order must be one of {', '.join(ORDERS)}; got {self.order!r}")
        if any(a not in (1, -1) for a in self.approach):
            raise GridError(f"approach must be +1 or -1 per axis; got {self.approach!r}")
        if not (math.isfinite(self.backlash_mm) and self.backlash_mm >= 0):
            raise GridError(f"backlash_mm must be a finite distance >= 0 (mm); got {self.backlash_mm!r}")
        if len(self.centre_mm) != 3 or not all(math.isfinite(c) for c in self.centre_mm):
            raise GridError(f"centre must be (x, y, z), finite numbers of mm; got {self.centre_mm!r}")
        dot = sum(a * b for a, b in zip(self.row_axis, self.col_axis))
        if dot != 0:
            raise GridError("row and column axes must be different stage axes")

    @property
    def centre_index(self) -> tuple[int, int]:
        return self.rows // 2, self.cols // 2

    def settings(self) -> dict[str, Any]:
        """The values a resumed capture must share (JSON-friendly)."""
        d = asdict(self)
        d["centre_mm"] = [float(c) for c in self.centre_mm]
        d["row_axis"] = axis_name(self.row_axis)
        d["col_axis"] = axis_name(self.col_axis)
        d["approach"] = list(self.approach)
        return d


ORDERS = ("serpentine", "raster")


@dataclass(frozen=True)
class Move:
    """One absolute move of a plan. ``view`` is ``(u, v)`` when a frame is taken at the end, or
    ``None`` for a backlash take-up move."""

    target_mm: tuple[float, float, float]
    view: tuple[int, int] | None = None
    note: str = field(default="", compare=False)


def view_position(spec: GridSpec, u: int, v: int) -> tuple[float, float, float]:
    """Machine position (mm) of view ``(u, v)``."""
    u0, v0 = spec.centre_index
    du, dv = (u - u0) * spec.pitch_mm, (v - v0) * spec.pitch_mm
    return tuple(
        round(c + du * r + dv * k, 9) for c, r, k in zip(spec.centre_mm, spec.row_axis, spec.col_axis)
    )  # type: ignore[return-value]


def scan_order(rows: int, cols: int, *, order: str = "serpentine") -> list[tuple[int, int]]:
    """Grid positions in visiting order: row by row, every other row reversed for ``serpentine``."""
    if order not in ORDERS:
        raise GridError(f"order must be one of {', '.join(ORDERS)}; got {order!r}")
    views = []
    for u in range(rows):
        columns = range(cols)
        if order == "serpentine" and u % 2 == 1:
            columns = reversed(range(cols))
        views.extend((u, v) for v in columns)
    return views


def plan_moves(
    spec: GridSpec,
    *,
    views: Sequence[tuple[int, int]] | None = None,
    start_mm: Sequence[float] | None = None,
) -> list[Move]:
    """Every move of a scan, in order, including backlash take-up moves.

    ``views``: the views still to take, in any order (default all); they are visited in the spec's
    order. ``start_mm``: where the stage is (unknown by default, so the first view is approached
    from ``backlash_mm`` away on every axis).
    """
    wanted = None if views is None else set(map(tuple, views))
    ordered = [uv for uv in scan_order(spec.rows, spec.cols, order=spec.order) if wanted is None or uv in wanted]
    moves: list[Move] = []
    current = None if start_mm is None else tuple(float(c) for c in start_mm)
    for u, v in ordered:
        target = view_position(spec, u, v)
        wrong = [
            current is None or (t - c) * a < -1e-9
            for t, c, a in zip(target, current or target, spec.approach)
        ]
        if spec.backlash_mm > 0 and any(wrong):
            pre = tuple(
                t - a * spec.backlash_mm if bad else t for t, a, bad in zip(target, spec.approach, wrong)
            )
            moves.append(Move(pre, None, "take up backlash"))  # type: ignore[arg-type]
        moves.append(Move(target, (u, v)))
        current = target
    return moves


def check_limits(moves: Sequence[Move], limits_mm: Sequence[tuple[float, float]] | None) -> None:
    """Raise :class:`GridError` naming the first move outside ``limits_mm`` (per axis ``(min, max)``)."""
    if limits_mm is None:
        return
    for move in moves:
        for axis, (value, (lo, hi)) in enumerate(zip(move.target_mm, limits_mm)):
            if not lo - 1e-9 <= value <= hi + 1e-9:
                what = f"view {move.view}" if move.view else "a backlash take-up move"
                raise GridError(
                    f"{what} needs {AXES[axis]} = {value:.3f} mm, outside the stage's travel "
                    f"[{lo:.3f}, {hi:.3f}] mm; move the grid centre (--centre-mm) or shrink the grid"
                )


def grid_extent_mm(moves: Sequence[Move]) -> tuple[tuple[float, float], ...]:
    """Per-axis ``(min, max)`` of all move targets."""
    return tuple(
        (min(m.target_mm[i] for m in moves), max(m.target_mm[i] for m in moves)) for i in range(3)
    )


def format_plan(moves: Sequence[Move]) -> str:
    """A dry run's listing: one line per move."""
    lines = []
    for i, move in enumerate(moves, start=1):
        x, y, z = move.target_mm
        what = f"view u={move.view[0]:02d} v={move.view[1]:02d}" if move.view else move.note
        lines.append(f"{i:4d}  X{x:9.3f} Y{y:9.3f} Z{z:9.3f}  {what}")
    return "\n".join(lines)
