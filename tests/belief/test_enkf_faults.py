"""The ensemble Kalman filter refuses bad inputs with one line naming the argument, the field or the model
method, and says the fix: constructor arguments of the wrong type, ensembles too small to have a
covariance, beliefs and observations of the wrong shape, dtype or finiteness, a ``model.observe`` that
does not give one perturbed observation per member in the particles' dtype, a singular observation
covariance without a ridge, and localisation coordinates that do not fit. An observation that carries
no information leaves the forecast as it is, without an error."""

from __future__ import annotations

import math

import pytest
import torch

from escort_rl.belief import EnKFFilter, ParticleBelief, SIRFilter
from escort_rl.config import ConfigError
from escort_rl.models import LinearGaussian

B, N, D = 2, 12, 3


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def one_line_error(fn, kind: type[Exception] = ValueError) -> str:
    """The message of the ``kind`` that ``fn()`` raises: one line, not chained to a deeper error."""
    with pytest.raises(kind) as info:
        fn()
    message = str(info.value)
    assert "\n" not in message, message
    assert info.value.__cause__ is None, repr(info.value.__cause__)
    return message


def inputs(model=None, n: int = N):
    model = model or LinearGaussian(state_dim=D)
    belief = EnKFFilter().init(model, (B,), n, gen(0)) if n > 1 else SIRFilter().init(model, (B,), n, gen(0))
    return model, belief, torch.zeros(B, dtype=torch.long), torch.full((B, D), 0.3)


# ---------------------------------------------------------------------------------------------
# The constructor
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, expected", [
    ({"inflation": "1.1"}, "EnKFFilter.inflation: expected a number, got '1.1'"),
    ({"inflation": True}, "EnKFFilter.inflation: expected a number, got 'True'"),
    ({"localisation_radius": -2.0}, "EnKFFilter.localisation_radius: must be > 0, got -2.0"),
    ({"localisation_radius": "far"}, "EnKFFilter.localisation_radius: expected a number or null, got 'far'"),
    ({"ridge": math.inf}, "EnKFFilter.ridge: must be a finite number, got inf"),
    ({"inflaton": 1.05}, "EnKFFilter: unknown parameter 'inflaton'; EnKFFilter takes inflation, localisation_radius, "
                         "ridge"),
], ids=["inflation-string", "inflation-bool", "radius-negative", "radius-string", "ridge-inf", "misspelt-key"])
def test_a_bad_constructor_argument_is_named(kwargs, expected):
    assert one_line_error(lambda: EnKFFilter(**kwargs), ConfigError) == expected


def test_a_positional_inflation_is_named_as_the_params_object():
    assert one_line_error(lambda: EnKFFilter(1.05), ConfigError) == (
        "EnKFFilter: params must be a EnKFParams, got float")


# ---------------------------------------------------------------------------------------------
# The ensemble, the belief and the observation
# ---------------------------------------------------------------------------------------------


def test_one_particle_is_refused_at_init():
    """One member has no covariance: the gain would be 0 and the observation ignored without a word."""
    message = one_line_error(lambda: EnKFFilter().init(LinearGaussian(state_dim=D), (B,), 1, gen(0)))
    assert message == ("num_particles: EnKFFilter needs at least 2 particles (its gain is the ensemble's covariance), "
                       "got 1; use num_particles >= 2")


def test_a_one_particle_belief_from_another_filter_is_refused():
    model, belief, action, obs = inputs(n=1)
    message = one_line_error(lambda: EnKFFilter().update(model, belief, action, obs, gen(1)))
    assert message.startswith("belief.particles: EnKFFilter needs at least 2 particles"), message
    assert "got 1 per belief; build it with num_particles >= 2" in message


def _nan_observation(obs):
    obs = obs.clone()
    obs[1, 2] = math.nan
    return obs


def _inf_observation(obs):
    obs = obs.clone()
    obs[0, 0] = math.inf
    return obs


SHAPE = f"observation: expected shape {(B, D)} (batch, model.obs_dim)"


@pytest.mark.parametrize("spoil, expected", [
    (_nan_observation, "observation: contains NaN or Inf (flat batch indices [1]); filters need finite observations"),
    (_inf_observation, "observation: contains NaN or Inf (flat batch indices [0]); filters need finite observations"),
    (lambda obs: torch.zeros(B, D + 1), f"{SHAPE}, got {(B, D + 1)}"),
    (lambda obs: torch.zeros(B + 1, D), f"{SHAPE}, got {(B + 1, D)}"),
    (lambda obs: obs.tolist(), f"{SHAPE}, got list"),
], ids=["nan", "inf", "wrong-obs-dim", "wrong-batch", "a-list"])
def test_a_bad_observation_is_named(spoil, expected):
    model, belief, action, obs = inputs()
    assert one_line_error(lambda: EnKFFilter().update(model, belief, action, spoil(obs), gen(1))) == expected


@pytest.mark.parametrize("make, start", [
    (lambda b: ParticleBelief.uniform(torch.zeros(B, N, D + 1)),
     f"belief.particles: last dimension is {D + 1} but model.state_dim is {D}"),
    (lambda b: ParticleBelief(b.particles.round().long(), b.log_weights),
     "belief.particles: expected a floating-point tensor [*B, N, d], got shape (2, 12, 3), dtype torch.int64"),
    (lambda b: ParticleBelief(b.particles.double(), b.log_weights.double()),
     "model.transition: fails on belief.particles of shape (2, 12, 3) and dtype torch.float64"),
    (lambda b: b.particles, "belief: expected a ParticleBelief, got Tensor; build it with the filter's init"),
], ids=["wrong-state-dim", "integer-particles", "float64-belief-of-a-float32-model", "a-bare-tensor"])
def test_a_bad_belief_is_named(make, start):
    model, belief, action, obs = inputs()
    message = one_line_error(lambda: EnKFFilter().update(model, make(belief), action, obs, gen(1)))
    assert message.startswith(start), message


def test_particles_without_a_particle_axis_are_named():
    message = one_line_error(lambda: ParticleBelief.uniform(torch.zeros(N)))
    assert message.startswith("particles: expected a floating-point tensor [*B, N, d]"), message
    assert "got shape (12,)" in message and "particles.unsqueeze(-1)" in message


def test_a_seed_passed_as_the_generator_is_named():
    model, belief, action, obs = inputs()
    message = one_line_error(lambda: EnKFFilter().update(model, belief, action, obs, 5))
    assert message == ("generator: expected a torch.Generator or None, got int 5; pass "
                       "torch.Generator().manual_seed(seed)")
    assert one_line_error(lambda: EnKFFilter().init(model, (B,), N, 5)).startswith("generator: ")


def test_integer_observations_are_read_as_the_particles_dtype():
    model, belief, action, _ = inputs()
    ints = torch.tensor([[0, 1, 0], [2, 0, 1]])
    as_int = EnKFFilter().update(model, belief, action, ints, gen(1))
    as_float = EnKFFilter().update(model, belief, action, ints.float(), gen(1))
    assert as_int.particles.dtype == torch.float32
    torch.testing.assert_close(as_int.particles, as_float.particles, rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# What the EnKF needs of the model: model.observe
# ---------------------------------------------------------------------------------------------


class Observe(LinearGaussian):
    """A 3-D linear-Gaussian model whose ``observe`` makes one mistake (``kind``)."""

    def __init__(self, kind: str) -> None:
        super().__init__(state_dim=D)
        self.kind = kind

    def observe(self, s_next, a, generator=None):
        o = super().observe(s_next, a, generator)
        if self.kind == "float64":
            return o.double()
        if self.kind == "integers":
            return o.round().long()
        if self.kind == "per_belief":
            return o[..., 0, :]
        if self.kind == "raises":
            raise RuntimeError("observation table not loaded\nsecond line")
        if self.kind == "noise_free_constant":
            return torch.zeros_like(o)
        if self.kind == "noise_free_repeated":  # one coordinate seen three times: a rank-1 covariance
            return s_next[..., :1].expand(o.shape).clone()
        return o


class ObserveWithoutGenerator(LinearGaussian):
    def observe(self, s_next, a):
        return s_next.clone()


class WithoutObserve(LinearGaussian):
    observe = None


@pytest.mark.parametrize("model, start", [
    (Observe("float64"), "model.observe: returned shape (2, 12, 3), dtype torch.float64, expected a torch.float32 "
                         "tensor (the particles' dtype) of shape (2, 12, 3)"),
    (Observe("integers"), "model.observe: returned shape (2, 12, 3), dtype torch.int64, expected a torch.float32"),
    (Observe("per_belief"), "model.observe: returned shape (2, 3), dtype torch.float32, expected a torch.float32 "
                            "tensor (the particles' dtype) of shape (2, 12, 3) (one observation per particle"),
    (Observe("raises"), "model.observe: fails on belief.particles of shape (2, 12, 3) and dtype torch.float32 "
                        "(RuntimeError: observation table not loaded)"),
    (ObserveWithoutGenerator(state_dim=D), "model.observe: fails on belief.particles of shape (2, 12, 3) and dtype "
                                           "torch.float32 (TypeError: "),
    (WithoutObserve(state_dim=D), "model.observe: WithoutObserve has no method observe()"),
], ids=["float64", "integers", "one-per-belief", "raises", "no-generator-argument", "missing"])
def test_a_model_observe_that_does_not_fit_is_named(model, start):
    _, belief, action, obs = inputs()
    message = one_line_error(lambda: EnKFFilter().update(model, belief, action, obs, gen(1)), (ValueError, TypeError))
    assert message.startswith(start), message


@pytest.mark.parametrize("kind", ["noise_free_constant", "noise_free_repeated"],
                         ids=["noise-free-constant", "noise-free-repeated-coordinate"])
def test_a_singular_observation_covariance_without_a_ridge_names_ridge(kind):
    model, belief, action, obs = inputs(Observe(kind))
    message = one_line_error(lambda: EnKFFilter(ridge=0.0).update(model, belief, action, obs, gen(1)))
    assert message.startswith(f"EnKFFilter.ridge: the ensemble's observation covariance is singular ({N} particles, "
                              f"obs_dim {D}, ridge=0.0); set ridge > 0"), message


def test_an_uninformative_observation_leaves_the_forecast_with_the_default_ridge():
    """A noise-free constant observation carries no information: every observation value gives the
    same finite analysis (the forecast), not NaN and not an error."""
    model, belief, action, obs = inputs(Observe("noise_free_constant"))
    first = EnKFFilter().update(model, belief, action, obs, gen(1)).particles
    second = EnKFFilter().update(model, belief, action, obs + 5.0, gen(1)).particles
    assert bool(torch.isfinite(first).all())
    torch.testing.assert_close(first, second, rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# Localisation coordinates
# ---------------------------------------------------------------------------------------------


def coordinates(**attrs) -> LinearGaussian:
    model = LinearGaussian(state_dim=D)
    for name, value in attrs.items():
        setattr(model, name, value)
    return model


@pytest.mark.parametrize("attrs, expected", [
    ({"state_coordinates": [0.0, 1.0]},
     "model.state_coordinates: expected 3 rows ([3] or [3, k]: where each state coordinate lies), got shape (2, 1)"),
    ({"observation_coordinates": torch.zeros(3, 2, 2)},
     "model.observation_coordinates: expected 3 rows ([3] or [3, k]: where each observation coordinate lies), got "
     "shape (3, 2, 2)"),
    ({"observation_coordinates": "abc"},
     "model.observation_coordinates: expected a list or tensor of positions, [3] or [3, k], got str 'abc'"),
    ({"state_coordinates": [0.0, math.nan, 2.0]},
     "model.state_coordinates: expected finite positions, got NaN or inf (the taper would cut every correlation of "
     "that coordinate); give each coordinate a finite position"),
    ({"state_coordinates": torch.zeros(3, 2)},
     "model.state_coordinates, model.observation_coordinates: expected positions in the same space, got 2 and 1 "
     "columns; give both [size, k] with one k"),
], ids=["too-few-rows", "three-axes", "a-string", "nan", "different-spaces"])
def test_localisation_coordinates_that_do_not_fit_are_named(attrs, expected):
    model, belief, action, obs = inputs(coordinates(**attrs))
    filt = EnKFFilter(localisation_radius=1.0)
    assert one_line_error(lambda: filt.update(model, belief, action, obs, gen(1))) == expected
