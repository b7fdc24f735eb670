"""REINFORCE (escort_rl.trainers.reinforce): the per-time baseline, Monte-Carlo targets and the loss
against hand-computed values."""

import math

import torch
from tensordict import TensorDict

from escort_rl.config import compose
from escort_rl.models import LightDark10D
from escort_rl.trainers.checkpointing import load_checkpoint
from escort_rl.trainers.reinforce import Reinforce, TimeBaseline
from escort_rl.trainers.training import train

TINY_RF = ["trainer=reinforce", "filter=sir", "trainer.num_envs=4", "env.max_steps=12", "num_particles=8",
           "actor.hidden=8", "trainer.minibatch_size=16", "trainer.checkpoint_every=1"]


def test_time_baseline_fits_the_per_step_mean():
    b = TimeBaseline(4)
    steps = torch.tensor([[0], [0], [1], [3], [3], [3]])
    target = torch.tensor([[1.0], [3.0], [-2.0], [6.0], [0.0], [3.0]])
    b.fit_(steps, target)
    assert b.table.tolist() == [2.0, -2.0, 0.0, 3.0, 0.0]
    torch.testing.assert_close(b(torch.tensor([[3], [1], [9]])), torch.tensor([[3.0], [-2.0], [0.0]]))


def _episode_batch(model, t: int = 4):
    """One env, one terminated episode of ``t`` steps with rewards 1..t."""
    g = torch.Generator().manual_seed(1)
    parts = torch.randn(1, t, 5, 10, generator=g)
    logw = torch.full((1, t, 5), -math.log(5))
    done = torch.zeros(1, t, 1, dtype=torch.bool)
    done[0, -1] = True
    reward = torch.arange(1, t + 1, dtype=torch.float32).view(1, t, 1)
    steps = torch.arange(t).view(1, t, 1)
    return TensorDict({"particles": parts, "particle_log_weights": logw, "step_count": steps,
                       "action": torch.randint(0, 10, (1, t), generator=g),
                       "next": {"particles": parts, "particle_log_weights": logw, "step_count": steps + 1,
                                "reward": reward, "done": done, "terminated": done}}, [1, t])


def test_monte_carlo_targets_and_the_policy_gradient_by_hand():
    cfg = compose([*TINY_RF, "trainer.gamma=0.5", "trainer.baseline=learned"])
    model = LightDark10D()
    algo = Reinforce(cfg, model)
    batch = _episode_batch(model)
    algo.loss.value_estimator(batch)
    expected = torch.tensor([1 + 0.5 * (2 + 0.5 * (3 + 0.5 * 4)), 2 + 0.5 * (3 + 0.5 * 4), 3 + 0.5 * 4, 4.0])
    torch.testing.assert_close(batch["value_target"].flatten(), expected)

    batch["advantage"] = torch.tensor([1.0, -1.0, 0.5, 2.0]).view(1, 4, 1)
    out = algo.loss(batch.reshape(-1))
    logits = algo.actor(batch["particles"].flatten(0, 1), batch["particle_log_weights"].flatten(0, 1))
    logp = torch.distributions.Categorical(logits=logits).log_prob(batch["action"].flatten())
    torch.testing.assert_close(out["loss_actor"], -(logp * batch["advantage"].flatten()).mean())


def test_time_baseline_gives_zero_advantage_when_every_episode_is_the_same():
    cfg = compose([*TINY_RF, "trainer.gamma=0.5"])
    algo = Reinforce(cfg, LightDark10D())
    batch = torch.cat([_episode_batch(None), _episode_batch(None)], 0)
    algo.loss.value_estimator(batch)
    algo.critic.fit_(batch["step_count"], batch["value_target"])
    algo.loss.value_estimator(batch)
    torch.testing.assert_close(batch["advantage"], torch.zeros_like(batch["advantage"]))


def test_reinforce_runs_with_renamed_keys(tmp_path):
    run = tmp_path / "run"
    train(compose([*TINY_RF, "keys.particles=bx", "keys.log_weights=bw", "trainer.iterations=2",
                   f"output_dir={run}"]), progress=False)
    state = load_checkpoint(run)["trainer_state"]
    assert state["iteration"] == 2 and all(h["episodes"] == 4 for h in state["history"])
    assert all(math.isfinite(h["loss_actor"]) for h in state["history"])
