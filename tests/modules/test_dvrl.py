"""DVRL: the ELBO against closed-form marginals, resampling, partial resets, a short training run,
the TorchRL policy in an env rollout, the image encoder, and the configs."""

from __future__ import annotations

import math
from functools import partial

import pytest
import torch
from linear_gaussian_parts import CarryLatent, LinearEmission, LinearPrior, LinearProposal
from omegaconf import OmegaConf
from torch import nn
from torch.distributions import Independent, MultivariateNormal, Normal
from torchrl.collectors import Collector
from torchrl.envs import Compose, InitTracker, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import step_mdp

from escort_rl.belief.resampling import systematic
from escort_rl.config import config_dir
from escort_rl.envs import POMDPEnv
from escort_rl.models import DOMAINS
from escort_rl.models.light_dark import LightDark10D
from escort_rl.modules.dvrl import DVRL, DVRLState, resample
from escort_rl.modules.dvrl_networks import AtariEncoder
from escort_rl.modules.dvrl_torchrl import DVRLPolicy

torch.set_num_threads(1)
CONFIGS = config_dir() / "dvrl"


# ------------------------------------------------------------- a linear-Gaussian model as DVRL parts
# h carries the previous z (h_0 = 0), so with H = Z = 1:
#   z_t ~ N(h_{t-1}, 1) = N(z_{t-1}, 1),   o_t ~ N(z_t, σ²),   q(z_t | h, o) = N(α h + β o + γ, s²).
def linear_gaussian_dvrl(num_particles: int, proposal: nn.Module, sigma: float, resample: bool = True) -> DVRL:
    return DVRL(1, n_actions=2, latent_dim=1, hidden=1, num_particles=num_particles, encoding_dim=2,
                summary="deepsets", summary_dim=2, resample=resample,
                observation_encoder=nn.Identity(), prior=LinearPrior(), proposal=proposal,
                emission=LinearEmission(sigma), recurrence=CarryLatent())


def run(dvrl: DVRL, observations: list[float], batch: int, seed: int) -> torch.Tensor:
    """Σ_t ELBO_t for ``batch`` independent filters on the same observations: ``[batch]``."""
    g = torch.Generator().manual_seed(seed)
    state = dvrl.initial_state(batch)
    action = torch.zeros(batch, dtype=torch.long)
    total = torch.zeros(batch)
    with torch.no_grad():
        for t, o in enumerate(observations):
            reset = torch.full((batch,), t == 0)
            state, elbo, _ = dvrl.step(state, action, torch.full((batch, 1), o), reset, generator=g)
            total += elbo
    return total


def gaussian_kl(m1: float, s1: float, m2: float, s2: float) -> float:
    """KL(N(m1, s1²) || N(m2, s2²))."""
    return math.log(s2 / s1) + (s1**2 + (m1 - m2) ** 2) / (2 * s2**2) - 0.5


SIGMA, OBS = 0.5, 1.5
LOG_P = float(Normal(0.0, math.sqrt(1 + SIGMA**2)).log_prob(torch.tensor(OBS)))  # log N(o; 0, 1 + σ²)
POST_MEAN, POST_STD = OBS / (1 + SIGMA**2), math.sqrt(SIGMA**2 / (1 + SIGMA**2))


def test_elbo_is_a_bound_that_tightens_with_k():
    q_mean, q_std = 0.6, 0.6  # not the posterior N(1.2, 0.447²)
    proposal = LinearProposal(0.0, 0.0, q_mean, q_std)
    elbo_1 = run(linear_gaussian_dvrl(1, proposal, SIGMA), [OBS], batch=20000, seed=0)
    elbo_100 = run(linear_gaussian_dvrl(100, proposal, SIGMA), [OBS], batch=2000, seed=1)
    se_1 = float(elbo_1.std()) / math.sqrt(elbo_1.numel())
    se_100 = float(elbo_100.std()) / math.sqrt(elbo_100.numel())
    # K = 1: E[ELBO] = log p(o) - KL(q || posterior), exactly.
    expected_1 = LOG_P - gaussian_kl(q_mean, q_std, POST_MEAN, POST_STD)
    assert abs(float(elbo_1.mean()) - expected_1) < 4 * se_1
    # A lower bound for every K, tighter with more particles.
    assert float(elbo_1.mean()) < LOG_P - 0.5
    assert float(elbo_100.mean()) <= LOG_P + 4 * se_100
    assert float(elbo_100.mean()) > float(elbo_1.mean()) + 0.5
    assert LOG_P - float(elbo_100.mean()) < 0.05


@pytest.mark.parametrize("k", [1, 7])
def test_elbo_is_exact_with_the_posterior_as_proposal(k):
    # q(z | o) = N(o / (1 + σ²), σ²/(1 + σ²)) is the posterior, so every weight is p(o).
    proposal = LinearProposal(0.0, 1 / (1 + SIGMA**2), 0.0, POST_STD)
    elbo = run(linear_gaussian_dvrl(k, proposal, SIGMA), [OBS], batch=64, seed=2)
    torch.testing.assert_close(elbo, torch.full_like(elbo, LOG_P), rtol=0, atol=1e-5)


@pytest.mark.parametrize("resample_every_step", [True, False])
def test_marginal_estimate_is_unbiased_over_two_steps(resample_every_step):
    # z_1 ~ N(0, 1), z_2 ~ N(z_1, 1), o_t ~ N(z_t, σ²): o ~ N(0, [[1 + σ², 1], [1, 2 + σ²]]).
    observations = [1.0, 2.5]
    cov = torch.tensor([[1 + SIGMA**2, 1.0], [1.0, 2 + SIGMA**2]], dtype=torch.float64)
    log_p = float(MultivariateNormal(torch.zeros(2, dtype=torch.float64), cov).log_prob(
        torch.tensor(observations, dtype=torch.float64)))
    proposal = LinearProposal(0.5, 0.5, 0.0, 0.8)  # a rough guess, not the filtering posterior
    dvrl = linear_gaussian_dvrl(4, proposal, SIGMA, resample=resample_every_step)
    log_z = run(dvrl, observations, batch=40000, seed=3).double()
    ratio = torch.exp(log_z - log_p)  # E[p̂ / p] = 1 for an unbiased estimate p̂
    se = float(ratio.std()) / math.sqrt(ratio.numel())
    assert abs(float(ratio.mean()) - 1.0) < 4 * se + 1e-3
    assert float(log_z.mean()) < log_p  # and so a lower bound in log space


# ------------------------------------------------------------------------------------ resampling
def test_resample_keeps_shapes_and_gives_uniform_weights():
    g = torch.Generator().manual_seed(0)
    state = DVRLState(torch.randn(3, 5, 4, generator=g), torch.randn(3, 5, 2, generator=g),
                      torch.log_softmax(torch.randn(3, 5, generator=g), -1))
    idx = systematic(state.log_w, g)
    new = resample(state, idx)
    assert new.h.shape == state.h.shape and new.z.shape == state.z.shape and new.log_w.shape == state.log_w.shape
    torch.testing.assert_close(new.log_w, torch.full((3, 5), -math.log(5)))
    for b in range(3):
        assert torch.equal(new.h[b], state.h[b, idx[b]])
        assert torch.equal(new.z[b], state.z[b, idx[b]])


# ----------------------------------------------------------------------------------- partial resets
def small_dvrl(resample_every_step: bool = True) -> DVRL:
    torch.manual_seed(0)
    return DVRL(3, n_actions=4, latent_dim=2, hidden=8, num_particles=6, encoding_dim=8,
                resample=resample_every_step)


@pytest.mark.parametrize("resample_every_step", [True, False])
def test_partial_reset_touches_only_the_reset_rows(resample_every_step):
    dvrl = small_dvrl(resample_every_step)
    g = torch.Generator().manual_seed(1)
    state = DVRLState(torch.randn(3, 6, 8, generator=g), torch.randn(3, 6, 2, generator=g),
                      torch.log_softmax(torch.randn(3, 6, generator=g), -1))
    action, obs = torch.tensor([1, 2, 3]), torch.randn(3, 3, generator=g)
    reset = torch.tensor([True, False, True])

    def step(s, mask):
        return dvrl.step(s, action, obs, mask, generator=torch.Generator().manual_seed(7))

    with torch.no_grad():
        new, elbo, summary = step(state, reset)
        kept, elbo_kept, summary_kept = step(state, torch.zeros(3, dtype=torch.bool))
        fresh_rows = dvrl.reset_rows(state, reset)
        fresh, elbo_fresh, summary_fresh = step(fresh_rows, reset)
    # the env that was not reset: bit-identical to a step without any reset
    for a, b in ((new.h, kept.h), (new.z, kept.z), (new.log_w, kept.log_w), (elbo, elbo_kept),
                 (summary, summary_kept)):
        assert torch.equal(a[1], b[1])
    # the reset envs: the same as starting from fresh particles, and not what they had
    for a, b in ((new.h, fresh.h), (new.log_w, fresh.log_w), (elbo, elbo_fresh)):
        assert torch.equal(a, b)
    assert not torch.equal(new.h[0], kept.h[0])
    torch.testing.assert_close(fresh_rows.log_w[0], torch.full((6,), -math.log(6)))
    assert torch.equal(fresh_rows.h[[0, 2]], torch.zeros(2, 6, 8))


def test_step_rejects_bad_inputs():
    dvrl = small_dvrl()
    state = dvrl.initial_state(2)
    with pytest.raises(ValueError, match="observation"):
        dvrl.step(state, torch.zeros(2, dtype=torch.long), torch.zeros(2, 5))
    with pytest.raises(ValueError, match="observation"):
        dvrl.step(state, torch.zeros(2, dtype=torch.long), torch.tensor([[0.0, float("nan"), 0.0]] * 2))
    with pytest.raises(ValueError, match="state.h"):
        dvrl.step(DVRLState(state.h[:, :2], state.z, state.log_w), torch.zeros(2, dtype=torch.long),
                  torch.zeros(2, 3))
    with pytest.raises(ValueError, match="action_prev"):
        dvrl.step(state, torch.tensor([0, 4]), torch.zeros(2, 3))
    dvrl.step(state, torch.tensor([0, -1]), torch.zeros(2, 3), torch.tensor([False, True]))  # ignored on resets
    with pytest.raises(ValueError, match="summary"):
        DVRL(3, 4, 2, summary="lstm")


class ImpossibleEmission(LinearEmission):
    def forward(self, h, z, action_enc):
        return Independent(Normal(z + 1e30, torch.full_like(z, 1e-30)), 1)


def test_zero_likelihood_gives_minus_inf_elbo_and_uniform_weights_not_nan():
    dvrl = linear_gaussian_dvrl(5, LinearProposal(0.0, 0.0, 0.0, 1.0), SIGMA)
    dvrl.emission = ImpossibleEmission(SIGMA)
    with torch.no_grad():
        state, elbo, summary = dvrl.step(dvrl.initial_state(2), torch.zeros(2, dtype=torch.long),
                                         torch.zeros(2, 1), torch.ones(2, dtype=torch.bool))
    assert torch.isneginf(elbo).all()
    torch.testing.assert_close(state.log_w, torch.full((2, 5), -math.log(5)))
    assert torch.isfinite(summary).all()


# --------------------------------------------------------------------------------------- training
def linear_gaussian_sequences(batch: int, steps: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``s_t = 0.8 s_{t-1} + 0.5 (2 a_{t-1} - 1) + 0.3 ε``, ``o_t = s_t + 0.2 ε'`` with random
    actions: ``(actions_prev [B, T], observations [B, T, 1])``."""
    actions = torch.randint(0, 2, (batch, steps), generator=g)
    s = torch.randn(batch, generator=g)
    obs = []
    for t in range(steps):
        if t:
            s = 0.8 * s + 0.5 * (2 * actions[:, t].float() - 1) + 0.3 * torch.randn(batch, generator=g)
        obs.append(s + 0.2 * torch.randn(batch, generator=g))
    return actions, torch.stack(obs, 1).unsqueeze(-1)


def test_training_lowers_the_negative_elbo():
    torch.manual_seed(0)
    dvrl = DVRL(1, n_actions=2, latent_dim=2, hidden=16, num_particles=4, encoding_dim=16, summary="deepsets")
    reset = torch.zeros(64, 8, dtype=torch.bool)
    reset[:, 0] = True
    eval_actions, eval_obs = linear_gaussian_sequences(64, 8, torch.Generator().manual_seed(123))

    def eval_loss() -> float:
        with torch.no_grad():
            _, elbo, _ = dvrl.unroll(dvrl.initial_state(64), eval_actions, eval_obs, reset,
                                     generator=torch.Generator().manual_seed(0))
        return -float(elbo.mean())

    before = eval_loss()
    optimizer = torch.optim.Adam(dvrl.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(1)
    for _ in range(100):
        actions, obs = linear_gaussian_sequences(32, 8, g)
        _, elbo, _ = dvrl.unroll(dvrl.initial_state(32), actions, obs, reset[:32])
        loss = -elbo.mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = eval_loss()
    assert after < before - 0.5, (before, after)  # about 1.55 -> 0.66 nats per step


# ------------------------------------------------------------------------------------ TorchRL
def make_env_and_policy(num_envs: int = 2):
    model = LightDark10D()
    torch.manual_seed(0)
    dvrl = DVRL(model.obs_dim, model.n_actions, latent_dim=5, hidden=16, num_particles=8, encoding_dim=16)
    policy = DVRLPolicy(dvrl)
    env = POMDPEnv(model, batch_size=(num_envs,), seed=0, max_steps=50)
    return TransformedEnv(env, Compose(InitTracker(), policy.make_tensordict_primer())), policy


def test_policy_runs_in_env_rollout_with_the_primer():
    env, policy = make_env_and_policy()
    with torch.no_grad():
        td = env.rollout(5, policy)
    assert td.batch_size == (2, 5)
    shapes = {"dvrl_h": (2, 5, 8, 16), "dvrl_z": (2, 5, 8, 5), "dvrl_log_w": (2, 5, 8), "dvrl_prev_action": (2, 5),
              "logits": (2, 5, 10), "action": (2, 5), "state_value": (2, 5, 1), "dvrl_elbo": (2, 5)}
    for key, shape in shapes.items():
        assert td[key].shape == shape, key
        if key in policy.state_keys.values():
            assert td["next", key].shape == shape, key
    assert td["is_init"].squeeze(-1).tolist() == [[True, False, False, False, False]] * 2
    # the primer starts fresh particles; the state then moves, and next(t) is the root of t + 1
    assert torch.equal(td["dvrl_h"][:, 0], torch.zeros(2, 8, 16))
    torch.testing.assert_close(td["dvrl_log_w"][:, 0], torch.full((2, 8), -math.log(8)))
    assert not torch.equal(td["dvrl_h"][:, 1], td["dvrl_h"][:, 0])
    assert not torch.equal(td["dvrl_h"][:, 4], td["dvrl_h"][:, 3])
    assert torch.equal(td["next", "dvrl_h"][:, :-1], td["dvrl_h"][:, 1:])
    assert torch.equal(td["dvrl_prev_action"][:, 1:], td["action"][:, :-1])
    torch.testing.assert_close(torch.logsumexp(td["next", "dvrl_log_w"], -1), torch.zeros(2, 5), atol=1e-5, rtol=0)
    assert torch.isfinite(td["dvrl_elbo"]).all()
    # the trainer's replay: gradients flow to the belief model from the ELBO and the heads
    logits, value, elbo = policy.replay(td)
    assert logits.shape == (2, 5, 10) and value.shape == (2, 5) and elbo.shape == (2, 5)
    (-elbo.mean() + logits.logsumexp(-1).mean() + value.mean()).backward()
    assert policy.dvrl.proposal.mean.weight.grad is not None


def test_partial_env_reset_reprimes_only_the_reset_env():
    env, policy = make_env_and_policy()
    with torch.no_grad():
        td = step_mdp(env.step(policy(env.reset())))
        td.set("_reset", torch.tensor([[True], [False]]))
        out = env.reset(td)
        assert out["is_init"].squeeze(-1).tolist() == [True, False]
        assert torch.equal(out["dvrl_h"][1], td["dvrl_h"][1]) and torch.equal(out["dvrl_z"][1], td["dvrl_z"][1])
        assert torch.equal(out["dvrl_h"][0], torch.zeros(8, 16))
        torch.testing.assert_close(out["dvrl_log_w"][0], torch.full((8,), -math.log(8)))
        policy(out)  # the policy steps on from the mixed batch


def test_collector_with_partial_resets():
    # two envs with episodes of 3 and 4 steps: the resets fall at different steps in each env
    model = LightDark10D()
    torch.manual_seed(0)
    policy = DVRLPolicy(DVRL(model.obs_dim, model.n_actions, latent_dim=5, hidden=16, num_particles=8))
    envs = SerialEnv(2, [partial(POMDPEnv, model, (1,), seed=s, max_steps=3 + s) for s in (0, 1)])
    env = TransformedEnv(envs, Compose(InitTracker(), policy.make_tensordict_primer()))
    collector = Collector(env, policy, frames_per_batch=24, total_frames=24, auto_register_policy_transforms=False)
    batch = next(iter(collector)).reshape(2, -1)  # [env, T]
    collector.shutdown()
    is_init = batch["is_init"].squeeze(-1)
    assert is_init[0].nonzero().squeeze(-1).tolist() == [0, 3, 6, 9]
    assert is_init[1].nonzero().squeeze(-1).tolist() == [0, 4, 8]
    # every first step starts from primed particles; every other step from the previous step's state
    assert torch.equal(batch["dvrl_h"][is_init], torch.zeros(int(is_init.sum()), 8, 16))
    carried = ~is_init[:, 1:]
    assert torch.equal(batch["dvrl_h"][:, 1:][carried], batch["next", "dvrl_h"][:, :-1][carried])


def primed_worker_env(policy: DVRLPolicy, seed: int) -> TransformedEnv:
    """One env with its own primer (the primer inside each ParallelEnv worker); episodes of 3 + seed steps."""
    env = POMDPEnv(LightDark10D(), batch_size=(1,), seed=seed, max_steps=3 + seed)
    return TransformedEnv(env, Compose(InitTracker(), policy.make_tensordict_primer()))


@pytest.mark.slow
def test_parallel_env_ships_the_state_to_its_workers():
    # ParallelEnv ships only state-spec keys to its workers: the primer registers the particles there
    model = LightDark10D()
    torch.manual_seed(0)
    policy = DVRLPolicy(DVRL(model.obs_dim, model.n_actions, latent_dim=5, hidden=16, num_particles=8))
    env = ParallelEnv(2, [partial(primed_worker_env, policy, s) for s in (0, 1)])
    try:
        with torch.no_grad():
            td = env.rollout(6, policy, break_when_any_done=False)
    finally:
        env.close()
    is_init = td["is_init"].reshape(2, 6)
    assert is_init.tolist() == [[True, False, False, True, False, False], [True, False, False, False, True, False]]
    h, next_h = td["dvrl_h"].reshape(2, 6, 8, 16), td["next", "dvrl_h"].reshape(2, 6, 8, 16)
    assert torch.equal(h[is_init], torch.zeros(int(is_init.sum()), 8, 16))
    carried = ~is_init[:, 1:]
    assert torch.equal(h[:, 1:][carried], next_h[:, :-1][carried])
    assert not torch.equal(h[:, 1:][carried], h[:, :-1][carried])  # and the state moves
    prev_action, action = td["dvrl_prev_action"].reshape(2, 6), td["action"].reshape(2, 6)
    assert torch.equal(prev_action[:, 1:][carried], action[:, :-1][carried])


def test_policy_names_the_missing_keys():
    env, policy = make_env_and_policy()
    td = env.reset()
    with pytest.raises(KeyError, match="InitTracker"):
        policy(td.exclude("is_init"))
    with pytest.raises(KeyError, match="make_tensordict_primer"):
        policy(td.exclude("dvrl_h"))


# ------------------------------------------------------------------------------------ images
def test_atari_encoder_and_image_dvrl_shapes():
    torch.manual_seed(0)
    encoder = AtariEncoder(channels=3, encoding_dim=32)
    assert encoder(torch.rand(2, 3, 84, 84)).shape == (2, 32)
    dvrl = DVRL((1, 84, 84), n_actions=6, latent_dim=4, hidden=16, num_particles=2, encoding_dim=16)
    with torch.no_grad():
        state, elbo, summary = dvrl.step(dvrl.initial_state(2), torch.zeros(2, dtype=torch.long),
                                         torch.rand(2, 1, 84, 84), torch.ones(2, dtype=torch.bool))
    assert state.h.shape == (2, 2, 16) and elbo.shape == (2,) and summary.shape == (2, 16)
    assert torch.isfinite(elbo).all()
    with pytest.raises(ValueError, match="obs_shape"):
        DVRL((3, 64, 64), n_actions=6, latent_dim=4)


# ------------------------------------------------------------------------------------ configs
@pytest.mark.parametrize("name, latent_dim", [("lightdark10d", 5), ("kidnapped20d", 10), ("mtt20d", 20)])
def test_configs_build_for_their_domain(name, latent_dim):
    cfg = OmegaConf.to_container(OmegaConf.load(CONFIGS / f"{name}.yaml"))
    assert cfg["name"] == name
    model = DOMAINS[name]()
    dvrl = DVRL.from_config(cfg, model.obs_dim, model.n_actions)
    assert (dvrl.latent_dim, dvrl.hidden, dvrl.num_particles) == (latent_dim, 64, 100)
    with pytest.raises(ValueError, match="dvrl.obs_dim"):
        DVRL.from_config(cfg, model.obs_dim + 1, model.n_actions)
    with pytest.raises(ValueError, match="dvrl.module.particles"):
        DVRL.from_config({**cfg, "module": {**cfg["module"], "particles": 3}}, model.obs_dim, model.n_actions)
