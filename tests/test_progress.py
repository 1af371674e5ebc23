"""The progress protocol (``progress(fraction, message)``) and the bar that shows it."""

from __future__ import annotations

import io

from recon.progress import Progress, part, report, step


def test_bar_shows_fraction_message_and_ends_the_line():
    stream = io.StringIO()
    with Progress("matching", stream=stream, interval_s=0.0) as bar:
        bar(0.25, "initial")
        bar(0.5, "line search")
        bar(1.0, "done")
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("matching [") and " 25.0%  initial" in lines[0]
    assert " 50.0%  line search" in lines[1]
    assert "100.0%  done" in lines[-1] and "ETA --:--" in lines[-1]


def test_bar_never_goes_back_and_quiet_writes_nothing():
    stream = io.StringIO()
    bar = Progress("x", stream=stream, interval_s=0.0)
    bar(0.6)
    bar(0.4)
    assert bar.fraction == 0.6
    quiet = io.StringIO()
    with Progress("x", stream=quiet, quiet=True) as silent:
        silent(0.5, "half")
    assert quiet.getvalue() == ""


def test_eta_counts_only_this_runs_work():
    bar = Progress("capture", stream=io.StringIO())
    bar(0.5, "40 of 81 views on disk")  # resumed: half was done by an earlier run
    assert bar.eta_s() is None
    bar.start -= 10.0  # ten seconds for the next quarter
    bar(0.75)
    assert abs(bar.eta_s() - 10.0) < 0.5


def test_part_maps_a_sub_task_into_its_share():
    seen = []
    sub = part(lambda f, m: seen.append((round(f, 6), m)), 0.2, 0.6)
    sub(0.0, "a")
    sub(0.5, "b")
    sub(2.0, "c")  # clipped to the part's end
    assert seen == [(0.2, "a"), (0.4, "b"), (0.6, "c")]
    assert part(None, 0.0, 1.0) is None
    report(None, 0.5, "nothing happens")


def test_a_step_without_fractions_shows_its_start_and_its_end():
    stream = io.StringIO()
    with step("export", "meshing", stream=stream):
        pass
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and "  0.0%  meshing" in lines[0] and "100.0%  meshing" in lines[1]
    quiet = io.StringIO()
    with step("export", "meshing", stream=quiet, quiet=True):
        pass
    assert quiet.getvalue() == ""
    failed = io.StringIO()
    try:
        with step("export", "meshing", stream=failed):
            raise ValueError("no points")
    except ValueError:
        pass
    assert "100.0%" not in failed.getvalue()  # a failed step does not claim to be done
