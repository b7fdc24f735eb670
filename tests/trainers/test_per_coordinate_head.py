"""``actor.head=per_coordinate``: the policy's outputs from one network shared by the model's action groups
(``action_coordinates``), built from the config, trained, saved and loaded like the pooled head."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

import escort_rl
from conftest import tiny_overrides
from escort_rl.config import ConfigError, compose
from escort_rl.trainers.builders import build_model, build_policy
from escort_rl.trainers.training import train


def _belief(model, batch: int = 4, n: int = 16) -> TensorDict:
    particles = model.initial_belief((batch,), n, torch.Generator().manual_seed(0))
    return TensorDict({"particles": particles, "particle_log_weights": torch.zeros(batch, n)}, batch_size=[batch])


@pytest.mark.parametrize("env, shape", [("lightdark10d", ()), ("lightdark10d_continuous", (5,))])
def test_the_config_builds_a_group_head_for_light_dark(env, shape):
    cfg = compose([f"env={env}", "actor.head=per_coordinate", "actor.hidden=8"])
    model = build_model(cfg.env)
    actor, policy = build_policy(cfg, model)
    assert actor.groups.tolist() == [list(g) for g in model.action_coordinates]
    out = policy(_belief(model))
    assert out["action"].shape == (4, *shape)
    assert torch.isfinite(out["action_log_prob"]).all()


def test_a_model_without_action_coordinates_is_refused_naming_the_key():
    cfg = compose(["env=linear_gaussian", "actor.head=per_coordinate", "actor.hidden=8"])
    with pytest.raises(ConfigError, match=r"actor\.head=per_coordinate.*action_coordinates.*actor\.head=pooled"):
        build_policy(cfg, build_model(cfg.env))


def test_a_trained_group_head_loads_as_it_was_saved(tmp_path):
    run = tmp_path / "run"
    cfg = compose(tiny_overrides("trainer.iterations=1", "actor.head=per_coordinate", f"output_dir={run}"))
    train(cfg, progress=False)
    policy = escort_rl.load_policy(run)
    td = _belief(build_model(cfg.env))
    logits = policy(td)["logits"]
    assert logits.shape == (4, 10) and torch.isfinite(logits).all()
    assert policy.module[0].module.groups is not None


def test_auto_takes_the_groups_where_the_model_declares_them():
    for env, grouped in (("lightdark10d", True), ("linear_gaussian", False)):
        cfg = compose([f"env={env}", "actor.hidden=8"])
        assert cfg.actor.head == "auto"
        actor, _ = build_policy(cfg, build_model(cfg.env))
        assert (actor.groups is not None) == grouped, env


def test_a_saved_config_from_before_the_heads_has_the_pooled_head():
    from omegaconf import OmegaConf

    cfg = compose(["actor.hidden=8"])
    saved = OmegaConf.to_container(cfg)
    del saved["actor"]["head"], saved["actor"]["group_hidden"]
    actor, _ = build_policy(OmegaConf.create(saved), build_model(cfg.env))
    assert actor.groups is None
