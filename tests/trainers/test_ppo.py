"""PPO (escort_rl.trainers.ppo): the loss against hand-computed values, GAE's shape, renamed keys,
warm start and exact resume."""

import dataclasses
import math
import shutil

import pytest
import torch
from tensordict import TensorDict

from escort_rl.config import compose
from escort_rl.modules import DeepSetsActor, make_deepsets_policy
from escort_rl.trainers.builders import belief_keys
from escort_rl.trainers.checkpointing import list_checkpoints, load_checkpoint
from escort_rl.trainers.ppo import make_ppo_loss
from escort_rl.trainers.training import train

TINY_PPO = ["trainer=ppo", "filter=sir", "trainer.warm_start_filter=null", "trainer.num_envs=4",
            "trainer.rollout_steps=6", "env.max_steps=12",
            "num_particles=8", "actor.hidden=8", "trainer.minibatches=2", "trainer.epochs=2",
            "trainer.warm_start_epochs=null", "trainer.checkpoint_every=1"]


def _tiny_batch(n: int = 6, particles: int = 5, d: int = 10, keys=("particles", "particle_log_weights")):
    g = torch.Generator().manual_seed(0)
    return TensorDict({
        keys[0]: torch.randn(n, particles, d, generator=g),
        keys[1]: torch.full((n, particles), -math.log(particles)),
        "action": torch.randint(0, 10, (n,), generator=g),
        "action_log_prob": torch.full((n,), -math.log(10.0)) + 0.1 * torch.randn(n, generator=g),
        "advantage": torch.randn(n, 1, generator=g),
        "value_target": torch.randn(n, 1, generator=g),
    }, [n])


@pytest.mark.parametrize("keys", [("particles", "particle_log_weights"), ("belief_x", "belief_logw")])
def test_ppo_loss_matches_the_clipped_objective_by_hand(keys):
    cfg = compose(["trainer=ppo", f"keys.particles={keys[0]}", f"keys.log_weights={keys[1]}",
                   "trainer.clip_epsilon=0.2", "trainer.entropy_coef=0.01", "trainer.critic_coef=0.5"])
    torch.manual_seed(0)
    actor, critic = DeepSetsActor(10, 10, hidden=8), DeepSetsActor(10, 1, hidden=8)
    loss = make_ppo_loss(make_deepsets_policy(actor, *belief_keys(cfg)), critic, cfg)
    batch = _tiny_batch(keys=keys)
    out = loss(batch.clone())

    logits = actor(batch[keys[0]], batch[keys[1]])
    dist = torch.distributions.Categorical(logits=logits)
    ratio = torch.exp(dist.log_prob(batch["action"]) - batch["action_log_prob"])
    adv = batch["advantage"].squeeze(-1)
    adv = (adv - adv.mean()) / adv.std().clamp_min(1e-6)  # normalize_advantage
    objective = -torch.minimum(ratio * adv, ratio.clamp(0.8, 1.2) * adv).mean()
    value = critic(batch[keys[0]], batch[keys[1]])
    critic_loss = 0.5 * torch.nn.functional.smooth_l1_loss(value, batch["value_target"])
    torch.testing.assert_close(out["loss_objective"], objective, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out["loss_critic"], critic_loss, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out["loss_entropy"], -0.01 * dist.entropy().mean(), rtol=1e-4, atol=1e-6)


def test_gae_with_a_zero_critic_is_the_discounted_return():
    """With V ≡ 0 and λ = 1, GAE's advantage is the discounted reward-to-go of the episode."""
    cfg = compose(["trainer=ppo", "trainer.gamma=0.5", "trainer.gae_lambda=1.0"])
    actor, critic = DeepSetsActor(10, 10, hidden=4), DeepSetsActor(10, 1, hidden=4)
    for p in critic.parameters():
        torch.nn.init.zeros_(p)
    loss = make_ppo_loss(make_deepsets_policy(actor, *belief_keys(cfg)), critic, cfg)
    t = 4
    reward = torch.tensor([1.0, 2.0, 3.0, 4.0]).view(1, t, 1)
    done = torch.tensor([False, True, False, True]).view(1, t, 1)
    parts = torch.zeros(1, t, 3, 10)
    logw = torch.zeros(1, t, 3)
    td = TensorDict({"particles": parts, "particle_log_weights": logw,
                     "next": {"particles": parts, "particle_log_weights": logw, "reward": reward, "done": done,
                              "terminated": done}}, [1, t])
    loss.value_estimator(td)
    expected = torch.tensor([1 + 0.5 * 2, 2.0, 3 + 0.5 * 4, 4.0]).view(1, t, 1)
    torch.testing.assert_close(td["advantage"], expected)


def test_ppo_trains_with_renamed_keys_and_warm_start(tmp_path):
    run = tmp_path / "run"
    cfg = compose([*TINY_PPO, "filter=escort", "filter.num_steps=2", "filter.compile=false",
                   "keys.particles=belief_x", "keys.log_weights=belief_logw", "trainer.iterations=2",
                   "trainer.warm_start_filter=sir", "trainer.warm_start_iterations=1", f"output_dir={run}"])
    train(cfg, progress=False)
    state = load_checkpoint(run)["trainer_state"]
    assert state["iteration"] == 2 and state["frames"] == 2 * 4 * 12
    for record in state["history"]:
        assert all(math.isfinite(record[k]) for k in ("loss_objective", "loss_critic", "entropy"))
        assert record["episodes"] == 4  # one full episode per env per iteration


def _params(run) -> dict:
    from omegaconf import OmegaConf

    from escort_rl.models import LightDark10D
    from escort_rl.trainers.builders import build_actor, build_critic

    cfg = OmegaConf.create(load_checkpoint(run)["config"])
    actor, (critic, _) = build_actor(cfg, 10, 10, LightDark10D()), build_critic(cfg, LightDark10D(), "state")
    load_checkpoint(run, actor=actor, critic=critic)
    return {**{f"a.{k}": v for k, v in actor.state_dict().items()},
            **{f"c.{k}": v for k, v in critic.state_dict().items()}}


def test_ppo_resume_is_exact(tmp_path):
    """Two iterations straight equal one iteration, a stop, and a resume for the second."""
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    train(compose([*TINY_PPO, "trainer.iterations=2", f"output_dir={straight}"]), progress=False)
    train(compose([*TINY_PPO, "trainer.iterations=1", f"output_dir={resumed}"]), progress=False)
    cfg = compose([*TINY_PPO, "trainer.iterations=2", f"output_dir={resumed}"])
    train(cfg, resume_state={"path": str(resumed)}, progress=False)
    a, b = _params(straight), _params(resumed)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    ha = load_checkpoint(straight)["trainer_state"]["history"]
    hb = load_checkpoint(resumed)["trainer_state"]["history"]
    assert [h["episode_return"] for h in ha] == [h["episode_return"] for h in hb]


def test_linear_lr_schedule_falls_per_update_and_resumes_on_the_same_schedule(tmp_path):
    """trainer.lr_schedule=linear: each update's rate is lr·(1 − u/U) over the run's U updates (two per
    iteration here), the history records the last update's, and a stop and resume matches a straight run."""
    sched = [*TINY_PPO, "trainer.lr_schedule=linear", "trainer.lr=0.001"]
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    train(compose([*sched, "trainer.iterations=3", f"output_dir={straight}"]), progress=False)
    history = load_checkpoint(straight)["trainer_state"]["history"]
    assert [round(h["lr"], 9) for h in history] == [round(1e-3 * (1 - u / 6), 9) for u in (1, 3, 5)]
    shutil.copytree(straight, resumed)  # the same run, stopped after its first iteration
    for later in list_checkpoints(resumed / "checkpoints")[:-1]:
        shutil.rmtree(later)
    cfg = compose([*sched, "trainer.iterations=3", f"output_dir={resumed}"])
    train(cfg, resume_state={"path": str(resumed)}, progress=False)
    a, b = _params(straight), _params(resumed)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_collection_config_applies_exploring_starts_and_the_warm_start_filter():
    from escort_rl.trainers.scaffold import collection_config

    cfg = compose([*TINY_PPO, "filter=escort", "trainer.warm_start_filter=sir", "trainer.warm_start_iterations=2",
                   "trainer.exploring_starts=true"])
    warm, main = collection_config(cfg, "sir", True), collection_config(cfg, "escort", True)
    assert warm.filter.kind == "sir" and main.filter.kind == "escort"
    for c in (warm, main):
        assert (c.env.model.start_low, c.env.model.start_high, c.env.model.prior_width) == (0.0, 10.0, 2.0)
        assert c.env.model.goal == cfg.env.model.goal  # the other env keys are kept
    # evaluation's env unchanged: the paper's box, and the prior is the start distribution
    assert (cfg.env.model.start_low, cfg.env.model.start_high, cfg.env.model.prior_width) == (0.0, 2.0, None)
    plain = compose([*TINY_PPO, "trainer.exploring_starts=false", "trainer.warm_start_filter=null"])
    assert collection_config(plain, "sir", False) is plain


def test_a_short_run_improves_the_return():
    """12 PPO iterations (23k frames, 60-step episodes) raise the mean return of sampled actions on the
    same 128 seeded evaluation episodes. Measured over training seeds 0-19: the paired gain was 3.8 to
    6.1 (s.e. about 0.08 each); the test asks for more than 1 and 5 standard errors."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from escort_rl.trainers.builders import build_model, make_env
    from escort_rl.trainers.ppo import PPO
    from escort_rl.trainers.scaffold import iteration_seed

    cfg = compose(["trainer=ppo", "filter=sir", "num_particles=16", "trainer.num_envs=32", "env.max_steps=60",
                   "trainer.rollout_steps=30", "trainer.warm_start_filter=null", "actor.hidden=32", "seed=7"])

    def returns(policy):
        env = make_env(cfg, 128, seed=123)
        torch.manual_seed(123)
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            rollout = env.rollout(60, policy, break_when_any_done=False)
        reward, done = rollout["next", "reward"].squeeze(-1), rollout["next", "done"].squeeze(-1)
        first_episode = (torch.cumsum(done.long(), 1) - done.long()) == 0
        return (reward * first_episode).sum(1)

    torch.manual_seed(7)
    algo = PPO(cfg, build_model(cfg.env))
    before = returns(algo.policy)
    for it in range(12):
        seed = iteration_seed(7, it)
        torch.manual_seed(seed)
        algo.iteration(it, seed)
    algo.close()
    gain = returns(algo.policy) - before
    se = gain.std() / gain.numel() ** 0.5
    assert gain.mean() > 1.0 and gain.mean() > 5 * se, (float(gain.mean()), float(se))


def test_action_repeat_counts_env_steps_and_decides_every_k_steps(tmp_path):
    """With trainer.action_repeat = 3 an iteration runs ⌈12 / 3⌉ = 4 decisions per env (one batch of
    rollout_steps = 4), and the frames it reports are env steps: 4 envs × 12 steps."""
    from escort_rl.models import LightDark10D
    from escort_rl.trainers.ppo import PPO

    cfg = compose([*TINY_PPO, "trainer.action_repeat=3", "trainer.rollout_steps=6", "trainer.exploring_starts=false",
                   f"output_dir={tmp_path}"])  # far from the goal: no episode ends inside the 12 steps
    algorithm = PPO(cfg, LightDark10D())
    try:
        assert (algorithm.rollout_steps, algorithm.batches) == (4, 1)
        stats = algorithm.iteration(0, seed=0)
    finally:
        algorithm.close()
    assert stats["frames"] == 4 * 12
    assert math.isfinite(stats["loss_objective"])


def test_recurrent_ppo_refuses_an_action_repeat_and_particle_subsampling(tmp_path):
    from escort_rl.config import ConfigError

    with pytest.raises(ConfigError, match="^trainer.action_repeat: trainer=recurrent_ppo"):
        train(compose(["trainer=recurrent_ppo", "trainer.action_repeat=2", f"output_dir={tmp_path}"]), progress=False)
    with pytest.raises(ConfigError, match="^trainer.update_particles: trainer=recurrent_ppo"):
        train(compose(["trainer=recurrent_ppo", "trainer.update_particles=8", f"output_dir={tmp_path}"]),
              progress=False)


def test_update_particles_trains_on_a_subset_with_the_old_log_prob_recomputed_on_it(tmp_path):
    """trainer.update_particles = 3 of 5: each frame keeps 3 of its own particles (with their
    log-weights), and action_log_prob is the policy's log-probability on that subset."""
    from escort_rl.models import LightDark10D
    from escort_rl.trainers.ppo import PPO

    cfg = compose([*TINY_PPO, "trainer.update_particles=3", f"output_dir={tmp_path}"])
    algorithm = PPO(cfg, LightDark10D())
    try:
        batch = _tiny_batch().reshape(2, 3)  # [E, T] frames of 5 particles
        batch["particle_log_weights"] = torch.randn(2, 3, 5, generator=torch.Generator().manual_seed(2))
        sub = algorithm.subsample_particles(batch)
        assert sub["particles"].shape == (2, 3, 3, 10)
        for e in range(2):
            for t in range(3):
                rows = [int((batch["particles"][e, t] == p).all(-1).nonzero()) for p in sub["particles"][e, t]]
                assert len(set(rows)) == 3  # distinct particles of the same frame
                torch.testing.assert_close(sub["particle_log_weights"][e, t], batch["particle_log_weights"][e, t, rows])
        expected = algorithm.policy.get_dist(sub).log_prob(sub["action"])
        torch.testing.assert_close(sub["action_log_prob"], expected)
        assert not torch.allclose(sub["action_log_prob"], batch["action_log_prob"])
        algorithm.params = dataclasses.replace(algorithm.params, update_particles=5)
        assert algorithm.subsample_particles(batch) is batch  # M >= N: the batch as collected
    finally:
        algorithm.close()


def test_warm_start_epochs_apply_to_the_warm_start_iterations_only():
    """``trainer.warm_start_epochs`` sets the passes per batch while the warm-start filter collects;
    ``trainer.epochs`` after it, and everywhere when there is no warm start."""
    from escort_rl.models import LightDark10D
    from escort_rl.trainers.ppo import PPO

    cfg = compose([*TINY_PPO, "trainer.warm_start_filter=sir", "trainer.warm_start_iterations=1",
                   "trainer.warm_start_epochs=3"])
    ppo = PPO(cfg, LightDark10D())
    assert [ppo.epochs_for(i) for i in range(3)] == [3, 2, 2]
    steps = []
    step = ppo.optimizer.step
    ppo.optimizer.step = lambda *a, **k: (steps.append(1), step(*a, **k))[1]
    try:
        per_pass = ppo.batches * int(cfg.trainer.minibatches)  # Adam steps in one pass over every batch
        ppo.iteration(0, seed=1)
        assert len(steps) == 3 * per_pass
        ppo.iteration(1, seed=2)
        assert len(steps) == 3 * per_pass + 2 * per_pass
    finally:
        ppo.close()
    plain = PPO(compose([*TINY_PPO, "trainer.warm_start_filter=null", "trainer.warm_start_epochs=3"]), LightDark10D())
    assert plain.epochs_for(0) == 2


def _continuous_loss(cap):
    """A TanhNormal PPO loss on a 1-D box [-2, 2], with ``trainer.max_importance_ratio=cap``."""
    cfg = compose(["trainer=ppo", "trainer.clip_epsilon=0.2", "trainer.entropy_coef=0.0",
                   f"trainer.max_importance_ratio={'null' if cap is None else cap}"])
    torch.manual_seed(0)
    actor, critic = DeepSetsActor(10, 2, hidden=8), DeepSetsActor(10, 1, hidden=8)
    box = (torch.tensor([-2.0]), torch.tensor([2.0]))
    policy = make_deepsets_policy(actor, *belief_keys(cfg), action_box=box, distribution="tanh_normal")
    return make_ppo_loss(policy, critic, cfg), actor


def test_the_importance_cap_bounds_the_surrogate_as_dual_clip_does():
    """With cap ``c`` the ratio ``r`` that weighs the surrogate is ``min(r, c)``: the objective is
    ``−mean(min(min(r, c)·A, clip(r, 1 ± ε)·min(r, c)/r·A))``; a negative advantage contributes at most
    ``c·|A|``, where uncapped it grows with ``r`` (here about e^40)."""
    batch = _tiny_batch()
    batch["action"] = torch.linspace(-1.9, 1.9, 6).unsqueeze(-1)
    batch["action_log_prob"] = torch.full((6,), -40.0)  # drawn from a policy far wider than today's
    batch["advantage"] = torch.tensor([[-1.0], [-0.5], [0.3], [1.0], [-2.0], [0.7]])
    uncapped, _ = _continuous_loss(None)
    assert float(uncapped(batch.clone())["loss_objective"].detach()) > 1e12
    loss, actor = _continuous_loss(3.0)
    out = loss(batch.clone())
    with torch.no_grad():
        dist = loss.actor_network.get_dist(batch.clone())
        ratio = torch.exp(dist.log_prob(batch["action"]) - batch["action_log_prob"])
    adv = batch["advantage"].squeeze(-1)
    adv = (adv - adv.mean()) / adv.std().clamp_min(1e-6)
    capped = ratio.clamp_max(3.0)
    objective = -torch.minimum(capped * adv, ratio.clamp(0.8, 1.2) * capped / ratio * adv).mean()
    assert bool((ratio > 3.0).all())  # every sample is capped
    torch.testing.assert_close(out["loss_objective"], objective, rtol=1e-4, atol=1e-5)
    assert float(out["loss_objective"]) <= 3.0 * float(adv.abs().max())


def _ppo_with_poisoned_losses(poisoned):
    """A tiny PPO whose ``total_loss`` is made infinite on the minibatch steps in ``poisoned``
    (``"all"``: every step), and the list of the Adam steps it took."""
    from escort_rl.models import LightDark10D
    from escort_rl.trainers.ppo import PPO

    ppo = PPO(compose([*TINY_PPO, "trainer.warm_start_filter=null"]), LightDark10D())
    calls, steps = [], []
    total_loss, step = ppo.total_loss, ppo.optimizer.step

    def poisoned_total(minibatch, out):
        calls.append(1)
        value = total_loss(minibatch, out)
        return value * float("inf") if poisoned == "all" or len(calls) in poisoned else value

    ppo.total_loss = poisoned_total
    ppo.optimizer.step = lambda *a, **k: (steps.append(1), step(*a, **k))[1]
    return ppo, steps


def test_a_non_finite_gradient_step_is_skipped_and_counted():
    ppo, steps = _ppo_with_poisoned_losses({1, 3})
    try:
        stats = ppo.iteration(0, seed=1)
        per_iteration = ppo.batches * ppo.epochs * int(ppo.cfg.trainer.minibatches)
        assert len(steps) == per_iteration - 2
        assert stats["skipped_steps"] == pytest.approx(2 / per_iteration)
        assert math.isfinite(stats["grad_norm"]) and math.isfinite(stats["loss_objective"])
        assert all(bool(torch.isfinite(p).all()) for p in ppo.loss.parameters())
    finally:
        ppo.close()


def test_an_update_with_no_finite_step_raises_and_names_the_fix():
    ppo, steps = _ppo_with_poisoned_losses("all")
    try:
        with pytest.raises(FloatingPointError, match="trainer.max_importance_ratio=3"):
            ppo.iteration(0, seed=1)
        assert steps == []
    finally:
        ppo.close()


def test_the_log_keeps_what_clip_ppo_loss_returns(tmp_path):
    """kl_approx, ESS and the critic's explained variance reach the history beside the loss terms."""
    run = tmp_path / "run"
    train(compose([*TINY_PPO, "trainer.iterations=1", "trainer.critic_input=belief", f"output_dir={run}"]),
          progress=False)
    record = load_checkpoint(run)["trainer_state"]["history"][0]
    for key in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "clip_fraction", "kl_approx", "ESS",
                "explained_variance", "grad_norm"):
        assert math.isfinite(record[key]), key
    assert 0 < record["ESS"] <= 1  # ClipPPOLoss's normalised effective sample size of the importance ratios
    assert record["explained_variance"] <= 1


@pytest.mark.parametrize("critic_input", ["state", "belief"])
def test_the_critic_is_the_one_ppo_params_name(critic_input, tmp_path):
    from escort_rl.models import LightDark10D
    from escort_rl.modules import DeepSetsActor, DeepSetsCritic
    from escort_rl.modules.critics import StateValueNet
    from escort_rl.trainers.params import PPOParams
    from escort_rl.trainers.ppo import PPO

    overrides = [] if critic_input == PPOParams.critic_input else [f"trainer.critic_input={critic_input}"]
    algorithm = PPO(compose([*TINY_PPO, *overrides, f"output_dir={tmp_path}"]), LightDark10D())
    try:
        assert algorithm.params.critic_input == critic_input
        expected = StateValueNet if critic_input == "state" else DeepSetsCritic
        assert type(algorithm.critic) is expected and not isinstance(algorithm.critic, DeepSetsActor)
    finally:
        algorithm.close()


def test_the_belief_trainers_read_typed_params_not_config_defaults():
    """No ``cfg.trainer.get(key, default)`` repeats a default of the Params dataclasses (one of them
    once disagreed with PPOParams on critic_input)."""
    import inspect
    import re

    from escort_rl.trainers import builders, ppo, recurrent_ppo, reinforce, scaffold

    for module in (builders, ppo, recurrent_ppo, reinforce, scaffold):
        found = re.findall(r"\b(?:trainer|t|actor)\.get\(", inspect.getsource(module))
        assert not found, f"{module.__name__}: {found}"
