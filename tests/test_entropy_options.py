"""The estimator's options: groups by step, presets as data, one-line checks before any work."""

from __future__ import annotations

import dataclasses

import pytest

from recon.entropy import DEFAULTS, EntropyOptions, make_options
from recon.entropy.options import GROUPS, PRESETS, STEP_OF, check_value

#: Values that used to pass the check and fail (or run) later: issue #22, point 9.
BAD_VALUES = [
    ("occlusion_views", "foo", "occlusion_views"),
    ("disparity_bin", 0.0, "disparity_bin"),
    ("initial_window", 4, "initial_window"),
    ("intensity_scale", 0.0, "intensity_scale"),
    ("initial_range", (5.0, -5.0), "initial_range"),
    ("gamma", -1.0, "gamma"),
    ("tv_iterations", -1, "tv_iterations"),
]


@pytest.mark.parametrize(("name", "value", "named"), BAD_VALUES)
def test_a_bad_value_is_a_one_line_value_error_before_any_work(name, value, named):
    with pytest.raises(ValueError, match=named) as error:
        make_options(**{name: value})
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match=named):
        check_value(name, value)


def test_every_field_belongs_to_one_step_and_keeps_its_flat_name():
    flat = [f.name for f in dataclasses.fields(EntropyOptions)]
    grouped = [f.name for g in GROUPS.values() for f in dataclasses.fields(g)]
    assert sorted(flat) == sorted(grouped) and len(set(grouped)) == len(grouped) == len(STEP_OF)
    options = make_options(step=0.05, gamma=0.1)
    assert options.matching.step == 0.05 and options.refine.gamma == 0.1
    assert dataclasses.replace(options, gamma=0.3).refine.gamma == 0.3


def test_help_texts_describe_without_continuing_the_previous_field_or_quoting_scores():
    for f in dataclasses.fields(EntropyOptions):
        text = f.metadata["help"]
        assert text and not text.startswith("...") and not text.endswith("..."), f.name
        assert "better on" not in text and "worse on" not in text and "scores" not in text, f.name


def test_presets_name_existing_fields_and_pass_the_checks():
    for name, values in PRESETS.items():
        assert set(values) <= set(STEP_OF), name
        options = make_options(preset=name)
        assert all(getattr(options, k) == v for k, v in values.items())
    assert make_options(preset="default") == DEFAULTS
