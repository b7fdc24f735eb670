"""bench gradient-noise (escort_rl.bench.gradient_noise): the noise statistics against their closed
form, the decision gradient against a hand computation, and a measurement on tiny REINFORCE and PPO runs."""

import math

import pytest
import torch

from conftest import gen, one_line_error
from escort_rl.bench.gradient_noise import (
    MONTE_CARLO,
    decision_gradient,
    gradient_noise_markdown,
    gradient_statistics,
    measure_run,
)
from escort_rl.config import compose
from escort_rl.trainers.training import train


def test_statistics_of_gaussian_gradients_match_the_closed_form(per_test_generator):
    # g_r = μ + σ z_r: noise = P σ², signal = ‖μ‖²; the estimates' standard errors are about 0.01 P σ²
    # and 0.7 here, so the bounds are 6 standard errors.
    r, p, sigma = 400, 50, 1.0
    mu = torch.ones(p)
    g = mu + sigma * torch.randn(r, p, generator=per_test_generator)
    s = gradient_statistics(g)
    assert abs(s["noise"] / (p * sigma**2) - 1) < 6 * math.sqrt(2 / (p * (r - 1)))
    assert abs(s["signal"] - p) < 6 * math.sqrt(4 * p * sigma**2 / r)
    assert abs(s["snr"] - 1.0) < 0.15
    # cos(g_r, mean of others) ≈ ‖μ‖² / (‖μ + σz‖ ‖μ‖) ≈ 1/√2 when ‖μ‖² = P σ²
    assert abs(s["cosine"] - 1 / math.sqrt(2)) < 0.05


def test_pure_noise_has_no_signal(per_test_generator):
    g = torch.randn(400, 50, generator=per_test_generator)
    s = gradient_statistics(g)
    assert abs(s["snr"]) < 6 * math.sqrt(2 / 400) and abs(s["cosine"]) < 0.05


def test_one_gradient_is_refused():
    assert "R >= 2" in one_line_error(lambda: gradient_statistics(torch.ones(1, 3)))


def test_decision_gradient_is_the_score_function_gradient_by_hand():
    # A categorical policy with logits θ (no input): ∇θ [−(1/M) Σ log π(a_t) A_t] = −(1/M) Σ (onehot(a_t) − π) A_t,
    # the same whatever the chunk.
    from tensordict import TensorDict

    theta = torch.randn(3, generator=gen(0), requires_grad=True)

    class Policy:
        def get_dist(self, td):
            return torch.distributions.Categorical(logits=theta.expand(td.shape[0], 3))

    actions = torch.tensor([0, 2, 2, 1, 0])
    adv = torch.tensor([1.0, -0.5, 2.0, 0.3, -1.0])
    batch = TensorDict({"action": actions}, batch_size=[5])
    pi = torch.softmax(theta.detach(), -1)
    expected = -((torch.nn.functional.one_hot(actions, 3) - pi) * adv[:, None]).mean(0)
    for chunk in (5, 2):
        torch.testing.assert_close(decision_gradient(Policy(), [theta], batch, adv, chunk), expected)


@pytest.mark.parametrize("trainer", [["trainer=reinforce", "trainer.baseline=learned", "trainer.minibatch_size=16"],
                                     ["trainer=ppo", "trainer.rollout_steps=6", "trainer.teacher=none",
                                      "trainer.warm_start_iterations=0"]])
def test_measure_run_on_a_tiny_run(tmp_path, trainer):
    run = tmp_path / "run"
    train(compose([*trainer, "filter=sir", "trainer.num_envs=4", "env.max_steps=12", "num_particles=8",
                   "actor.hidden=8", "trainer.iterations=1", f"output_dir={run}"]), progress=False)
    res = measure_run(run, batches=3, lambdas=(0.9,))
    assert res["iteration"] == 1 and res["batches"] == 3 and res["frames_per_batch"] > 0
    assert set(res["estimators"]) == {MONTE_CARLO, "GAE λ=0.9"}
    for s in res["estimators"].values():
        assert all(math.isfinite(v) for v in s.values()) and s["noise"] > 0
    assert res["estimators"][MONTE_CARLO]["agreement"] == pytest.approx(1.0)
    assert "GAE λ=0.9" in gradient_noise_markdown([res])
