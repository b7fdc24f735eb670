"""Training in POPGym's own env (``env.popgym_task``: TorchRL's ``GymEnv``) and in the model's
simulator, and the refusals that go with the task."""

import math

import pytest

pytest.importorskip("popgym")

from escort_rl.config import ConfigError, compose  # noqa: E402
from escort_rl.trainers.training import train  # noqa: E402
from escort_rl.trainers.validation import validate_train_config  # noqa: E402

TINY = ["trainer.num_envs=2", "trainer.iterations=1", "num_particles=8", "actor.hidden=8"]
BELIEF_PPO = ["trainer=ppo", "filter=sir", "trainer.critic_input=belief", "trainer.warm_start_iterations=0",
              "trainer.warm_start_filter=null", "trainer.exploring_starts=false"]


@pytest.mark.parametrize("overrides", [
    ["env=popgym_pendulum", "env.popgym_task=NoisyPositionOnlyPendulumHard", "trainer=recurrent_ppo",
     "trainer.minibatches=2"],
    ["env=popgym_cartpole", "env.popgym_task=NoisyPositionOnlyCartPoleEasy", "env.model.obs_noise=0.1", *BELIEF_PPO],
], ids=["gru-pendulum-gym", "belief-ppo-cartpole-gym"])
def test_training_in_popgyms_own_env(tmp_path, overrides):
    from escort_rl.trainers.checkpointing import load_checkpoint

    run = train(compose([*overrides, *TINY, f"output_dir={tmp_path / 'run'}"]), progress=False)
    history = load_checkpoint(run)["trainer_state"]["history"]
    assert history[-1]["frames"] >= 2 * 200  # one iteration: at least an episode of 200 steps per env
    ret = history[-1]["episode_return"]
    assert math.isnan(ret) or -1.0 - 1e-5 <= ret <= 1.0 + 1e-5  # POPGym's scaled returns


@pytest.mark.parametrize("overrides,field", [
    (["env=popgym_cartpole", "env.popgym_task=NoisyPositionOnlyPendulumEasy", *BELIEF_PPO], "env.popgym_task"),
    (["env=popgym_cartpole", "env.popgym_task=Pong", *BELIEF_PPO], "env.popgym_task"),
    (["env=popgym_cartpole", "env.popgym_task=PositionOnlyCartPoleHard", *BELIEF_PPO], "env.max_steps"),
    (["env=popgym_cartpole", "env.popgym_task=NoisyPositionOnlyCartPoleEasy", "trainer=dvrl_a2c"], "env.popgym_task"),
    (["env=popgym_cartpole", "env.popgym_task=NoisyPositionOnlyCartPoleEasy", "trainer=ppo",
      "trainer.critic_input=state"], "env.popgym_task"),
])
def test_a_task_that_does_not_fit_is_named(overrides, field):
    with pytest.raises(ConfigError, match=f"^{field}"):
        validate_train_config(compose(overrides))


GRU_ANY = ["env=popgym", "trainer=recurrent_ppo", "trainer.minibatches=2", *TINY]


@pytest.mark.parametrize("task,steps", [("RepeatPreviousEasy", 51), ("BattleshipEasy", 64)])
def test_the_gru_trains_on_a_memory_game(tmp_path, task, steps):
    """``env=popgym``: the GRU trains on a task no model here knows (one-hot observations; Battleship's
    multi-discrete shot as one action), and evaluation runs it beside random in the same env, with no
    scripted controller and no position error."""
    from escort_rl.trainers.checkpointing import load_checkpoint
    from escort_rl.trainers.evaluate import evaluate

    run = train(compose([*GRU_ANY, f"env.popgym_task={task}", f"env.max_steps={steps}",
                         f"output_dir={tmp_path / 'run'}"]), progress=False)
    history = load_checkpoint(run)["trainer_state"]["history"]
    assert history[-1]["frames"] >= 2 * steps
    result = evaluate(run, episodes=2, output=tmp_path / "eval")
    assert set(result) >= {"trained", "random"} and "scripted" not in result
    for row in ("trained", "random"):
        assert math.isnan(result[row]["final_position_error"])
        assert math.isfinite(result[row]["episode_return"])  # Battleship's repeated shots can pass -1


@pytest.mark.parametrize("overrides,field", [
    (["env=popgym", "trainer=ppo"], "trainer"),
    (["env=popgym", "trainer=dvrl_a2c"], "trainer"),
    (["env=popgym", "trainer=recurrent_ppo", "env.max_steps=20"], "env.max_steps"),
    (["env=popgym", "trainer=recurrent_ppo", "env.popgym_task=Pong"], "env.popgym_task"),
    (["env=popgym", "trainer=recurrent_ppo", "env.popgym_task=null"], "env.popgym_task"),
])
def test_what_env_popgym_cannot_do_is_named(overrides, field):
    with pytest.raises(ConfigError, match=f"^{field}"):
        validate_train_config(compose(overrides))
