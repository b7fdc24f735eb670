"""Tests of BeliefTransform: specs, resets, validation, and reproducibility across processes."""

from __future__ import annotations

import functools
import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import Compose, ParallelEnv, SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs

from escort_rl.belief import ParticleBelief, SIRFilter
from escort_rl.envs import POMDPEnv
from escort_rl.models import LightDark10D, LinearGaussian
from escort_rl.transforms import BeliefTransform
from escort_rl.transforms.belief_transform import derive_seed

# ---------------------------------------------------------------------------------------------
# Module-level factories and policies: multi-process tests pickle them (spawn start method).
# ---------------------------------------------------------------------------------------------


def make_belief_env(
    env_seed: int,
    filter_seed: int,
    batch: int = 2,
    num_particles: int = 20,
    max_steps: int | None = 8,
    resample_threshold: float = 0.5,
) -> TransformedEnv:
    model = LightDark10D()
    return TransformedEnv(
        POMDPEnv(model, batch_size=(batch,), seed=env_seed, max_steps=max_steps, expose_state=True),
        BeliefTransform(model, SIRFilter(resample_threshold=resample_threshold), num_particles, seed=filter_seed),
    )


class CyclicAction(torch.nn.Module):
    """A deterministic policy: action = (step_count + offset) mod n_actions (varies the actions)."""

    def __init__(self, n_actions: int = 10, offset: int = 0) -> None:
        super().__init__()
        self.n_actions, self.offset = n_actions, offset

    def forward(self, step_count: torch.Tensor) -> torch.Tensor:
        return ((step_count.squeeze(-1) + self.offset) % self.n_actions).long()


def cyclic_policy(offset: int = 0) -> TensorDictModule:
    return TensorDictModule(CyclicAction(10, offset), in_keys=["step_count"], out_keys=["action"])


class GreedyOnBeliefMean(torch.nn.Module):
    """A deterministic policy that reads the belief: push the dimension whose weighted mean position
    is farthest below the goal (8) in the positive direction."""

    def forward(self, particles: torch.Tensor, log_weights: torch.Tensor) -> torch.Tensor:
        w = torch.softmax(log_weights, dim=-1).unsqueeze(-1)
        mean_pos = (w * particles).sum(-2)[..., :5]
        return 2 * torch.argmax(8.0 - mean_pos, dim=-1)


def belief_policy() -> TensorDictModule:
    return TensorDictModule(
        GreedyOnBeliefMean(), in_keys=["particles", "particle_log_weights"], out_keys=["action"]
    )


# (env seed, filter seed) per sub-env / worker; filter seed None shares the base env's generator
ENV_SEEDS = ((11, 101), (12, None))
FACTORIES = [functools.partial(make_belief_env, e, f) for e, f in ENV_SEEDS]


def make_base_env(env_seed: int, batch: int = 2, max_steps: int | None = 8) -> POMDPEnv:
    """A bare POMDPEnv: the sub-env of a batched env with the BeliefTransform on top."""
    return POMDPEnv(LightDark10D(), batch_size=(batch,), seed=env_seed, max_steps=max_steps, expose_state=True)


BASE_FACTORIES = [functools.partial(make_base_env, 11), functools.partial(make_base_env, 12)]


def belief_on_top(kind, filter_seed, num_particles: int = 20) -> TransformedEnv:
    """TorchRL's usual placement: ``TransformedEnv(SerialEnv/ParallelEnv(...), BeliefTransform(...))``."""
    kwargs = {"mp_start_method": "spawn"} if kind is ParallelEnv else {}
    return TransformedEnv(
        kind(2, BASE_FACTORIES, **kwargs),
        BeliefTransform(LightDark10D(), SIRFilter(), num_particles, seed=filter_seed),
    )


# ---------------------------------------------------------------------------------------------
# Specs and the step/reset contract
# ---------------------------------------------------------------------------------------------


def test_check_env_specs_and_spec_contents():
    env = make_belief_env(0, 1, batch=3, num_particles=16)
    check_env_specs(env)
    for spec in (env.observation_spec, env.state_spec):
        assert spec["particles"].shape == (3, 16, 10)
        assert spec["particle_log_weights"].shape == (3, 16)
        assert spec["particles"].dtype == torch.float32
    assert "observation" in env.observation_spec.keys()
    td = env.reset()
    assert td["particles"].shape == (3, 16, 10)
    torch.testing.assert_close(td["particle_log_weights"], torch.full((3, 16), -math.log(16)))
    # the prior is the model's start distribution: positions in [0, 2]^5, zero velocity
    p = td["particles"]
    assert bool(((p[..., :5] >= 0) & (p[..., :5] <= 2)).all()) and bool((p[..., 5:] == 0).all())


def test_check_env_specs_linear_gaussian():
    model = LinearGaussian(state_dim=4, obs_dim=2)
    env = TransformedEnv(POMDPEnv(model, (2,), seed=0, max_steps=5, expose_state=True),
                         BeliefTransform(model, SIRFilter(), 8, seed=0))
    check_env_specs(env)


@pytest.mark.parametrize("batch_size", [(), (2, 3)], ids=["unbatched", "2d"])
def test_other_batch_shapes(batch_size):
    model = LightDark10D()
    env = TransformedEnv(POMDPEnv(model, batch_size, seed=0, max_steps=3, expose_state=True),
                         BeliefTransform(model, SIRFilter(), 7, seed=1))
    check_env_specs(env)
    roll = env.rollout(5, break_when_any_done=False)
    assert roll["next", "particles"].shape == (*batch_size, 5, 7, 10)
    lse = torch.logsumexp(roll["next", "particle_log_weights"], -1)
    torch.testing.assert_close(lse, torch.zeros_like(lse), rtol=0, atol=1e-5)


def test_step_updates_the_belief_with_the_filter():
    """One env step equals one SIRFilter.update on the env's action and next observation, with the
    transform's generator."""
    env = make_belief_env(3, 4, batch=2, num_particles=32)
    td = env.reset()
    td["action"] = torch.tensor([0, 5])
    out = env.step(td)
    nxt = out["next"]
    assert nxt["particles"].shape == (2, 32, 10)
    lse = torch.logsumexp(nxt["particle_log_weights"], -1)
    torch.testing.assert_close(lse, torch.zeros(2), rtol=0, atol=1e-5)
    # replay the update: the transform's generator was seeded with 4 and used once for the prior
    g = torch.Generator().manual_seed(4)
    model = env.transform.model
    prior = SIRFilter().init(model, (2,), 32, g)
    torch.testing.assert_close(prior.particles, td["particles"])
    post = SIRFilter().update(model, ParticleBelief(td["particles"], td["particle_log_weights"]),
                              td["action"], nxt["observation"], g)
    torch.testing.assert_close(post.particles, nxt["particles"])
    torch.testing.assert_close(post.log_weights, nxt["particle_log_weights"])
    # the belief carries information: over the next steps its weighted mean is nearer the true
    # position than the prior mean was at the start (≈1.3-1.5 here, 10-D with 32 particles)
    prior_err = (td["particles"].mean(-2) - td["true_state"])[:, :5].norm(dim=-1)
    roll = env.rollout(7, cyclic_policy(), break_when_any_done=False, tensordict=env.step_mdp(out),
                       auto_reset=False)
    nxt_all = roll["next"]
    w = torch.softmax(nxt_all["particle_log_weights"], -1).unsqueeze(-1)
    err = ((w * nxt_all["particles"]).sum(-2) - nxt_all["true_state"])[..., :5].norm(dim=-1)  # [B, T]
    assert bool((err.mean(-1) < 0.8 * prior_err).all()), (err, prior_err)


def test_partial_reset_reinitialises_only_selected_rows():
    env = make_belief_env(5, 6, batch=4, num_particles=20, max_steps=None)
    td = env.reset()
    for t in range(3):
        td["action"] = torch.full((4,), t, dtype=torch.long)
        td = env.step_mdp(env.step(td))
    before_x = td["particles"].clone()
    before_w = td["particle_log_weights"].clone()
    assert not torch.allclose(before_w, torch.full_like(before_w, -math.log(20)))  # weights moved
    mask = torch.tensor([False, True, False, True])
    td["_reset"] = mask.unsqueeze(-1)
    # EnvBase.reset restores the rows not being reset from its input, so look at the transformed
    # env's own reset output too: the transform itself must keep those rows
    raw = env._reset(td.clone())
    assert torch.equal(raw["particles"][~mask], before_x[~mask])
    assert torch.equal(raw["particle_log_weights"][~mask], before_w[~mask])
    out = env.reset(td)
    assert torch.equal(out["particles"][~mask], before_x[~mask])
    assert torch.equal(out["particle_log_weights"][~mask], before_w[~mask])
    assert not bool((out["particles"][mask] == before_x[mask]).all())
    torch.testing.assert_close(out["particle_log_weights"][mask], torch.full((2, 20), -math.log(20)))
    p = out["particles"][mask]
    assert bool(((p[..., :5] >= 0) & (p[..., :5] <= 2)).all()) and bool((p[..., 5:] == 0).all())
    # the env rows were reset in step with the beliefs
    assert out["step_count"].squeeze(-1).tolist() == [3, 0, 3, 0]
    # and stepping on continues from the kept beliefs
    out["action"] = torch.zeros(4, dtype=torch.long)
    nxt = env.step(out)["next"]
    assert nxt["particles"].shape == (4, 20, 10)


def test_reset_places_the_prior_around_each_start_under_exploring_starts():
    """With a model whose prior is placed around the start (``prior_width``), every reset row's
    particles lie within ``prior_width`` of that row's start, partial resets included."""
    model = LightDark10D(start_low=0.0, start_high=10.0, prior_width=0.5)
    env = TransformedEnv(POMDPEnv(model, batch_size=(6,), seed=1, max_steps=None, expose_state=True),
                         BeliefTransform(model, SIRFilter(), 16, seed=2))
    td = env.reset()

    def near(out, rows):
        gap = out["particles"][rows][..., :5] - out["true_state"][rows][:, None, :5]
        return bool((gap.abs() <= 0.5).all())

    assert near(td, slice(None))
    mask = torch.tensor([True, False, False, True, False, False])
    td["_reset"] = mask.unsqueeze(-1)
    out = env.reset(td)
    assert near(out, mask)


def test_auto_reset_in_rollout_reinitialises_done_rows():
    env = make_belief_env(7, 8, batch=2, num_particles=20, max_steps=4)
    roll = env.rollout(6, cyclic_policy(), break_when_any_done=False)
    # step 4 (index 4) starts from a freshly reset env: the root belief there is a new prior
    torch.testing.assert_close(roll["particle_log_weights"][:, 4], torch.full((2, 20), -math.log(20)))
    p = roll["particles"][:, 4]
    assert bool((p[..., 5:] == 0).all())
    # the belief at the end of the episode was not the prior any more
    assert not bool((roll["next", "particles"][:, 3][..., 5:] == 0).all())


def test_auto_partial_reset_in_rollout_keeps_the_other_rows():
    """Rows whose episodes end at different steps: the rollout's automatic partial reset gives the
    done row a new prior and leaves the other row's belief as the filter left it."""
    env = make_belief_env(9, 10, batch=2, num_particles=20, max_steps=4)
    td = env.reset()
    for t in range(2):
        td["action"] = torch.full((2,), t, dtype=torch.long)
        td = env.step_mdp(env.step(td))
    td["_reset"] = torch.tensor([[True], [False]])
    td = env.reset(td)  # row 0 restarts: row 1 now ends two steps before row 0
    assert td["step_count"].squeeze(-1).tolist() == [0, 2]
    roll = env.rollout(4, cyclic_policy(), break_when_any_done=False, tensordict=td, auto_reset=False)
    truncated = roll["next", "truncated"].squeeze(-1)
    assert truncated.tolist() == [[False, False, False, True], [False, True, False, False]]
    # step 2 starts after row 1 was reset: row 1 holds a new prior, row 0 continues
    prior = torch.full((20,), -math.log(20))
    torch.testing.assert_close(roll["particle_log_weights"][1, 2], prior)
    assert bool((roll["particles"][1, 2][:, 5:] == 0).all())
    assert torch.equal(roll["particles"][0, 2], roll["next", "particles"][0, 1])
    assert torch.equal(roll["particle_log_weights"][0, 2], roll["next", "particle_log_weights"][0, 1])
    # and row 1's belief before the reset was a filtered one, not a prior
    assert not bool((roll["next", "particles"][1, 1][:, 5:] == 0).all())


def test_wrong_model_dimensions_are_rejected():
    env_model = LightDark10D()
    base = POMDPEnv(env_model, (2,), seed=0, max_steps=5, expose_state=True)
    with pytest.raises(ValueError, match="BeliefTransform.model") as info:
        env = TransformedEnv(base, BeliefTransform(LinearGaussian(state_dim=3), SIRFilter(), 10, seed=0))
        env.observation_spec  # specs are transformed lazily in some torchrl versions
    assert "obs_dim" in str(info.value)
    # the same obs_dim but another state_dim
    base = POMDPEnv(env_model, (2,), seed=0, max_steps=5, expose_state=True)
    with pytest.raises(ValueError, match="BeliefTransform.model") as info:
        env = TransformedEnv(base, BeliefTransform(LinearGaussian(state_dim=3, obs_dim=5), SIRFilter(), 10))
        env.observation_spec
    assert "state_dim" in str(info.value)


class NaNObservationModel(LightDark10D):
    """Light-Dark whose sensor fails (returns NaN) for the second env after the first step."""

    def observe(self, s_next, a, generator=None):
        o = super().observe(s_next, a, generator)
        if o.shape[0] == 2 and bool((a == 7).any()):
            o = o.clone()
            o[1] = float("nan")
        return o


def test_nan_observation_reaching_the_filter_is_rejected():
    env = TransformedEnv(
        POMDPEnv(NaNObservationModel(), (2,), seed=0, max_steps=5, expose_state=True),
        BeliefTransform(LightDark10D(), SIRFilter(), 10, seed=0),
    )
    td = env.reset()
    td["action"] = torch.tensor([0, 1])
    td = env.step_mdp(env.step(td))  # a good step
    td["action"] = torch.tensor([7, 7])
    with pytest.raises(ValueError) as info:
        env.step(td)
    assert str(info.value).startswith("observation:"), str(info.value)


def test_transform_without_reset_raises():
    env = make_belief_env(0, 0)
    td = TensorDict({"action": torch.zeros(2, dtype=torch.long)}, batch_size=[2])
    env.base_env.reset()
    with pytest.raises(KeyError, match="particles"):
        env.step(td)


def test_transform_rejects_bad_arguments():
    with pytest.raises(TypeError, match="filter"):
        BeliefTransform(LightDark10D(), object(), 10)
    with pytest.raises(ValueError, match="num_particles"):
        BeliefTransform(LightDark10D(), SIRFilter(), 0)
    with pytest.raises(NotImplementedError):
        BeliefTransform(LightDark10D(), SIRFilter(), 4)(TensorDict({}, batch_size=[]))


def test_same_seeds_give_identical_beliefs_and_different_seeds_do_not():
    def run(env_seed, filter_seed):
        env = make_belief_env(env_seed, filter_seed, batch=2, num_particles=20)
        return env.rollout(12, belief_policy(), break_when_any_done=False)

    a, b = run(1, 2), run(1, 2)
    assert torch.equal(a["next", "particles"], b["next", "particles"])
    assert torch.equal(a["action"], b["action"])
    c = run(1, 3)  # same env, another filter seed
    assert torch.equal(c["true_state"][:, 0], a["true_state"][:, 0])
    assert not torch.equal(c["next", "particles"], a["next", "particles"])


def test_env_set_seed_seeds_a_filter_without_its_own_seed():
    """With seed=None the filter draws from the base env's generator, so env.set_seed covers it."""
    env = make_belief_env(0, None)
    env.set_seed(5)
    a = env.rollout(6, cyclic_policy(), break_when_any_done=False)
    env.set_seed(5)
    b = env.rollout(6, cyclic_policy(), break_when_any_done=False)
    assert torch.equal(a["next", "particles"], b["next", "particles"])
    assert torch.equal(a["next", "particle_log_weights"], b["next", "particle_log_weights"])
    other = make_belief_env(0, None)
    other.set_seed(5)
    assert torch.equal(other.rollout(6, cyclic_policy(), break_when_any_done=False)["next", "particles"],
                       a["next", "particles"])
    env.set_seed(6)
    c = env.rollout(6, cyclic_policy(), break_when_any_done=False)
    assert not torch.equal(a["next", "particles"], c["next", "particles"])


def test_set_seed_reseeds_the_filter():
    env = make_belief_env(0, None)
    env.transform.set_seed(42)
    env.base_env.set_seed(1)
    a = env.rollout(5, cyclic_policy(), break_when_any_done=False)
    env.transform.set_seed(42)
    env.base_env.set_seed(1)
    b = env.rollout(5, cyclic_policy(), break_when_any_done=False)
    assert torch.equal(a["next", "particles"], b["next", "particles"])


def _seeded_rollout(env, seed: int, steps: int = 6) -> TensorDict:
    env.set_seed(seed)
    return env.rollout(steps, cyclic_policy(), break_when_any_done=False)


def test_env_set_seed_twice_reproduces_a_transform_with_its_own_seed():
    """BeliefTransform(seed=5): env.set_seed(s) restarts its generator, so the same s reproduces
    the particles however often it is called, on this env or on a fresh one."""
    env = make_belief_env(0, 5)
    a = _seeded_rollout(env, 3)
    b = _seeded_rollout(env, 3)
    assert torch.equal(a["next", "particles"], b["next", "particles"])
    assert torch.equal(a["next", "particle_log_weights"], b["next", "particle_log_weights"])
    fresh = make_belief_env(99, 5)  # other construction seed for the env, same transform seed
    assert torch.equal(_seeded_rollout(fresh, 3)["next", "particles"], a["next", "particles"])
    # another env seed, or another transform seed under the same env seed, gives other particles
    assert not torch.equal(_seeded_rollout(env, 4)["next", "particles"], a["next", "particles"])
    other_filter = _seeded_rollout(make_belief_env(0, 6), 3)
    assert torch.equal(other_filter["true_state"], a["true_state"])
    assert not torch.equal(other_filter["next", "particles"], a["next", "particles"])
    # transform.set_seed gives the transform its constructor-like seed back: env.set_seed no longer
    # applies, and the particles are those of a transform seeded with 5 that no env.set_seed reached
    env.base_env.set_seed(3)
    env.transform.set_seed(5)
    c = env.rollout(6, cyclic_policy(), break_when_any_done=False)
    ref = make_belief_env(0, 5)
    ref.base_env.set_seed(3)
    assert torch.equal(c["next", "particles"],
                       ref.rollout(6, cyclic_policy(), break_when_any_done=False)["next", "particles"])
    assert not torch.equal(c["next", "particles"], a["next", "particles"])


def test_belief_seed_differs_from_the_env_seed():
    """The filter's noise must not replay the env's noise: its seed is derived from the env seed,
    differs from it and from the seeds a batched env hands its other sub-envs."""
    from torchrl._utils import seed_generator

    for s in (0, 1, 3, 12345):
        seeds = {s, seed_generator(s), seed_generator(seed_generator(s))}
        assert derive_seed(s, None) not in seeds
        assert derive_seed(s, None) != derive_seed(s, 5)
        assert derive_seed(s, 5) == derive_seed(s, 5)
        assert 0 <= derive_seed(s, 5) < 2**63
    env = make_belief_env(0, 5)
    env.set_seed(3)
    env.reset()
    assert env.transform._generator.initial_seed() == derive_seed(3, 5)
    assert env.base_env.generator.initial_seed() == 3


@pytest.mark.parametrize("placement", ["compose", "append_transform"])
def test_env_set_seed_reaches_a_transform_inside_a_compose(placement):
    model = LightDark10D()
    transform = BeliefTransform(model, SIRFilter(), 12, seed=5)
    base = POMDPEnv(model, batch_size=(2,), seed=0, max_steps=8, expose_state=True)
    if placement == "compose":
        env = TransformedEnv(base, Compose(StepCounter(), transform))
    else:
        env = TransformedEnv(base, StepCounter())
        env.append_transform(transform)
    a = _seeded_rollout(env, 3)["next", "particles"]
    assert a.shape == (2, 6, 12, 10)
    assert torch.equal(_seeded_rollout(env, 3)["next", "particles"], a)
    assert not torch.equal(_seeded_rollout(env, 4)["next", "particles"], a)


@pytest.mark.parametrize("filter_seed", [None, 5], ids=["no-transform-seed", "transform-seed-5"])
def test_env_set_seed_seeds_a_transform_on_top_of_a_serial_env(filter_seed):
    env = belief_on_top(SerialEnv, filter_seed)
    try:
        a = _seeded_rollout(env, 3)
        assert a["next", "particles"].shape == (2, 2, 6, 20, 10)
        assert torch.equal(_seeded_rollout(env, 3)["next", "particles"], a["next", "particles"])
        assert torch.equal(_seeded_rollout(env, 3)["next", "particle_log_weights"],
                           a["next", "particle_log_weights"])
        assert not torch.equal(_seeded_rollout(env, 4)["next", "particles"], a["next", "particles"])
    finally:
        env.close()
    fresh = belief_on_top(SerialEnv, filter_seed)  # a second, identically seeded run
    try:
        assert torch.equal(_seeded_rollout(fresh, 3)["next", "particles"], a["next", "particles"])
    finally:
        fresh.close()


def test_env_set_seed_seeds_transforms_inside_the_sub_envs_of_a_serial_env():
    """The transform in each sub-env (one with its own seed, one sharing its env's generator)."""
    env = SerialEnv(2, FACTORIES)
    try:
        a = _seeded_rollout(env, 3, steps=10)
        assert torch.equal(_seeded_rollout(env, 3, steps=10)["next", "particles"], a["next", "particles"])
        assert not torch.equal(_seeded_rollout(env, 4, steps=10)["next", "particles"], a["next", "particles"])
    finally:
        env.close()


# ---------------------------------------------------------------------------------------------
# Reproducibility across processes
# ---------------------------------------------------------------------------------------------

ROLLOUT_STEPS = 30


def _single_process_reference(policy_fn, steps: int = ROLLOUT_STEPS) -> torch.Tensor:
    """[n_envs, batch, steps, N, d]: each factory's env rolled out on its own, in this process."""
    out = []
    for factory in FACTORIES:
        env = factory()
        out.append(env.rollout(steps, policy_fn(), break_when_any_done=False)["next", "particles"])
    return torch.stack(out)


@pytest.mark.slow
def test_serial_and_parallel_env_give_identical_particles():
    reference = _single_process_reference(cyclic_policy)
    serial = SerialEnv(2, FACTORIES)
    try:
        s = serial.rollout(ROLLOUT_STEPS, cyclic_policy(), break_when_any_done=False)
    finally:
        serial.close()
    parallel = ParallelEnv(2, FACTORIES, mp_start_method="spawn")
    try:
        p = parallel.rollout(ROLLOUT_STEPS, cyclic_policy(), break_when_any_done=False)
    finally:
        parallel.close()
    assert s["next", "particles"].shape == (2, 2, ROLLOUT_STEPS, 20, 10)
    # the episodes were truncated and restarted (max_steps=8) inside the rollout
    assert bool(s["next", "truncated"].any())
    assert torch.equal(s["next", "particles"], p["next", "particles"])
    assert torch.equal(s["next", "particle_log_weights"], p["next", "particle_log_weights"])
    assert torch.equal(s["next", "particles"], reference)
    # the two sub-envs were seeded differently
    assert not torch.equal(s["next", "particles"][0], s["next", "particles"][1])


def _collect(collector, n_batches: int) -> list:
    out = []
    try:
        for i, data in enumerate(collector):
            out.append(data.clone())
            if i + 1 == n_batches:
                break
    finally:
        collector.shutdown()
    return out


@pytest.mark.slow
def test_collectors_give_identical_particles_to_a_single_process_run():
    frames_per_env = 2 * 12  # batch 2 x 12 steps per collection, two collections = 24 steps
    n_batches = 2
    steps = 12 * n_batches
    reference = _single_process_reference(belief_policy, steps)  # [worker, batch, steps, N, d]

    # Collector: one process, one factory at a time
    for w, factory in enumerate(FACTORIES):
        batches = _collect(
            Collector(factory, belief_policy(), frames_per_batch=frames_per_env,
                      total_frames=frames_per_env * n_batches, auto_register_policy_transforms=False),
            n_batches,
        )
        got = torch.cat([b["next", "particles"] for b in batches], dim=1)  # [batch, steps, N, d]
        assert got.shape == (2, steps, 20, 10)
        assert torch.equal(got, reference[w]), f"Collector, factory {w}"

    # MultiSyncCollector: two worker processes, each with its own factory
    multi = MultiSyncCollector(
        FACTORIES,
        belief_policy(),
        frames_per_batch=2 * frames_per_env,
        total_frames=2 * frames_per_env * n_batches,
        cat_results="stack",
        num_threads=torch.get_num_threads(),
        num_sub_threads=1,
        auto_register_policy_transforms=False,
    )
    batches = _collect(multi, n_batches)
    got = torch.cat([b["next", "particles"] for b in batches], dim=-3)  # time is the 3rd-last dim
    assert got.shape == (2, 2, steps, 20, 10)
    assert torch.equal(got, reference)


@pytest.mark.slow
@pytest.mark.parametrize("filter_seed", [None, 5], ids=["no-transform-seed", "transform-seed-5"])
def test_env_set_seed_seeds_a_transform_on_top_of_a_parallel_env(filter_seed):
    """ParallelEnv, the usual placement: env.set_seed(s) twice gives the same particles, and the
    same as the same transform on top of a SerialEnv of the same sub-envs."""
    parallel = belief_on_top(ParallelEnv, filter_seed)
    try:
        a = _seeded_rollout(parallel, 3, steps=10)
        b = _seeded_rollout(parallel, 3, steps=10)
        c = _seeded_rollout(parallel, 4, steps=10)
    finally:
        parallel.close()
    serial = belief_on_top(SerialEnv, filter_seed)
    try:
        s = _seeded_rollout(serial, 3, steps=10)
    finally:
        serial.close()
    assert a["next", "particles"].shape == (2, 2, 10, 20, 10)
    assert bool(a["next", "truncated"].any())  # episodes restarted inside the rollout
    assert torch.equal(a["next", "particles"], b["next", "particles"])
    assert torch.equal(a["next", "particle_log_weights"], b["next", "particle_log_weights"])
    assert torch.equal(a["next", "particles"], s["next", "particles"])
    assert not torch.equal(a["next", "particles"], c["next", "particles"])


@pytest.mark.slow
def test_env_set_seed_seeds_transforms_inside_the_workers_of_a_parallel_env():
    serial = SerialEnv(2, FACTORIES)
    try:
        s = _seeded_rollout(serial, 3, steps=10)
    finally:
        serial.close()
    parallel = ParallelEnv(2, FACTORIES, mp_start_method="spawn")
    try:
        a = _seeded_rollout(parallel, 3, steps=10)
        b = _seeded_rollout(parallel, 3, steps=10)
    finally:
        parallel.close()
    assert torch.equal(a["next", "particles"], b["next", "particles"])
    assert torch.equal(a["next", "particles"], s["next", "particles"])


def _collect_after_seed(collector, seed: int, n_batches: int = 2) -> torch.Tensor:
    """collector.set_seed(seed), then a reset (the collector reset its envs when it was built,
    before any seed), then ``n_batches`` batches of particles."""
    collector.set_seed(seed)
    collector.reset()
    out = []
    for i, data in enumerate(collector):
        out.append(data["next", "particles"].clone())
        if i + 1 == n_batches:
            break
    return torch.cat(out, dim=-3)


@pytest.mark.slow
def test_collector_set_seed_seeds_a_transform_on_top_of_a_batched_env():
    runs = {}
    for kind in (SerialEnv, ParallelEnv):
        collector = Collector(belief_on_top(kind, None), belief_policy(), frames_per_batch=2 * 2 * 6,
                              total_frames=-1, auto_register_policy_transforms=False)
        try:
            runs[kind] = [_collect_after_seed(collector, s) for s in (7, 7, 8)]
        finally:
            collector.shutdown()
    a, b, c = runs[ParallelEnv]
    assert a.shape == (2, 2, 12, 20, 10)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    assert torch.equal(a, runs[SerialEnv][0])


@pytest.mark.slow
def test_multi_sync_collector_set_seed_seeds_the_workers_transforms():
    """Each worker holds a transform on top of a SerialEnv with no seed of its own (it would draw
    OS entropy): two identically seeded runs of a two-worker collector give the same particles."""

    def run(seed: int) -> torch.Tensor:
        collector = MultiSyncCollector(
            [functools.partial(belief_on_top, SerialEnv, None)] * 2, belief_policy(),
            frames_per_batch=2 * 4 * 6, total_frames=-1, cat_results="stack",
            num_threads=torch.get_num_threads(), num_sub_threads=1, auto_register_policy_transforms=False,
        )
        try:
            return _collect_after_seed(collector, seed)
        finally:
            collector.shutdown()

    a = run(7)
    assert a.shape == (2, 2, 2, 12, 20, 10)  # [worker, sub-env, batch, time, N, d]
    assert torch.equal(a, run(7))
    assert not torch.equal(a[0], a[1])  # the workers were seeded differently


def test_a_model_with_other_actions_is_refused_when_the_transform_joins_the_env():
    from torchrl.envs import TransformedEnv

    from escort_rl.belief import SIRFilter
    from escort_rl.envs import POMDPEnv
    from escort_rl.models import LightDark10D

    class FourActions(LightDark10D):
        n_actions = 4

    with pytest.raises(ValueError, match=r"^BeliefTransform.model: model.n_actions is 4 but the env's 'action' has 10"):
        TransformedEnv(POMDPEnv(LightDark10D(), batch_size=(2,), expose_state=True),
                       BeliefTransform(FourActions(), SIRFilter(), 8))
