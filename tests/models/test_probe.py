"""The model probe (escort_rl.models.probe): a user's model with one mistake at a time is refused before
anything trains, by an error that names the method; every package model passes."""

from __future__ import annotations

import math

import pytest
import torch

import escort_rl
from escort_rl.config import ConfigError, registry
from escort_rl.models import check_model
from escort_rl.models.probe import ModelProbeError, probe_model


class Drift:
    """A 2-D linear-Gaussian model: position and velocity, three pushes, the position observed."""

    state_dim, obs_dim, n_actions = 2, 1, 3
    device = torch.device("cpu")
    noise = torch.tensor([0.05, 0.02])
    push = torch.tensor([0.0, 0.1, -0.1])

    def initial_state(self, shape, generator=None):
        return torch.randn(*shape, 2, generator=generator)

    def initial_belief(self, shape, n, generator=None):
        return torch.randn(*shape, n, 2, generator=generator)

    def transition_mean(self, s, a):
        return torch.stack([s[..., 0] + 0.1 * s[..., 1], s[..., 1] + self.push[a]], -1)

    def transition_scale_tril(self):
        return torch.diag(self.noise)

    def transition(self, s, a, generator=None):
        mean = self.transition_mean(s, a)
        return mean + torch.randn(mean.shape, generator=generator) * self.noise

    def transition_log_prob(self, s_next, s, a):
        z = (s_next - self.transition_mean(s, a)) / self.noise
        return (-0.5 * z**2 - torch.log(self.noise) - 0.5 * math.log(2 * math.pi)).sum(-1)

    def observe(self, s_next, a, generator=None):
        return s_next[..., :1] + 0.3 * torch.randn(s_next.shape[:-1] + (1,), generator=generator)

    def observation_log_prob(self, o, s_next, a):
        z = (o[..., 0] - s_next[..., 0]) / 0.3
        return -0.5 * z**2 - math.log(0.3) - 0.5 * math.log(2 * math.pi)

    def reward(self, s, a, s_next):
        return -s_next[..., 0].abs()

    def is_terminal(self, s):
        return s[..., 0].abs() > 100.0


class FloatTerminal(Drift):
    def is_terminal(self, s):
        return (s[..., 0].abs() > 100.0).float()


class ObservationWithoutItsDimension(Drift):
    def observe(self, s_next, a, generator=None):
        return super().observe(s_next, a, generator)[..., 0]


class BeliefIgnoringN(Drift):
    def initial_belief(self, shape, n, generator=None):
        return torch.randn(*shape, 10, 2, generator=generator)


class Float64Start(Drift):
    def initial_state(self, shape, generator=None):
        return super().initial_state(shape, generator).double()


class TransitionLogProbWithATrailingDim(Drift):
    def transition_log_prob(self, s_next, s, a):
        return super().transition_log_prob(s_next, s, a).unsqueeze(-1)


class DetachedLikelihood(Drift):
    def observation_log_prob(self, o, s_next, a):
        return super().observation_log_prob(o, s_next.detach(), a)


class RewardWithATrailingDim(Drift):
    def reward(self, s, a, s_next):
        return super().reward(s, a, s_next).unsqueeze(-1)


class DiagonalScale(Drift):
    def transition_scale_tril(self):
        return self.noise.clone()


MISTAKES = [
    (FloatTerminal(), "model.is_terminal(s): expected dtype torch.bool, got torch.float32"),
    (ObservationWithoutItsDimension(), "model.observe(s_next, a, generator): expected shape (3, 1)"),
    (BeliefIgnoringN(), "model.initial_belief(shape=(3,), n=4, generator): expected shape (3, 4, 2)"),
    (Float64Start(), "model.initial_state(shape=(3,), generator): expected dtype torch.float32, got torch.float64"),
    (Drift, "model: got the class Drift, not an instance of it; pass Drift(...) instead"),
    (TransitionLogProbWithATrailingDim(), "model.transition_log_prob(s_next, s, a): expected shape (3,)"),
    (DetachedLikelihood(), "model.observation_log_prob("),
    (RewardWithATrailingDim(), "model.reward(s, a, s_next): expected shape (3,)"),
    (DiagonalScale(), "model.transition_scale_tril(): expected shape (2, 2)"),
]


@pytest.mark.parametrize(("model", "start"), MISTAKES, ids=lambda v: v if isinstance(v, str) else None)
def test_a_model_with_one_mistake_is_refused_before_training_naming_the_method(model, start, tmp_path):
    with pytest.raises(ConfigError) as info:
        escort_rl.train(["env=custom", "trainer.iterations=1", "trainer.warm_start_filter=null",
                         f"output_dir={tmp_path / 'run'}"], model=model, progress=False)
    message = str(info.value)
    assert start in message and "\n" not in message, message
    assert not (tmp_path / "run" / "checkpoints").exists()  # nothing trained


def test_a_detached_likelihood_is_named_for_its_missing_gradient():
    with pytest.raises(ModelProbeError, match=r"not differentiable in the state .* ESCORT and SVGD move the particles"):
        probe_model(DetachedLikelihood())


def test_a_flat_likelihood_written_on_the_state_passes():
    class Flat(Drift):
        def observation_log_prob(self, o, s_next, a):
            return 0.0 * s_next[..., 0] + 0.0 * o[..., 0]

    probe_model(Flat())


def test_a_nan_log_density_is_refused():
    class NaNLikelihood(Drift):
        def observation_log_prob(self, o, s_next, a):
            return super().observation_log_prob(o, s_next, a) * torch.nan

    with pytest.raises(ModelProbeError, match=r"^model.observation_log_prob\(o, s_next, a\): expected finite or -inf"):
        probe_model(NaNLikelihood())


def test_a_method_that_raises_is_named_with_its_error():
    class Raises(Drift):
        def reward(self, s, a, s_next):
            raise RuntimeError("shapes do not match\nsecond line")

    with pytest.raises(ModelProbeError, match=r"^model.reward\(s, a, s_next\): raised RuntimeError: shapes do not "
                                              r"match$"):
        probe_model(Raises())


@pytest.mark.parametrize("name", registry.names("model"))
def test_every_package_model_passes_the_probe(name):
    probe_model(registry.resolve("model", name)())


def test_check_model_probes_once_then_remembers():
    calls = []

    class Counting(Drift):
        def reward(self, s, a, s_next):
            calls.append(1)
            return super().reward(s, a, s_next)

    model = Counting()
    check_model(model)
    check_model(model)
    assert len(calls) == 1


def test_check_model_from_the_shell(capsys):
    from escort_rl.cli import main

    assert main(["check-model", "escort_rl.models:LightDark10D", "--model-arg", "n_pos=6"]) == 0
    assert "passes the probe" in capsys.readouterr().out
    assert main(["check-model", f"{__name__}:DiagonalScale"]) == 2
    assert capsys.readouterr().err.startswith("error: model.transition_scale_tril(): expected shape (2, 2)")


def test_an_env_probes_its_simulator_without_the_densities_a_filter_needs():
    """An env only simulates (POPGym's deterministic dynamics have no transition density); a filter
    built on the same model later still gets the full probe."""
    from escort_rl.envs import POMDPEnv

    class NoDensity(Drift):
        def transition_log_prob(self, s_next, s, a):
            raise ValueError("deterministic dynamics have no density")

    model = NoDensity()
    POMDPEnv(model, batch_size=(2,))
    with pytest.raises(ModelProbeError, match=r"^model.transition_log_prob\(s_next, s, a\): raised ValueError"):
        check_model(model)
