"""``escort_rl.make_filter(name, **overrides)``: any filter by its config name, as a run builds it."""

from __future__ import annotations

import pytest

import escort_rl
from escort_rl.config import ConfigError, compose
from escort_rl.config.files import option_names
from escort_rl.trainers.builders import build_filter


@pytest.mark.parametrize("name", option_names("filter"))
def test_every_filter_option_is_built_as_a_run_builds_it(name):
    made, from_config = escort_rl.make_filter(name), build_filter(compose([f"filter={name}"]).filter)
    assert type(made) is type(from_config)
    assert vars(made).keys() == vars(from_config).keys()
    for key, value in vars(from_config).items():
        if isinstance(value, (int, float, str, bool, type(None))):
            assert getattr(made, key) == value, key


def test_overrides_change_the_options_keys():
    f = escort_rl.make_filter("escort_train", num_steps=4, compile=False)
    assert f.num_steps == 4 and f.step_size == escort_rl.make_filter("escort_train").step_size


@pytest.mark.parametrize(("name", "overrides", "start"), [
    ("escort_train", {"num_stepz": 3}, "filter: unknown key 'filter.num_stepz'"),
    ("escort_train", {"num_steps": "x"}, "filter.num_steps: expected an int, got 'x'"),
    ("nope", {}, "config: no filter config 'nope'; choose one of"),
])
def test_a_bad_name_or_key_is_named(name, overrides, start):
    with pytest.raises(ConfigError) as info:
        escort_rl.make_filter(name, **overrides)
    assert str(info.value).startswith(start), str(info.value)
