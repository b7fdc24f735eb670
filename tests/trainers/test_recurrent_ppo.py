"""Recurrent PPO (escort_rl.trainers.recurrent_ppo, escort_rl.modules.recurrent): the GRU's hidden
state through ParallelEnv and a collector, per-env partial resets, recurrent mode against stepping,
and a tiny training run with exact resume."""

import math
from functools import partial

import pytest
import torch
from omegaconf import OmegaConf
from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv, SerialEnv
from torchrl.modules import set_recurrent_mode

from escort_rl.config import ConfigError, compose
from escort_rl.modules.recurrent import RECURRENT_KEY
from escort_rl.trainers.builders import build_model
from escort_rl.trainers.checkpointing import load_checkpoint
from escort_rl.trainers.recurrent_ppo import (
    RecurrentPPO,
    build_recurrent_actor_critic,
    make_recurrent_env,
    make_recurrent_ppo_loss,
    observation_scaling,
)
from escort_rl.trainers.scaffold import run_training

TINY = ["trainer.num_envs=4", "trainer.rollout_steps=6", "env.max_steps=12", "trainer.minibatches=2",
        "trainer.epochs=2", "trainer.checkpoint_every=1"]
HIDDEN = 8


def tiny_cfg(*overrides: str, hidden: int = HIDDEN):
    """The tiny recurrent-PPO config, as a plain (untyped) config. ``trainer=recurrent_ppo`` needs its
    schema in escort_rl/config/schema.py; until it is there, the PPO config with the recurrent keys added."""
    try:
        cfg = compose(["trainer=recurrent_ppo", *TINY, *overrides])
    except ConfigError:
        cfg = compose(["trainer=ppo", *TINY, *overrides])
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    cfg.trainer.algorithm = "recurrent_ppo"
    cfg.trainer.hidden = hidden
    return cfg


def test_observation_scaling_takes_the_position_part():
    cfg = tiny_cfg()
    loc, scale = observation_scaling(cfg, build_model(cfg.env))
    assert loc == [8.0] * 5 and scale == [2.0] * 5  # Light-Dark 10D observes its 5-D position
    mtt = tiny_cfg("env=mtt20d")
    loc, scale = observation_scaling(mtt, build_model(mtt.env))
    assert loc == [0.0] * 14 and scale == [1.0] * 14  # not a slice of the state: left as is


def test_the_env_carries_the_policys_primer_and_draws_nothing_from_torch():
    cfg = tiny_cfg()
    _, _, primer = build_recurrent_actor_critic(cfg, build_model(cfg.env))
    torch.manual_seed(3)
    expected = torch.rand(3)
    torch.manual_seed(3)
    env = make_recurrent_env(cfg, 2, seed=0)
    assert torch.equal(torch.rand(3), expected)  # a collector built mid-run leaves the run's draws alone
    td = env.reset()
    assert td[RECURRENT_KEY].shape == (2, 1, HIDDEN) and (td[RECURRENT_KEY] == 0).all()
    assert td["is_init"].all()
    assert primer.primers[RECURRENT_KEY].shape == env.transform[-1].primers[RECURRENT_KEY].shape[-2:]
    env.close()


# ------------------------------------------------------------- (a) the hidden state in ParallelEnv
def _collect_one(env, policy, frames: int):
    collector = Collector(env, policy, frames_per_batch=frames, total_frames=-1, auto_register_policy_transforms=False)
    try:
        iterator = iter(collector)
        torch.manual_seed(0)  # the policy samples its actions in this process: the same draws for both
        return next(iterator).clone()
    finally:
        collector.shutdown()


@pytest.mark.slow
def test_the_hidden_state_survives_parallel_env_and_a_collector():
    cfg = tiny_cfg("env.max_steps=4")  # episodes restart inside the batch
    policy, _, _ = build_recurrent_actor_critic(cfg, build_model(cfg.env))
    factories = [partial(make_recurrent_env, cfg, 2, 11), partial(make_recurrent_env, cfg, 2, 12)]
    steps = 7
    single = _collect_one(SerialEnv(2, factories), policy, 4 * steps)  # one process
    parallel = _collect_one(ParallelEnv(2, factories, mp_start_method="spawn"), policy, 4 * steps)
    assert parallel.shape == (2, 2, steps)
    h, h_next = parallel[RECURRENT_KEY], parallel["next", RECURRENT_KEY]  # [2, 2, T, 1, H]
    is_init = parallel["is_init"].squeeze(-1)
    assert is_init[..., 0].all() and is_init[..., 4].all() and not is_init[..., 1:4].any()
    # zero where an episode starts, non-zero after its first step
    assert (h[is_init] == 0).all()
    assert (h[~is_init].abs().amax(-1).amax(-1) > 0).all()
    # carried: the state a step reads is the one the previous step wrote
    carried = ~is_init[..., 1:]
    assert torch.equal(h[..., 1:, :, :][carried], h_next[..., :-1, :, :][carried])
    # and it is exactly what the single-process run gives
    for key in ("observation", "action", "action_log_prob", RECURRENT_KEY, ("next", RECURRENT_KEY)):
        assert torch.equal(single[key], parallel[key]), key


# ------------------------------------------------------------------- (b) partial resets
def test_a_partial_reset_zeroes_only_that_envs_hidden_state():
    cfg = tiny_cfg()
    policy, _, _ = build_recurrent_actor_critic(cfg, build_model(cfg.env))
    env = make_recurrent_env(cfg, 2, seed=0)
    torch.manual_seed(0)
    with torch.no_grad():
        td = env.reset()
        for _ in range(3):
            _, td = env.step_and_maybe_reset(policy(td))
        kept = td[RECURRENT_KEY][1].clone()
        assert (td[RECURRENT_KEY].abs().amax(-1) > 0).all()
        td["_reset"] = torch.tensor([[True], [False]])
        td = env.reset(td)
        assert td["is_init"].squeeze(-1).tolist() == [True, False]
        assert (td[RECURRENT_KEY][0] == 0).all()
        assert torch.equal(td[RECURRENT_KEY][1], kept)
        assert int(td["step_count"][0]) == 0 and int(td["step_count"][1]) == 3
        # the next step starts env 0 afresh: the same GRU output as an env at its first step
        out = policy(td.clone())
        fresh = td.clone()
        fresh[RECURRENT_KEY] = torch.zeros_like(fresh[RECURRENT_KEY])
        fresh["is_init"] = torch.ones_like(fresh["is_init"])
        fresh = policy(fresh)
        torch.testing.assert_close(out["next", RECURRENT_KEY][0], fresh["next", RECURRENT_KEY][0])
        assert not torch.allclose(out["next", RECURRENT_KEY][1], fresh["next", RECURRENT_KEY][1])
    env.close()


# ------------------------------------------------------- (c) recurrent mode equals stepping
def test_recurrent_mode_gives_the_log_probs_and_values_of_stepping():
    cfg = tiny_cfg("env.max_steps=5")
    policy, value, _ = build_recurrent_actor_critic(cfg, build_model(cfg.env))
    env = make_recurrent_env(cfg, 3, seed=1)
    torch.manual_seed(0)
    with torch.no_grad():
        rollout = env.rollout(14, policy, break_when_any_done=False)
    env.close()
    # rows start mid-episode (a non-zero stored hidden state) and restart inside (is_init)
    batch = rollout[:, 3:].clone()
    batch.names = [None, "time"]
    e, t = batch.shape
    assert not batch["is_init"][:, 0].any() and batch["is_init"][:, 1:].any()
    assert (batch[RECURRENT_KEY][:, 0].abs().amax(-1) > 0).all()

    with set_recurrent_mode(True), torch.no_grad():
        dist = policy.get_dist(batch.select("observation", "is_init", RECURRENT_KEY).clone())
        log_prob = dist.log_prob(batch["action"])
        state_value = value(batch.select("observation", "is_init", RECURRENT_KEY).clone())["state_value"]
    assert log_prob.shape == (e, t)
    torch.testing.assert_close(log_prob, batch["action_log_prob"], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(dist.logits, torch.log_softmax(batch["logits"], -1), rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        stepped = torch.stack([value(batch[:, i].select("observation", "is_init", RECURRENT_KEY).clone())["state_value"]
                               for i in range(t)], 1)
    torch.testing.assert_close(state_value, stepped, rtol=1e-5, atol=1e-5)

    # GAE in recurrent mode: V(s_t) and V(s_{t+1}) as stepping gives them
    loss = make_recurrent_ppo_loss(policy, value, cfg)
    with set_recurrent_mode(True), torch.no_grad():
        loss.value_estimator(batch)
    torch.testing.assert_close(batch["state_value"], stepped, rtol=1e-5, atol=1e-5)
    nxt = batch["next"].select("observation", RECURRENT_KEY)
    nxt["is_init"] = torch.zeros(e, t, 1, dtype=torch.bool)
    with torch.no_grad():
        next_stepped = torch.stack([value(nxt[:, i].clone())["state_value"] for i in range(t)], 1)
    torch.testing.assert_close(batch["next", "state_value"], next_stepped, rtol=1e-5, atol=1e-5)
    # the PPO loss on the fresh batch: the probability ratio is one, nothing is clipped
    with set_recurrent_mode(True):
        out = loss(batch.clone())
    assert float(out["clip_fraction"]) == 0.0
    assert abs(float(out["kl_approx"])) < 1e-6


# ------------------------------------------------------------ (d) training and exact resume
def _params(run, cfg) -> dict:
    policy, value, _ = build_recurrent_actor_critic(cfg, build_model(cfg.env))
    load_checkpoint(run, actor=policy, critic=value)
    return {**{f"a.{k}": v for k, v in policy.state_dict().items()},
            **{f"c.{k}": v for k, v in value.state_dict().items()}}


def _train(cfg, resume_state=None):
    """What ``escort_rl.trainers.training.train`` does for this algorithm."""
    torch.manual_seed(int(cfg.seed))  # the networks' initial weights
    return run_training(cfg, RecurrentPPO(cfg, build_model(cfg.env)), resume_state=resume_state, progress=False)


def test_recurrent_ppo_trains_and_resumes_exactly(tmp_path):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    _train(tiny_cfg("trainer.iterations=2", f"output_dir={straight}"))
    _train(tiny_cfg("trainer.iterations=1", f"output_dir={resumed}"))
    _train(tiny_cfg("trainer.iterations=2", f"output_dir={resumed}"), resume_state={"path": str(resumed)})
    state = load_checkpoint(straight)["trainer_state"]
    assert state["iteration"] == 2 and state["frames"] == 2 * 4 * 12
    for record in state["history"]:
        assert all(math.isfinite(record[k]) for k in ("loss_objective", "loss_critic", "loss_entropy", "entropy"))
        assert record["episodes"] == 4  # one full episode per env per iteration
    cfg = tiny_cfg()
    a, b = _params(straight, cfg), _params(resumed, cfg)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    ha = load_checkpoint(straight)["trainer_state"]["history"]
    hb = load_checkpoint(resumed)["trainer_state"]["history"]
    assert [h["episode_return"] for h in ha] == [h["episode_return"] for h in hb]
    assert [h["loss_objective"] for h in ha] == [h["loss_objective"] for h in hb]


@pytest.mark.slow
def test_recurrent_ppo_runs_on_a_multi_sync_collector(tmp_path):
    cfg = tiny_cfg("trainer.iterations=1", "collector.workers=2", f"output_dir={tmp_path / 'run'}")
    _train(cfg)
    record = load_checkpoint(tmp_path / "run")["trainer_state"]["history"][0]
    assert record["frames"] == 4 * 12 and record["episodes"] == 4
    assert math.isfinite(record["loss_objective"]) and math.isfinite(record["loss_critic"])


def test_minibatches_are_whole_rows_and_warm_start_is_refused():
    model = build_model(tiny_cfg().env)
    with pytest.raises(ConfigError, match="trainer.minibatches"):
        RecurrentPPO(tiny_cfg("trainer.minibatches=5"), model)
    with pytest.raises(ConfigError, match="trainer.warm_start_filter"):
        RecurrentPPO(tiny_cfg("trainer.warm_start_filter=sir", "trainer.warm_start_iterations=1"), model)
