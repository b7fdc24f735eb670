"""Continuous actions (``env=lightdark10d_continuous``, the Gaussian policy) refuse a mistake with one
line naming the config key, the argument or the field, and say the fix: a force or start box out of
range, an input scaling that does not fit the state, a TanhNormal box that is not a box, and real
actions of the wrong dtype, shape or range handed to a filter. A float64 action is read as float32."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import config_error, one_line_error
from escort_rl.belief import EnKFFilter, ESCORTFilter, SIRFilter
from escort_rl.config import ConfigError, compose
from escort_rl.models import LightDark10DContinuous
from escort_rl.modules import DeepSetsActor, make_deepsets_policy
from escort_rl.trainers.builders import build_model, build_policy

ENV = "env=lightdark10d_continuous"
B, N = 2, 8



# ---------------------------------------------------------------------------------------------
# The config
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("overrides, expected", [
    (["env.model.force=-0.1"], "env.model: LightDark10DContinuous.force: the action box is [-force, force], so force "
                               "must be > 0, got -0.1"),
    (["env.model.force=0"], "env.model: LightDark10DContinuous.force: the action box is [-force, force], so force "
                            "must be > 0, got 0.0"),
    (["env.model.start_low=5.0", "env.model.start_high=1.0"],
     "env.model: LightDark10DContinuous.start_low: must be < start_high (the start box is [start_low, "
     "start_high]^n_pos), got 5.0 >= 1.0"),
], ids=["negative-force", "zero-force", "start-box-upside-down"])
def test_a_model_value_out_of_range_is_named_when_the_model_is_built(overrides, expected):
    cfg = compose([ENV, *overrides])
    assert one_line_error(lambda: build_model(cfg.env), ConfigError) == expected


@pytest.mark.parametrize("overrides, model, expected", [
    (["env.input_loc=[0,0,0]"], {}, "env.input_loc: expected a number or 10 numbers (one per dimension of the model's "
                                    "state), got 3; set env.input_loc to a number or a list of 10"),
    (["env.input_scale=[1,1]"], {}, "env.input_scale: expected a number or 10 numbers"),
    (["env.model.n_pos=6"], {"n_pos": 6}, "env.input_loc: expected a number or 12 numbers (one per dimension of the "
                                          "model's state), got 10"),
], ids=["input-loc-of-3", "input-scale-of-2", "n-pos-6-with-the-5d-scaling"])
def test_an_input_scaling_that_does_not_fit_the_state_names_its_key(overrides, model, expected):
    """It used to reach ``Tensor.expand`` inside the policy's constructor (a torch RuntimeError)."""
    cfg = compose([ENV, *overrides])
    message = one_line_error(lambda: build_policy(cfg, LightDark10DContinuous(**model)), ConfigError)
    assert message.startswith(expected), message


def test_a_negative_scripted_gain_is_named_while_composing():
    assert config_error([ENV, "env.scripted_gain=-2"]) == "config: env.scripted_gain: must be >= 0, got -2.0"


# ---------------------------------------------------------------------------------------------
# The continuous policy's box
# ---------------------------------------------------------------------------------------------

HIGH = torch.full((5,), 0.1)


@pytest.mark.parametrize("box, expected", [
    ((HIGH, -HIGH), "action_box: expected finite bounds with low < high in every dimension (the policy puts its "
                    "Gaussian in the box), got low [0.10000000149011612"),
    ((torch.full((5,), math.nan), HIGH), "action_box: expected finite bounds with low < high in every dimension"),
    ((torch.full((5,), -math.inf), HIGH), "action_box: expected finite bounds with low < high in every dimension"),
    ((-HIGH,), "action_box: expected a pair (low, high) of tensors [A], got tuple of 1 items"),
], ids=["low-above-high", "nan-bound", "infinite-bound", "one-bound"])
def test_a_tanh_normal_box_that_is_not_a_box_is_refused(box, expected):
    """A box with low > high or a NaN bound used to give a policy whose actions fall outside any box."""
    actor = DeepSetsActor(10, 10, hidden=8)
    assert one_line_error(lambda: make_deepsets_policy(actor, action_box=box)).startswith(expected)


# ---------------------------------------------------------------------------------------------
# Real actions handed to a filter
# ---------------------------------------------------------------------------------------------

FILTERS = {"sir": SIRFilter, "enkf": EnKFFilter, "escort": lambda: ESCORTFilter(num_steps=2)}


def _update(name: str, action: torch.Tensor):
    model, filt = LightDark10DContinuous(), FILTERS[name]()
    belief = filt.init(model, (B,), N, torch.Generator().manual_seed(0))
    return filt.update(model, belief, action, torch.zeros(B, 5), torch.Generator().manual_seed(1))


BOX = "action: real actions must lie in the box [model.action_low, model.action_high]"


@pytest.mark.parametrize("action, expected", [
    (torch.zeros(B, 5, dtype=torch.long), "action: expected a floating-point tensor (continuous actions), got dtype "
                                          "torch.int64"),
    (torch.zeros(B), "action: expected shape (2, 5) (a real vector of model.action_dim = 5 per belief), got (2,)"),
    (torch.zeros(B, 4), "action: expected shape (2, 5) (a real vector of model.action_dim = 5 per belief), got (2, 4)"),
    (torch.tensor([[0.0, math.nan, 0.0, 0.0, 0.0]] * B), BOX),
    (torch.full((B, 5), 0.5), BOX),
], ids=["integer", "discrete-shape", "wrong-action-dim", "nan", "outside-the-box"])
@pytest.mark.parametrize("name", sorted(FILTERS))
def test_a_bad_real_action_is_named_by_every_filter(name, action, expected):
    message = one_line_error(lambda: _update(name, action))
    assert message.startswith(expected), message
    if expected == BOX:
        assert "squash the policy's output into the box" in message


def test_a_float64_action_is_read_as_float32():
    action = torch.full((B, 5), 0.05)
    wide, narrow = _update("sir", action.double()), _update("sir", action)
    assert wide.particles.dtype == torch.float32
    torch.testing.assert_close(wide.particles, narrow.particles, rtol=0, atol=0)
