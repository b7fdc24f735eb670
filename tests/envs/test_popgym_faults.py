"""POPGym's tasks refuse a mistake with one line naming the config key, the argument or the action, and
say the fix: model values out of range, a filter's model whose observation noise is not the task's it
filters, model keys given to ``env=popgym`` (which has no model), a seed that is not an int, and actions
outside a task's action space, in the model's simulator and in POPGym's own env (where a NaN torque
used to step into NaN observations and an out-of-range index failed an ``assert`` inside POPGym). The
cases that need the ``popgym`` package skip without it."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import config_error, one_line_error
from escort_rl.config import ConfigError, compose
from escort_rl.envs import POMDPEnv
from escort_rl.envs.popgym import popgym_model
from escort_rl.models import POPGymPendulum
from escort_rl.trainers.builders import build_model
from escort_rl.trainers.validation import validate_train_config

CARTPOLE = "env=popgym_cartpole"
BELIEF_PPO = ["trainer=ppo", "filter=sir", "trainer.critic_input=belief", "trainer.warm_start_iterations=0",
              "trainer.warm_start_filter=null", "trainer.exploring_starts=false"]



def validation_error(overrides) -> str:
    return one_line_error(lambda: validate_train_config(compose(overrides)), ConfigError)


# ---------------------------------------------------------------------------------------------
# The env group's keys (no popgym needed)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("overrides, expected", [
    (["env.model.obs_noise=-0.1"], "config: env.model.obs_noise: must be >= 0, got -0.1"),
    (["env.model.obs_noise=high"], "config: env.model.obs_noise: expected a number, got 'high'"),
    (["env.model.max_episode_length=0"], "config: env.model.max_episode_length: must be >= 1, got 0"),
    (["env.model.obs_noise_floor=-1"], "config: env.model.obs_noise_floor: must be >= 0, got -1.0"),
    (["env.simulator.foo=1"], "config: unknown key 'env.simulator.foo'; check the spelling"),
], ids=["negative-noise", "noise-not-a-number", "zero-episode-length", "negative-noise-floor", "unknown-simulator-key"])
def test_a_model_value_out_of_range_is_named_while_composing(overrides, expected):
    assert config_error([CARTPOLE, *overrides]).startswith(expected)


def test_a_negative_simulator_noise_is_named_before_training():
    assert validation_error([CARTPOLE, *BELIEF_PPO, "env.simulator.process_noise=-1"]) == (
        "env.simulator.process_noise: must be >= 0, got -1.0")


def test_a_filter_model_without_process_noise_is_named_with_the_fix():
    """POPGym's dynamics are deterministic: the filters' model needs a process noise for a density."""
    message = one_line_error(lambda: build_model(compose([CARTPOLE, "env.model.process_noise=0"]).env), ConfigError)
    assert message.startswith("env.model: model.transition_log_prob(s_next, s, a): raised ValueError: "
                              "POPGymCartPole.process_noise: is 0"), message
    assert "a filter needs process_noise > 0" in message


@pytest.mark.parametrize("task, noise, assumed", [
    ("NoisyPositionOnlyCartPoleEasy", "0.1", "0.3"),
    ("PositionOnlyCartPoleEasy", "0", "0.3"),
], ids=["easy-noise-filtered-as-hard", "stateless-filtered-as-noisy"])
def test_a_filter_model_with_another_noise_than_its_popgym_task_is_named(task, noise, assumed):
    """The config's default noise is Hard's (0.3): acting in Easy's env used to filter with the wrong
    observation model, silently."""
    assert validation_error([CARTPOLE, *BELIEF_PPO, f"env.popgym_task={task}"]) == (
        f"env.model.obs_noise: POPGym's {task} adds observation noise {noise}, but the filters' model assumes "
        f"{assumed}; set env.model.obs_noise={noise}")


def test_the_gru_in_popgyms_own_env_does_not_read_the_models_noise():
    validate_train_config(compose([CARTPOLE, "trainer=recurrent_ppo", "env.popgym_task=NoisyPositionOnlyCartPoleEasy"]))
    validate_train_config(compose([CARTPOLE, *BELIEF_PPO, "env.popgym_task=NoisyPositionOnlyCartPoleEasy",
                                   "env.model.obs_noise=0.1"]))


def test_a_task_name_in_the_wrong_case_is_named():
    message = validation_error([CARTPOLE, *BELIEF_PPO, "env.popgym_task=noisypositiononlycartpoleeasy"])
    assert message.startswith("env.popgym_task: unknown POPGym control task 'noisypositiononlycartpoleeasy'; choose "
                              "one of NoisyPositionOnlyCartPoleEasy"), message


# ---------------------------------------------------------------------------------------------
# The models (no popgym needed)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("make, kind, expected", [
    (lambda: popgym_model("NoisyPositionOnlyCartPoleEasy", noise=0.1), ConfigError,
     "POPGymCartPole: unknown parameter 'noise'; POPGymCartPole takes max_episode_length, obs_noise, obs_noise_floor, "
     "process_noise"),
    (lambda: popgym_model("NoisyPositionOnlyCartPoleEasy", process_noise=-0.1), ConfigError,
     "POPGymCartPole.process_noise: must be >= 0, got -0.1"),
    (lambda: POPGymPendulum.from_name("NoisyPositionOnlyCartPoleEasy"), ValueError,
     "name: unknown POPGym Pendulum task 'NoisyPositionOnlyCartPoleEasy'; choose one of"),
], ids=["misspelt-key", "negative-process-noise", "a-cartpole-task-for-the-pendulum"])
def test_a_bad_model_argument_is_named(make, kind, expected):
    assert one_line_error(make, kind).startswith(expected)


@pytest.mark.parametrize("task, action, expected", [
    ("NoisyPositionOnlyCartPoleEasy", torch.tensor([0, 2]), "action: values must lie in [0, 2), got min 0, max 2"),
    ("NoisyPositionOnlyPendulumEasy", torch.tensor([[3.0], [0.0]]),
     "action: real actions must lie in the box [model.action_low, model.action_high] = [[-2.0], [2.0]]"),
    ("NoisyPositionOnlyPendulumEasy", torch.tensor([0, 1]),
     "action: expected real actions (float32) of shape (2, 1) for a model with continuous actions, got dtype "
     "torch.int64"),
], ids=["cartpole-index-2", "pendulum-torque-3", "pendulum-integer-torque"])
def test_an_action_outside_the_task_is_refused_by_the_models_simulator(task, action, expected):
    env = POMDPEnv(popgym_model(task), batch_size=(2,), seed=0)
    td = env.reset()
    td["action"] = action
    assert one_line_error(lambda: env.step(td)).startswith(expected)


# ---------------------------------------------------------------------------------------------
# POPGym's own env (needs popgym)
# ---------------------------------------------------------------------------------------------


def test_model_keys_given_to_env_popgym_are_named():
    pytest.importorskip("popgym")
    assert validation_error(["env=popgym", "trainer=recurrent_ppo", "+env.model.obs_noise=0.3"]) == (
        "env.model.obs_noise: env=popgym has no model of the task (the GRU reads POPGym's own observations), so it "
        "would be ignored; drop it, or use env=popgym_cartpole or env=popgym_pendulum for a model with its keys")


@pytest.mark.parametrize("seed", ["abc", 1.7, True], ids=["string", "fraction", "bool"])
def test_a_seed_that_is_not_an_int_is_named(seed):
    pytest.importorskip("popgym")
    from escort_rl.envs.popgym import make_popgym_env

    assert one_line_error(lambda: make_popgym_env("PositionOnlyCartPoleEasy", seed=seed)) == (
        f"seed: expected an int or None, got {seed!r}")


@pytest.mark.parametrize("task, action, expected", [
    ("NoisyPositionOnlyPendulumEasy", torch.tensor([5.0]),
     "action: expected an element of Box(-2.0, 2.0, (1,), float32), got [5.0]; pass finite values inside the box"),
    ("NoisyPositionOnlyPendulumEasy", torch.tensor([math.nan]),
     "action: expected an element of Box(-2.0, 2.0, (1,), float32), got [nan]; pass finite values inside the box"),
    ("NoisyPositionOnlyCartPoleEasy", torch.tensor(3),
     "action: expected an element of Discrete(2), got 3; pass an integer index in [0, 2)"),
], ids=["pendulum-torque-5", "pendulum-nan-torque", "cartpole-index-3"])
def test_an_action_outside_the_task_is_refused_by_popgyms_own_env(task, action, expected):
    pytest.importorskip("popgym")
    from escort_rl.envs.popgym import make_popgym_env

    env = make_popgym_env(task, seed=0)
    td = env.reset()
    td["action"] = action
    assert one_line_error(lambda: env.step(td)).startswith(expected)
