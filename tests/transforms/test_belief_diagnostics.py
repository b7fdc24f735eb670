"""BeliefTransform writes the belief's diagnostics (log-evidence, ESS, resampled) under ``next``, in its specs,
under renamable keys, with the log-evidence summed over an episode and restarted at its reset."""

from __future__ import annotations

import torch
from torchrl.envs import Compose, StepCounter, Transform, TransformedEnv
from torchrl.envs.utils import check_env_specs

from escort_rl.belief import SIRFilter
from escort_rl.envs import POMDPEnv
from escort_rl.models import LinearGaussian
from escort_rl.transforms import BeliefTransform


def make_env(max_steps: int = 4, **keys) -> TransformedEnv:
    model = LinearGaussian(state_dim=2, obs_dim=1)
    return TransformedEnv(POMDPEnv(model, batch_size=(3,), seed=0, max_steps=max_steps),
                          BeliefTransform(model, SIRFilter(resample_threshold=1.0), 50, seed=1, **keys))


def test_the_diagnostics_are_in_the_specs_and_sum_over_an_episode():
    env = make_env(max_steps=4)
    check_env_specs(env)
    spec = env.observation_spec
    assert spec["log_evidence"].shape == (3,) and spec["ess"].shape == (3,) and spec["resampled"].dtype == torch.bool
    assert "log_evidence" in env.state_spec.keys()  # the next step reads it, ParallelEnv ships it
    rollout = env.rollout(8, break_when_any_done=False)  # two episodes of 4 steps
    assert torch.equal(rollout["log_evidence"][:, 0], torch.zeros(3))
    evidence = rollout["next", "log_evidence"]  # [3, 8]
    steps = torch.diff(torch.cat([torch.zeros(3, 1), evidence], 1), dim=1)
    assert (steps[:, :4] < 0).all()  # each observation's density adds a (here negative) log term
    # after the reset at step 4 the sum starts again: the 5th value is one step's term, not the sum of 5
    assert torch.equal(rollout["log_evidence"][:, 4], torch.zeros(3))
    assert (evidence[:, 4] > evidence[:, 3]).all()
    assert rollout["next", "resampled"].all()  # resample_threshold=1: every step
    assert ((rollout["next", "ess"] >= 1) & (rollout["next", "ess"] <= 50)).all()


def test_the_diagnostics_keys_can_be_renamed():
    env = make_env(log_evidence_key="belief_logz", ess_key="belief_ess", resampled_key="belief_resampled")
    rollout = env.rollout(2)
    assert {"belief_logz", "belief_ess", "belief_resampled"} <= set(rollout["next"].keys())
    assert "log_evidence" not in rollout["next"].keys()


class Dropout(Transform):
    """Loses the observation of env 1 at every odd step: NaN in it, ``observed`` False."""

    def _step(self, tensordict, next_tensordict):
        step = int(tensordict["step_count"].reshape(-1)[0])
        observed = torch.ones(next_tensordict.batch_size, dtype=torch.bool)
        if step % 2 == 1:
            observed[1] = False
            next_tensordict["observation"][1] = float("nan")
        next_tensordict.set("observed", observed)
        return next_tensordict

    def _reset(self, tensordict, tensordict_reset):
        return tensordict_reset


def test_a_row_whose_observation_is_lost_predicts_only():
    model = LinearGaussian(state_dim=2, obs_dim=1)
    env = TransformedEnv(POMDPEnv(model, batch_size=(3,), seed=0, max_steps=6),
                         Compose(StepCounter(), Dropout(), BeliefTransform(model, SIRFilter(), 50, seed=1)))
    rollout = env.rollout(6)
    evidence = rollout["next", "log_evidence"]
    assert torch.isfinite(rollout["next", "particles"]).all() and torch.isfinite(evidence).all()
    lost = ~rollout["next", "observed"]
    assert lost[1, 1::2].all() and not lost[[0, 2]].any()
    before = torch.cat([torch.zeros(3, 1), evidence[:, :-1]], 1)
    assert torch.equal(evidence[lost], before[lost])  # no observation, no evidence added
    assert (evidence[~lost] != before[~lost]).all()
