"""PPO on continuous actions (env=lightdark10d_continuous): a short run trains and checkpoints, the
loaded policy acts with float actions inside the box, the scripted controller writes the clipped PD
signal, and the evaluation runs the trained, scripted and random policies."""

from __future__ import annotations

import json
import math

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

import escort_rl
from escort_rl.belief import SIRFilter
from escort_rl.config import compose
from escort_rl.envs import POMDPEnv
from escort_rl.models import LightDark10DContinuous
from escort_rl.planners import ScriptedBeliefController
from escort_rl.trainers.builders import build_model, build_policy, make_env
from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint
from escort_rl.trainers.loading import load_policy
from escort_rl.trainers.training import train
from escort_rl.transforms import BeliefTransform

TINY_PPO = ["trainer=ppo", "filter=sir", "trainer.num_envs=4", "trainer.rollout_steps=10", "env.max_steps=20",
            "num_particles=8", "actor.hidden=8", "trainer.minibatches=2", "trainer.epochs=2",
            "trainer.warm_start_filter=null", "trainer.checkpoint_every=1"]
CONTINUOUS = ["env=lightdark10d_continuous"]
ITERATIONS = 3  # 3 x 4 envs x 20 steps = 240 frames


def in_box(action: torch.Tensor, model) -> bool:
    return bool(((action >= model.action_low) & (action <= model.action_high)).all())


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A few hundred frames of PPO on the continuous env, shared by the tests that read the run."""
    out = tmp_path_factory.mktemp("ppo_continuous") / "run"
    cfg = compose([*TINY_PPO, *CONTINUOUS, f"trainer.iterations={ITERATIONS}", f"output_dir={out}"])
    assert train(cfg, progress=False) == out
    return out


def test_a_short_run_trains_and_checkpoints(run):
    assert resolve_checkpoint(run).exists()  # the newest intact checkpoint
    meta = load_checkpoint(run)
    state = meta["trainer_state"]
    assert state["iteration"] == ITERATIONS and state["frames"] == ITERATIONS * 4 * 20
    assert len(state["history"]) == ITERATIONS
    for record in state["history"]:
        for key in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "grad_norm"):
            assert math.isfinite(record[key]), (key, record)
    # the entropy is the clipped Gaussian's before the clip (the default actor.distribution): five scales of
    # about one half-width, 0.1, at the start; a few hundred frames move it little
    assert all(abs(r["entropy"] - 5 * math.log(0.1 * math.sqrt(2 * math.pi * math.e))) < 2.5 for r in state["history"])
    assert meta["config"]["env"]["name"] == "lightdark10d_continuous"
    # the checkpointed actor has the Gaussian head: 2 x action_dim outputs
    cfg = OmegaConf.create(meta["config"])
    actor, _ = build_policy(cfg, build_model(cfg.env))
    load_checkpoint(run, actor=actor)
    assert actor.n_actions == 10 and all(bool(torch.isfinite(p).all()) for p in actor.parameters())


@pytest.mark.parametrize("filter_overrides", [["filter=escort", "filter.num_steps=2", "filter.compile=false"],
                                              ["filter=enkf"]], ids=["escort", "enkf"])
def test_ppo_trains_on_other_filters_beliefs(tmp_path, filter_overrides):
    out = tmp_path / "run"
    cfg = compose([*TINY_PPO, *CONTINUOUS, *filter_overrides, "trainer.iterations=1", "env.max_steps=10",
                   "trainer.rollout_steps=5", f"output_dir={out}"])
    train(cfg, progress=False)
    record = load_checkpoint(out)["trainer_state"]["history"][-1]
    assert all(math.isfinite(record[k]) for k in ("loss_objective", "loss_critic", "entropy"))


def test_load_policy_acts_with_float_actions_in_the_box(run):
    cfg = OmegaConf.create(load_checkpoint(run)["config"])
    model = build_model(cfg.env)
    policy = load_policy(run)  # escort_rl.load_policy
    env = make_env(cfg, 3, seed=0)
    td = env.reset()
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        out = policy(td.clone())
    action = out["action"]
    assert action.shape == (3, 5) and action.dtype == torch.float32 and in_box(action, model)
    assert out["action_log_prob"].shape == (3,) and bool(torch.isfinite(out["action_log_prob"]).all())
    stepped = env.step(out)  # the env takes it
    assert bool(torch.isfinite(stepped["next", "particles"]).all())

    # the loaded policy is the checkpoint's actor: the same loc and scale, and the greedy action is
    # the mode's image, deterministic
    actor, _ = build_policy(cfg, model)
    load_checkpoint(run, actor=actor)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        a = policy(td.clone())
        b = policy(td.clone())
        params = actor(td["particles"], td["particle_log_weights"])
    torch.testing.assert_close(a["loc"], params[..., :5], rtol=0, atol=0)
    assert torch.equal(a["action"], b["action"]) and in_box(a["action"], model)

    # a rollout of the loaded policy in its env
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        rollout = make_env(cfg, 2, seed=1).rollout(6, policy, break_when_any_done=False)
    assert rollout["action"].shape == (2, 6, 5) and in_box(rollout["action"], model)


def test_scripted_controller_writes_the_clipped_pd_signal_on_the_belief_mean():
    model = LightDark10DContinuous()
    controller = ScriptedBeliefController(model)
    env = POMDPEnv(model, batch_size=(4,), seed=2, max_steps=10)
    from torchrl.envs import TransformedEnv

    belief_env = TransformedEnv(env, BeliefTransform(model, SIRFilter(), 16, seed=3))
    rollout = belief_env.rollout(10, controller, break_when_any_done=False)
    action = rollout["action"]
    assert action.shape == (4, 10, 5) and action.dtype == torch.float32 and in_box(action, model)

    def expected(particles, log_weights):
        w = torch.softmax(log_weights, -1).unsqueeze(-1)
        mean = (w * particles).sum(-2)
        u = (8.0 - mean[..., :5]) - 3.0 * mean[..., 5:]  # goal 8, gain_v 3 (the defaults)
        return u.clamp(-0.1, 0.1)

    torch.testing.assert_close(action, expected(rollout["particles"], rollout["particle_log_weights"]))

    # near the goal the signal is not saturated in every coordinate: beliefs around x = 8 ± 0.05,
    # v ∈ ±0.02, where u is inside the box in some coordinates and clipped in others
    g = torch.Generator().manual_seed(4)
    pos = 8.0 + 0.05 * torch.randn(6, 32, 5, generator=g)
    vel = 0.02 * torch.randn(6, 32, 5, generator=g)
    vel[:3, :, 0] = 0.2  # braking: u well below -0.1 in coordinate 0 of the first three beliefs
    particles = torch.cat([pos, vel], -1)
    log_weights = torch.randn(6, 32, generator=g)
    td = TensorDict({"particles": particles, "particle_log_weights": log_weights}, [6])
    out = controller(td)["action"]
    assert out.shape == (6, 5) and out.dtype == torch.float32
    want = expected(particles, log_weights)
    torch.testing.assert_close(out, want)
    unclipped = want.abs() < 0.1 - 1e-6
    assert bool(unclipped.any()) and bool((~unclipped).any())
    assert bool((out[:3, 0] == -0.1).all())


def test_scripted_controller_uses_its_gain_and_the_models_box():
    model = LightDark10DContinuous(force=0.5)
    particles = torch.zeros(2, 4, 10)
    particles[..., :5] = 7.9
    particles[0, :, 5:] = 0.01
    td = TensorDict({"particles": particles, "particle_log_weights": torch.zeros(2, 4)}, [2])
    out = ScriptedBeliefController(model, gain_v=2.0)(td)["action"]
    u = torch.tensor([[0.1 - 2.0 * 0.01] * 5, [0.1] * 5])
    torch.testing.assert_close(out, u)
    far = td.clone()
    far["particles"][..., :5] = 0.0  # far from the goal: the whole box's force, +0.5
    torch.testing.assert_close(ScriptedBeliefController(model)(far)["action"], torch.full((2, 5), 0.5))


def test_evaluation_of_the_continuous_run(run, tmp_path):
    result = escort_rl.evaluate(run, episodes=3, output=tmp_path / "ev")
    assert result["env"] == "lightdark10d_continuous" and result["trainer"] == "ppo"
    for row in ("trained", "scripted", "random"):
        m = result[row]
        assert m["episodes"] == 3, row
        for key in ("final_distance", "episode_return", "success_rate", "final_position_error"):
            assert m[key] is not None and math.isfinite(m[key]), (row, key)
        # 20 steps of -0.1·distance - 0.1 from [0, 2]^5, about 15.6 from the goal: a return near -33
        assert -60 < m["episode_return"] < 0, (row, m["episode_return"])
    for name in ("summary.md", "metrics.json", "learning_curve.png", "belief_projection.png"):
        assert (tmp_path / "ev" / name).stat().st_size > 0
    saved = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert saved["scripted"]["episodes"] == 3
    # the scripted controller pushes every coordinate toward the goal at full force: after 20 steps it
    # is closer than the random policy on the same seeded episodes
    assert result["scripted"]["final_distance"] < result["random"]["final_distance"]
    assert result["greedy"] is True  # the config's default: the clipped Gaussian's mean, in the box

    sampled = escort_rl.evaluate(run, episodes=2, output=tmp_path / "ev_sampled", greedy=False)
    assert sampled["greedy"] is False and math.isfinite(sampled["trained"]["episode_return"])
