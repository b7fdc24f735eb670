"""DVRL trained by A2C plus its ELBO (escort_rl.trainers.dvrl_a2c): the loss, the loop, resume, evaluation."""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict

from escort_rl.config import ConfigError, compose
from escort_rl.modules.dvrl_networks import StateReadout
from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint
from escort_rl.trainers.dvrl_a2c import a2c_loss, build_dvrl_policy, window_returns
from escort_rl.trainers.training import algorithm, train

SMALL = ["trainer=dvrl_a2c", "trainer.num_envs=4", "env.max_steps=30", "dvrl.module.num_particles=16",
         "dvrl.module.hidden=16", "dvrl.module.encoding_dim=16", "dvrl.module.summary_dim=16",
         "dvrl.loss.bptt_steps=10", "evaluate.episodes=3"]


def _cfg(tmp_path, *extra):
    return compose([*SMALL, f"output_dir={tmp_path}", *extra])


def test_window_returns_hand_example():
    reward = torch.tensor([[1.0, 2.0, 3.0]])
    done = torch.tensor([[False, True, False]])
    out = window_returns(reward, done, bootstrap=torch.tensor([10.0]), gamma=0.5)
    # R2 = 3 + 0.5*10 = 8; R1 = 2 (done: no bootstrap past it); R0 = 1 + 0.5*2 = 2
    assert torch.allclose(out, torch.tensor([[2.0, 2.0, 8.0]]))


def test_a2c_loss_pushes_toward_advantaged_actions_and_up_the_elbo():
    torch.manual_seed(0)
    b, t, a = 4, 6, 3
    logits = torch.zeros(b, t, a, requires_grad=True)
    value = torch.zeros(b, t, 1, requires_grad=True)
    elbo = torch.zeros(b, t, requires_grad=True)
    action = torch.randint(0, a, (b, t))
    reward = (action == 0).float().unsqueeze(-1)  # action 0 pays
    window = TensorDict({"logits": logits, "state_value": value, "dvrl_elbo": elbo, "action": action,
                         ("next", "reward"): reward, ("next", "done"): torch.zeros(b, t, 1, dtype=torch.bool)},
                        batch_size=[b, t])
    loss, terms = a2c_loss(window, torch.zeros(b), gamma=0.0, entropy_coef=0.0, value_loss_coef=0.5,
                           encoding_loss_coef=0.3)
    loss.backward()
    assert set(terms) == {"policy_loss", "value_loss", "entropy", "elbo"}
    # descending the loss raises the logit of the action taken where it paid (positive advantage)
    # and lowers it where it did not
    step = -logits.grad
    taken = step.gather(-1, action.unsqueeze(-1)).squeeze(-1)
    assert (taken[action == 0] > 0).all() and (taken[action != 0] < 0).all()
    assert torch.allclose(elbo.grad, torch.full_like(elbo, -0.3 / (b * t)))  # -c_enc * mean(ELBO)
    assert (value.grad.squeeze(-1)[action == 0] < 0).all()  # value rises toward the positive return


def test_a2c_loss_uses_raw_advantages_when_asked():
    """Without normalisation the policy loss is ``−mean(log π(a) · (R − V))`` with the raw advantage."""
    torch.manual_seed(0)
    b, t, a = 3, 4, 2
    logits = torch.randn(b, t, a)
    value = torch.randn(b, t, 1)
    action = torch.randint(0, a, (b, t))
    reward = torch.rand(b, t, 1)
    window = TensorDict({"logits": logits, "state_value": value, "action": action, ("next", "reward"): reward,
                         ("next", "done"): torch.zeros(b, t, 1, dtype=torch.bool)}, batch_size=[b, t])
    _, raw = a2c_loss(window, torch.zeros(b), gamma=0.0, entropy_coef=0.0, value_loss_coef=0.0,
                      encoding_loss_coef=0.0, elbo_key=None, normalize_advantage=False)
    log_pi = torch.distributions.Categorical(logits=logits).log_prob(action)
    want = -(log_pi * (reward.squeeze(-1) - value.squeeze(-1))).mean()
    assert raw["policy_loss"] == pytest.approx(float(want), rel=1e-5)
    _, normed = a2c_loss(window, torch.zeros(b), gamma=0.0, entropy_coef=0.0, value_loss_coef=0.0,
                         encoding_loss_coef=0.0, elbo_key=None)
    assert normed["policy_loss"] != pytest.approx(raw["policy_loss"])


def test_readout_fits_in_standardised_units_and_answers_in_state_units():
    readout = StateReadout(4, 2, hidden=8, loc=4.0, scale=2.0)
    summary = torch.randn(5, 4)
    target = readout(summary).detach()
    assert readout.loss(summary, target) < 1e-10
    assert torch.allclose(readout.loss(summary, target + 2.0), torch.tensor(1.0))  # 2 units = 1 scale
    with pytest.raises(ValueError, match="scale"):
        StateReadout(4, 2, scale=0.0)


def test_short_run_raises_the_elbo_and_fits_the_readout(tmp_path):
    cfg = _cfg(tmp_path, "trainer.iterations=8", "trainer.lr=0.003", "trainer.readout_lr=0.01")
    assert algorithm(cfg) == "dvrl_a2c"
    history = json.loads((train(cfg, progress=False) / "history.json").read_text())
    assert [h["frames"] for h in history] == [4 * 30 * (i + 1) for i in range(8)]
    first, last = history[:2], history[-2:]
    mean = lambda rows, k: sum(r[k] for r in rows) / len(rows)  # noqa: E731
    assert mean(last, "elbo") > mean(first, "elbo") + 1.0  # the model learns the observations
    assert mean(last, "readout_loss") < 0.5 * mean(first, "readout_loss")
    assert all(math.isfinite(h["policy_loss"]) and h["episodes"] == 4 for h in history)


def test_partial_resets_mid_window(tmp_path):
    # success radius 100: every episode ends after one step, so every step resets every env, inside
    # every BPTT window; the loop must carry on with fresh particles and count each episode
    cfg = _cfg(tmp_path, "trainer.iterations=1", "env.model.success_radius=100.0")
    history = json.loads((train(cfg, progress=False) / "history.json").read_text())
    assert history[0]["episodes"] == 4 * 30 and history[0]["success_rate"] == 1.0
    assert math.isfinite(history[0]["elbo"])


def test_resumed_run_equals_an_uninterrupted_one(tmp_path):
    whole = _cfg(tmp_path / "whole", "trainer.iterations=3", "trainer.checkpoint_every=1")
    train(whole, progress=False)
    part = _cfg(tmp_path / "part", "trainer.iterations=2", "trainer.checkpoint_every=1")
    train(part, progress=False)
    saved = load_checkpoint(resolve_checkpoint(tmp_path / "part"))
    cont = _cfg(tmp_path / "part", "trainer.iterations=3", "trainer.checkpoint_every=1")
    train(cont, resume_state=saved, progress=False)
    a = json.loads((tmp_path / "whole" / "history.json").read_text())
    b = json.loads((tmp_path / "part" / "history.json").read_text())
    assert [h["episode_return"] for h in a] == [h["episode_return"] for h in b]
    assert [h["elbo"] for h in a] == pytest.approx([h["elbo"] for h in b], rel=1e-5)


def test_evaluate_reports_the_readout_position_error(tmp_path):
    from escort_rl.trainers.evaluate import evaluate

    run = train(_cfg(tmp_path, "trainer.iterations=1"), progress=False)
    result = evaluate(run)
    assert result["filter"] == "dvrl (learned belief)" and result["trained"]["episodes"] == 3
    err = result["trained"]["final_position_error"]
    assert math.isfinite(err) and err > 0
    assert (tmp_path / "evaluation" / "summary.md").is_file()


def test_config_errors_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="dvrl.loss.bptt_steps"):
        train(_cfg(tmp_path, "dvrl.loss.bptt_steps=0"), progress=False)
    with pytest.raises(ConfigError, match="dvrl.loss.reward_scale"):
        train(_cfg(tmp_path, "dvrl.loss.reward_scale=0"), progress=False)
    with pytest.raises(ConfigError, match="collector.workers"):
        train(_cfg(tmp_path, "collector.workers=2"), progress=False)
    with pytest.raises(ConfigError, match="dvrl="):
        train(_cfg(tmp_path, "dvrl=mtt20d"), progress=False)
    with pytest.raises(ConfigError, match="trainer.algorithm"):
        algorithm(_cfg(tmp_path, "trainer.algorithm=ppo"))


def test_every_domain_builds_its_dvrl_policy():
    from escort_rl.trainers.builders import build_model

    for domain in ("lightdark10d", "kidnapped20d", "mtt20d"):
        cfg = compose([f"env={domain}", "trainer=dvrl_a2c"])
        model = build_model(cfg.env)
        policy = build_dvrl_policy(cfg, model)
        assert policy.readout is not None and policy.dvrl.latent_dim == cfg.dvrl.module.latent_dim
