"""ActionRepeat (escort_rl.transforms): a decision of k env steps equals k single steps with the
same action (belief included), rewards are summed, and an env that finishes inside a decision keeps
the step where it finished."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from escort_rl.belief import SIRFilter
from escort_rl.envs import POMDPEnv
from escort_rl.models import LightDark10D
from escort_rl.transforms import ActionRepeat, BeliefTransform, action_repeat_of


def _env(repeat: int, max_steps: int = 50, envs: int = 3, seed: int = 0) -> TransformedEnv:
    model = LightDark10D()
    belief = BeliefTransform(model, SIRFilter(), 16)
    env = TransformedEnv(POMDPEnv(model, batch_size=(envs,), seed=seed, max_steps=max_steps, expose_state=True),
                         Compose(belief, ActionRepeat(repeat)) if repeat > 1 else belief)
    env.set_seed(seed)
    return env


def _actions(decisions: int, envs: int = 3) -> torch.Tensor:
    return torch.randint(0, 10, (decisions, envs), generator=torch.Generator().manual_seed(7))


def _play(env, actions: torch.Tensor, repeat: int = 1) -> list[TensorDict]:
    """Step ``env`` with ``actions[j]`` held for ``repeat`` steps (``repeat`` > 1 only on a plain env)."""
    td, outs = env.reset(), []
    for a in actions:
        for _ in range(repeat):
            td["action"] = a
            td = env.step(td)
            outs.append(td["next"].clone())
            td = td["next"].clone()
    return outs


def test_the_env_with_an_action_repeat_passes_check_env_specs():
    check_env_specs(_env(4))
    assert action_repeat_of(_env(4)) == 4 and action_repeat_of(_env(1)) == 1


@pytest.mark.parametrize("repeat", [2, 4])
def test_a_decision_is_k_steps_with_the_same_action(repeat):
    actions = _actions(3)
    single = _play(_env(1), actions, repeat=repeat)
    held = _play(_env(repeat), actions)
    for j, out in enumerate(held):
        last = single[(j + 1) * repeat - 1]
        for key in ("true_state", "observation", "particles", "particle_log_weights"):
            torch.testing.assert_close(out[key], last[key])
        rewards = torch.stack([single[j * repeat + i]["reward"] for i in range(repeat)]).sum(0)
        torch.testing.assert_close(out["reward"], rewards)
        assert torch.equal(out["repeats"], torch.full((3, 1), repeat))


def test_an_episode_that_ends_inside_a_decision_keeps_its_last_step():
    """max_steps = 6 with k = 4: the second decision stops after 2 steps (truncation)."""
    actions = _actions(2)
    single = _play(_env(1, max_steps=6), actions, repeat=4)
    held = _play(_env(4, max_steps=6), actions)
    second = held[1]
    assert torch.equal(second["repeats"], torch.full((3, 1), 2)) and bool(second["truncated"].all())
    torch.testing.assert_close(second["true_state"], single[5]["true_state"])
    torch.testing.assert_close(second["particles"], single[5]["particles"])
    torch.testing.assert_close(second["reward"], single[4]["reward"] + single[5]["reward"])


@pytest.mark.parametrize("repeat", [0, -1, 1.5, True])
def test_a_bad_repeat_is_named(repeat):
    with pytest.raises(ValueError, match="^ActionRepeat.repeat: must be an integer >= 1"):
        ActionRepeat(repeat)
