"""Your own model, end to end: from a config (``env=custom env.model._target_=...``) and from Python
(``escort_rl.train(overrides, model=...)``), with and without a goal."""

from __future__ import annotations

import math

import pytest
import torch

import escort_rl
from conftest import tiny_overrides
from escort_rl.config import ConfigError, compose
from escort_rl.models import LinearGaussian
from escort_rl.trainers.builders import build_model

LINEAR = ["env=custom", "env.model._target_=escort_rl.models.LinearGaussian", "+env.model.state_dim=2"]
"""A package model named by its class, as a user's own would be: it has no goal (no distance_to_goal)."""
TINY_PPO = ["trainer=ppo", "trainer.iterations=2", "trainer.warm_start_iterations=1", "trainer.num_envs=4",
            "trainer.rollout_steps=10", "trainer.minibatches=2", "trainer.epochs=1", "env.max_steps=10"]


def test_a_model_named_by_its_class_is_built_with_its_keyword_arguments():
    model = build_model(compose(LINEAR).env)
    assert isinstance(model, LinearGaussian) and model.state_dim == 2


def test_a_custom_env_without_its_class_or_with_a_non_model_is_refused_by_name():
    with pytest.raises(ConfigError, match=r"^env\.model\._target_: missing"):
        build_model(compose(["env=custom"]).env)
    with pytest.raises(ConfigError, match=r"^env\.model\._target_: cannot import 'no_such\.Model'$"):
        build_model(compose(["env=custom", "env.model._target_=no_such.Model"]).env)
    with pytest.raises(ConfigError, match=r"^env\.model: model\.state_dim: expected an int attribute on object"):
        build_model(compose(["env=custom", "env.model._target_=builtins.object"]).env)


def test_a_goalless_model_from_config_trains_and_evaluates_with_its_return(tmp_path):
    run = escort_rl.train(tiny_overrides(*LINEAR, *TINY_PPO, f"output_dir={tmp_path / 'run'}"), progress=False)
    result = escort_rl.evaluate(run, episodes=3)
    for row in ("trained", "random"):
        assert result[row]["success_rate"] is None and result[row]["final_distance"] is None
        assert math.isfinite(result[row]["episode_return"]) and result[row]["episode_return"] < 0
    assert "scripted" not in result  # no scripted controller for a model the package does not know
    assert "| trained | — | — |" in (run / "evaluation" / "summary.md").read_text()


def test_a_model_object_trains_and_is_rebuilt_from_its_run(tmp_path):
    run_dir = tmp_path / "run"
    overrides = tiny_overrides(*TINY_PPO, f"output_dir={run_dir}")
    run = escort_rl.train(overrides, model=LinearGaussian(state_dim=3, obs_std=0.3), progress=False)
    assert run == run_dir and (run / "model.pt").is_file()
    from omegaconf import OmegaConf

    saved = OmegaConf.load(run / "config.yaml")
    assert saved.env.name == "custom" and saved.env.model._target_ == "escort_rl.models.saved.load_saved_model"
    rebuilt = build_model(saved.env)
    assert isinstance(rebuilt, LinearGaussian) and rebuilt.state_dim == 3 and rebuilt.obs_std == 0.3
    policy = escort_rl.load_policy(run)
    out = policy(policy_input(rebuilt))
    assert out["action"].shape == (5,)

    # another model into the same folder is another run: refused, and model.pt is left alone
    before = (run / "model.pt").read_bytes()
    with pytest.raises(ConfigError, match=r"^output_dir: .* already holds another run .*env\.model\.sha256"):
        escort_rl.train(overrides, model=LinearGaussian(state_dim=3, obs_std=0.9), progress=False)
    assert (run / "model.pt").read_bytes() == before

    # a damaged model file is detected, not loaded
    (run / "model.pt").write_bytes(before[:-7] + b"damaged")
    with pytest.raises(ConfigError, match=r"^env\.model\.path: .* is damaged"):
        build_model(saved.env)


def test_a_run_with_a_model_object_moves_with_its_folder(tmp_path):
    """The run reads its own model.pt where the run is now: moved, it loads, evaluates and resumes."""
    import shutil

    first = tmp_path / "first"
    escort_rl.train(tiny_overrides(*TINY_PPO, f"output_dir={first}"), model=LinearGaussian(state_dim=3, obs_std=0.3),
                    progress=False)
    moved = tmp_path / "moved"
    shutil.move(first, moved)
    assert not first.exists()
    policy = escort_rl.load_policy(moved)
    assert policy(policy_input(LinearGaussian(state_dim=3)))["action"].shape == (5,)
    assert escort_rl.evaluate(moved, episodes=2)["trained"]["episode_return"] is not None
    resumed = escort_rl.train([f"resume={moved}", "trainer.iterations=3"], progress=False)
    assert resumed == moved and not first.exists()


def policy_input(model):
    from tensordict import TensorDict

    particles = torch.randn(5, 16, model.state_dim)
    return TensorDict({"particles": particles, "particle_log_weights": torch.zeros(5, 16)}, batch_size=[5])


def test_a_model_object_needs_env_custom_and_the_protocol():
    with pytest.raises(ConfigError, match=r"^model: a model object replaces .* only with env=custom"):
        escort_rl.train(["env=lightdark10d"], model=LinearGaussian())
    with pytest.raises(ConfigError, match=r"^model\.state_dim: expected an int attribute on object"):
        escort_rl.train([], model=object())
    with pytest.raises(ConfigError, match=r"^model: a resumed run rebuilds the model it saved"):
        escort_rl.train(["resume=somewhere"], model=LinearGaussian())
