"""The scan grid: positions, serpentine order, backlash-free approach, limit checks."""

from __future__ import annotations

import pytest

from rig.grid import (
    GridError,
    GridSpec,
    Move,
    axis_name,
    check_limits,
    format_plan,
    parse_axis,
    plan_moves,
    scan_order,
    view_position,
)


def test_serpentine_and_raster_orders():
    assert scan_order(2, 3) == [(0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (1, 0)]
    assert scan_order(2, 3, order="raster") == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]
    order = scan_order(9, 9)
    assert len(order) == 81 and len(set(order)) == 81
    # serpentine: consecutive views are neighbours
    assert all(abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1 for a, b in zip(order, order[1:]))


def test_positions_follow_the_conventions():
    spec = GridSpec(centre_mm=(-50.0, -40.0, -10.0))
    assert view_position(spec, 4, 4) == (-50.0, -40.0, -10.0)  # centre view at the centre
    assert view_position(spec, 4, 5) == (-49.5, -40.0, -10.0)  # v grows along +x
    assert view_position(spec, 5, 4) == (-50.0, -39.5, -10.0)  # u grows along +y
    flipped = GridSpec(centre_mm=(0.0, 0.0, 0.0), row_axis=parse_axis("-x"), col_axis=parse_axis("+z"))
    assert view_position(flipped, 0, 0) == (2.0, 0.0, -2.0)


def test_every_view_is_reached_moving_in_the_approach_direction():
    for approach in [(1, 1, 1), (-1, 1, -1)]:
        spec = GridSpec(rows=4, cols=5, centre_mm=(-50.0, -50.0, -10.0), approach=approach, backlash_mm=0.3)
        moves = plan_moves(spec, start_mm=(-1.0, -1.0, -1.0))
        assert [m.view for m in moves if m.view] == scan_order(4, 5)
        previous = (-1.0, -1.0, -1.0)
        last_direction = [0, 0, 0]
        for move in moves:
            for axis in range(3):
                delta = move.target_mm[axis] - previous[axis]
                if abs(delta) > 1e-9:
                    last_direction[axis] = 1 if delta > 0 else -1
            if move.view is not None:
                assert last_direction == list(approach), (move, last_direction)
            previous = move.target_mm


def test_backlash_moves_only_where_needed():
    spec = GridSpec(rows=2, cols=3, centre_mm=(-50.0, -50.0, -10.0), backlash_mm=0.2)
    moves = plan_moves(spec)
    kinds = ["view" if m.view else "take-up" for m in moves]
    # first view: take-up on all axes; row 0 runs +x: direct; stepping to row 1 moves +y only: direct;
    # row 1 then runs -x: take-up before each further view
    assert kinds == ["take-up", "view", "view", "view", "view", "take-up", "view", "take-up", "view"]
    assert moves[0].target_mm == pytest.approx((-50.7, -50.7, -10.2))
    assert moves[5].target_mm == pytest.approx((-50.2, -50.0, -10.0))
    assert all(m.view for m in plan_moves(GridSpec(rows=2, cols=3, backlash_mm=0.0)))


def test_plan_for_the_remaining_views_keeps_the_order():
    spec = GridSpec(rows=3, cols=3)
    moves = plan_moves(spec, views=[(2, 2), (0, 1), (1, 0)])
    assert [m.view for m in moves if m.view] == [(0, 1), (1, 0), (2, 2)]


def test_check_limits_names_the_offending_move():
    spec = GridSpec(rows=3, cols=3, centre_mm=(-0.4, -50.0, -10.0))
    moves = plan_moves(spec)
    limits = ((-100.0, 0.0), (-100.0, 0.0), (-50.0, 0.0))
    with pytest.raises(GridError, match=r"view \(0, 2\) needs x = 0\.100 mm, outside .*--centre-mm"):
        check_limits(moves, limits)
    check_limits(plan_moves(GridSpec(rows=3, cols=3, centre_mm=(-1.0, -50.0, -10.0))), limits)
    check_limits(moves, None)
    with pytest.raises(GridError, match="backlash take-up"):
        check_limits([Move((-100.2, -1.0, -1.0))], limits)


def test_format_plan_and_axis_names():
    text = format_plan(plan_moves(GridSpec(rows=1, cols=2, centre_mm=(-5.0, -5.0, -1.0))))
    assert text.splitlines()[1] == "   2  X   -5.500 Y   -5.000 Z   -1.000  view u=00 v=00"
    assert axis_name(parse_axis("-y")) == "-y"


@pytest.mark.parametrize(
    "kwargs",
    [dict(rows=0), dict(pitch_mm=0.0), dict(order="spiral"), dict(approach=(1, 0, 1)),
     dict(backlash_mm=-1.0), dict(row_axis=(1.0, 0.0, 0.0))],
)
def test_bad_specs_are_refused(kwargs):
    with pytest.raises(GridError):
        GridSpec(**kwargs)
    with pytest.raises(GridError):
        parse_axis("w")
