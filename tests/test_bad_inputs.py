"""Bad inputs get one line naming the field, the argument or the model method, never a deep torch
error or a silently wrong result: belief shapes and dtypes, model outputs of the wrong shape or
dtype, filter and env constructor arguments of the wrong type, and the command line's output paths,
seeds and device."""

from __future__ import annotations

import pytest
import torch

from escort_rl.belief import ESCORTFilter, ParticleBelief, SIRFilter, SVGDFilter
from escort_rl.envs import POMDPEnv
from escort_rl.models import LightDark10D, LinearGaussian

B, N, D = 2, 12, 3

FILTERS = {
    "sir": lambda: SIRFilter(),
    "svgd": lambda: SVGDFilter(num_steps=3),
    "escort": lambda: ESCORTFilter(num_steps=3),
}


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _inputs(filt, b: int = B, n: int = N):
    model = LinearGaussian(state_dim=D)
    belief = filt.init(model, (b,), n, gen(0))
    return model, belief, torch.zeros(b, dtype=torch.long), torch.full((b, D), 0.3)


def _one_line_error(fn) -> str:
    with pytest.raises(ValueError) as info:
        fn()
    message = str(info.value)
    assert "\n" not in message, message
    return message


# ---------------------------------------------------------------------------------------------
# The input belief: shapes and dtypes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("shape", [(B, 1), (1, N), (B, N + 1)], ids=["one-column", "one-row", "one-too-many"])
def test_log_weights_of_another_shape_name_belief_log_weights(name, shape):
    """A [B, 1] or [1, N] log-weight tensor used to broadcast against the particles' [B, N] and give
    a belief without complaint."""
    filt = FILTERS[name]()
    model, belief, action, obs = _inputs(filt)
    bad = ParticleBelief(belief.particles, torch.zeros(shape))
    message = _one_line_error(lambda: filt.update(model, bad, action, obs, gen(1)))
    assert message.startswith(f"belief.log_weights: expected a floating-point tensor of shape {(B, N)}"), message
    assert f"got shape {shape}" in message


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_integer_particles_name_belief_particles(name):
    filt = FILTERS[name]()
    model, belief, action, obs = _inputs(filt)
    bad = ParticleBelief(belief.particles.round().long(), belief.log_weights)
    message = _one_line_error(lambda: filt.update(model, bad, action, obs, gen(1)))
    assert message.startswith("belief.particles: expected a floating-point tensor"), message
    assert "torch.int64" in message


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_a_float64_belief_of_a_float32_model_names_the_method_and_the_dtype(name):
    filt = FILTERS[name]()
    model, belief, action, obs = _inputs(filt)
    wide = ParticleBelief(belief.particles.double(), belief.log_weights.double())
    message = _one_line_error(lambda: filt.update(model, wide, action, obs, gen(1)))
    assert message.startswith("model.transition: fails on belief.particles of shape (2, 12, 3) and dtype "
                              "torch.float64"), message


# ---------------------------------------------------------------------------------------------
# Model methods that return the wrong shape or dtype
# ---------------------------------------------------------------------------------------------


class Misshapen(LinearGaussian):
    """A 3-D linear-Gaussian model whose ``transition`` or ``observation_log_prob`` returns the wrong
    shape or dtype (``kind``)."""

    def __init__(self, kind: str) -> None:
        super().__init__(state_dim=D)
        self.kind = kind
        self.observation_score = None  # the filters call observation_log_prob

    def transition(self, s, a, generator=None):
        out = super().transition(s, a, generator)
        if s.dim() == 3 and self.kind == "transition_drops_a_dimension":
            return out[..., :2]
        if s.dim() == 3 and self.kind == "transition_returns_ints":
            return out.round().long()
        return out

    def observation_log_prob(self, o, s_next, a):
        out = super().observation_log_prob(o, s_next, a)
        if self.kind == "log_prob_per_belief":
            return out[..., 0]
        if self.kind == "log_prob_with_a_trailing_axis":
            return out.unsqueeze(-1)
        return out


CULPRITS = {
    "transition_drops_a_dimension": "model.transition: returned shape (2, 12, 2)",
    "transition_returns_ints": "model.transition: returned shape (2, 12, 3), dtype torch.int64",
    "log_prob_per_belief": "model.observation_log_prob: returned shape (2,)",
    "log_prob_with_a_trailing_axis": "model.observation_log_prob: returned shape (2, 12, 1)",
}


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("kind", sorted(CULPRITS))
def test_a_model_output_of_the_wrong_shape_or_dtype_names_the_method(name, kind):
    filt = FILTERS[name]()
    _, belief, action, obs = _inputs(filt)
    message = _one_line_error(lambda: filt.update(Misshapen(kind), belief, action, obs, gen(1)))
    assert message.startswith(CULPRITS[kind]), message


def test_sir_refuses_a_log_likelihood_that_would_broadcast_silently():
    """With as many beliefs as particles, a [B, N, 1] log-likelihood broadcasts against the [B, N]
    log-weights without a torch error; SIR checks the shape itself."""
    filt = SIRFilter()
    _, belief, action, obs = _inputs(filt, b=4, n=4)
    message = _one_line_error(lambda: filt.update(Misshapen("log_prob_with_a_trailing_axis"), belief, action, obs))
    assert message.startswith("model.observation_log_prob: returned shape (4, 4, 1), dtype torch.float32, expected "
                              "a floating-point tensor of shape (4, 4)"), message


# ---------------------------------------------------------------------------------------------
# Constructor arguments of the wrong type
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch_shape", [(-1,), (2.5,), 2.5, (True,)], ids=["negative", "fraction", "float", "bool"])
def test_init_names_a_bad_batch_shape(batch_shape):
    message = _one_line_error(lambda: SIRFilter().init(LinearGaussian(state_dim=D), batch_shape, 8, gen(0)))
    assert message.startswith("batch_shape: expected a tuple of ints >= 0"), message


@pytest.mark.parametrize("kwargs, field", [(dict(resample_threshold="0.5"), "resample_threshold"),
                                           (dict(roughening=None), "roughening"),
                                           (dict(roughening="0.1"), "roughening")],
                         ids=["threshold-str", "roughening-none", "roughening-str"])
def test_sir_arguments_that_are_not_numbers_are_named(kwargs, field):
    message = _one_line_error(lambda: SIRFilter(**kwargs))
    assert message == f"SIRFilter.{field}: must be a number, got {kwargs[field]!r}"


@pytest.mark.parametrize("kwargs, expected", [
    (dict(batch_size=2.5), "POMDPEnv.batch_size: every size must be a positive int, got 2.5"),
    (dict(batch_size=(True,)), "POMDPEnv.batch_size: every size must be a positive int, got (True,)"),
    (dict(max_steps=2.5), "POMDPEnv.max_steps: must be a positive int or None, got 2.5"),
    (dict(max_steps=0), "POMDPEnv.max_steps: must be a positive int or None, got 0"),
    (dict(seed=2.5), "POMDPEnv.seed: must be an int or None, got 2.5"),
], ids=["batch-float", "batch-bool", "max-steps-fraction", "max-steps-zero", "seed-fraction"])
def test_pomdp_env_names_a_bad_argument(kwargs, expected):
    assert _one_line_error(lambda: POMDPEnv(LightDark10D(), **kwargs)) == expected
