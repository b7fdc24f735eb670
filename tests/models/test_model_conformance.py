"""Model conformance: every domain model follows :class:`escort_rl.models.POMDPModel` the same way.

The per-model files test each model's own law (densities by hand, paper constants, rates);
``tests/belief/test_observation_score.py`` checks the closed-form scores against autograd on filter-shaped
points. This suite checks, uniformly for every model, what envs, filters and planners rely on:

- shapes and dtypes of every protocol method for batch shapes ``()``, ``(3,)`` and ``(2, 4)``;
- the filters' broadcasting: particles ``[*B, N, d]`` against observations ``[*B, obs_dim]`` (as
  ``[*B, 1, obs_dim]``), actions ``[*B, N]`` or ``[*B, 1]``, and the prior-mixture pairing;
- finite outputs along a rollout and on the belief's particles;
- ``observation_score`` (where a model has one) equal to the autograd gradient of
  ``observation_log_prob`` at every batch shape, unbatched included;
- generator determinism: the same seed gives the same draws, the stream advances, and a method
  given a generator leaves torch's global generator alone.

Every test draws from the ``per_test_generator`` / ``per_test_seed`` fixtures (``tests/conftest.py``),
so ``pytest --seed-offset K`` runs the suite on other draws.
"""

from __future__ import annotations

import inspect

import pytest
import torch

import escort_rl.models as models
from escort_rl.models import (
    HiddenGoal,
    KidnappedRobot20D,
    LightDark1D,
    LightDark10D,
    LightDark10DContinuous,
    LinearGaussian,
    MultiTargetTracking20D,
    POMDPModel,
    POPGymCartPole,
    POPGymPendulum,
    check_model,
)
from escort_rl.models.protocol import action_shape, is_continuous, per_particle, random_action

MODELS = {
    "lightdark10d": LightDark10D,
    "lightdark-npos12": lambda: LightDark10D(n_pos=12),  # the family in more dimensions
    "lightdark1d": LightDark1D,
    "mtt20d": MultiTargetTracking20D,
    "kidnapped20d": KidnappedRobot20D,
    "lineargaussian": LinearGaussian,
    "lineargaussian-4x2": lambda: LinearGaussian(state_dim=4, obs_dim=2),  # obs_dim != state_dim
    "lightdark10d-continuous": LightDark10DContinuous,  # real actions [*B, 5]
    "popgym-cartpole": lambda: POPGymCartPole(obs_noise=0.2),
    "popgym-pendulum": lambda: POPGymPendulum(obs_noise=0.2),  # real actions [*B, 1]
    "hidden-goal": HiddenGoal,
    "hidden-goal-dim12-modes6": lambda: HiddenGoal(dim=12, modes=6, beacon_distance=0.5),  # near the beacon
}
SHAPES = [(), (3,), (2, 4)]
SHAPE_IDS = ["unbatched", "3", "2x4"]
N = 6  # particles per belief


@pytest.fixture(scope="module", params=list(MODELS))
def model(request):
    return MODELS[request.param]()


def actions(model, shape, g: torch.Generator) -> torch.Tensor:
    """Uniform actions ``[*shape]`` (``[*shape, action_dim]`` for real ones)."""
    return random_action(model, tuple(shape), g)


def per_belief(model, a: torch.Tensor) -> torch.Tensor:
    """One action per belief, broadcastable over its particles: ``[*B, 1]`` (``[*B, 1, action_dim]``)."""
    return a.unsqueeze(-1 - len(action_shape(model)))


def filter_points(model, batch, g: torch.Generator):
    """As in a filter update: prior particles ``x [*B, N, d]``, one action per belief ``a [*B]``,
    the predicted particles ``x' [*B, N, d]`` and the observation ``o [*B, obs_dim]`` of the true
    next state."""
    x = model.initial_belief(tuple(batch), N, g)
    a = actions(model, batch, g)
    a_bn = per_particle(model, a, (*batch, N))
    x_next = model.transition(x, a_bn, g)
    o = model.observe(model.transition(model.initial_state(tuple(batch), g), a, g), a, g)
    return x, a, x_next, o


def test_every_model_of_the_package_is_in_the_suite():
    """A model added to ``escort_rl.models`` must join this suite."""
    exported = {obj for name in models.__all__ if inspect.isclass(obj := getattr(models, name))
                and obj is not POMDPModel and all(hasattr(obj, f) for f in ("transition", "observe"))}
    covered = {type(make()) for make in MODELS.values()}
    assert exported == covered, exported ^ covered


def test_protocol_attributes(model):
    check_model(model)
    assert isinstance(model, POMDPModel)
    for name in ("state_dim", "obs_dim", "action_dim" if is_continuous(model) else "n_actions"):
        assert getattr(model, name) >= 1, name
    tril = model.transition_scale_tril()
    d = model.state_dim
    assert tril.shape == (d, d) and tril.dtype == torch.float32
    assert torch.isfinite(tril).all()
    assert torch.equal(tril, torch.tril(tril)) and bool((torch.diagonal(tril) >= 0).all())


@pytest.mark.parametrize("shape", SHAPES, ids=SHAPE_IDS)
def test_shapes_and_dtypes(model, shape, per_test_generator):
    d, m = model.state_dim, model.obs_dim
    s = model.initial_state(shape, per_test_generator)
    assert s.shape == (*shape, d) and s.dtype == torch.float32
    belief = model.initial_belief(shape, N, per_test_generator)
    assert belief.shape == (*shape, N, d) and belief.dtype == torch.float32
    a = actions(model, shape, per_test_generator)
    mean = model.transition_mean(s, a)
    assert mean.shape == (*shape, d) and mean.dtype == torch.float32
    s_next = model.transition(s, a, per_test_generator)
    assert s_next.shape == (*shape, d) and s_next.dtype == torch.float32
    log_t = model.transition_log_prob(s_next, s, a)
    assert log_t.shape == shape and log_t.dtype == torch.float32
    o = model.observe(s_next, a, per_test_generator)
    assert o.shape == (*shape, m) and o.dtype == torch.float32
    log_o = model.observation_log_prob(o, s_next, a)
    assert log_o.shape == shape and log_o.dtype == torch.float32
    r = model.reward(s, a, s_next)
    assert r.shape == shape and r.dtype == torch.float32
    done = model.is_terminal(s_next)
    assert done.shape == shape and done.dtype == torch.bool
    for name, value in (("initial_state", s), ("initial_belief", belief), ("transition", s_next),
                        ("observe", o), ("transition_log_prob", log_t), ("observation_log_prob", log_o),
                        ("reward", r)):
        assert torch.isfinite(value).all(), name


@pytest.mark.parametrize("batch", [(3,), (2, 4)], ids=["3", "2x4"])
def test_particles_broadcast_against_observations(model, batch, per_test_generator):
    """The filter's calls equal the same calls made one particle at a time."""
    x, a, x_next, o = filter_points(model, batch, per_test_generator)
    a_bn = per_particle(model, a, (*batch, N))
    lp = model.observation_log_prob(o.unsqueeze(-2), x_next, a_bn)
    assert lp.shape == (*batch, N)
    # an action per belief, broadcast over its particles, gives the same values
    torch.testing.assert_close(model.observation_log_prob(o.unsqueeze(-2), x_next, per_belief(model, a)), lp)
    torch.testing.assert_close(model.transition_mean(x, per_belief(model, a)), model.transition_mean(x, a_bn))
    flat_o, flat_x = o.reshape(-1, model.obs_dim), x_next.reshape(-1, N, model.state_dim)
    flat_a = a.reshape(-1, *action_shape(model))
    flat_lp = lp.reshape(-1, N)
    for i in range(flat_x.shape[0]):
        for j in range(N):
            torch.testing.assert_close(flat_lp[i, j], model.observation_log_prob(flat_o[i], flat_x[i, j], flat_a[i]))
    # the prior-mixture pairing: every predicted particle against every prior particle, [*B, N, N]
    tl = model.transition_log_prob(x_next.unsqueeze(-2), x.unsqueeze(-3), a_bn.unsqueeze(-2 - len(action_shape(model))))
    assert tl.shape == (*batch, N, N)
    flat_tl, flat_prior = tl.reshape(-1, N, N), x.reshape(-1, N, model.state_dim)
    for i in range(flat_x.shape[0]):
        for j in range(N):
            for k in (0, j, N - 1):
                torch.testing.assert_close(flat_tl[i, j, k],
                                           model.transition_log_prob(flat_x[i, j], flat_prior[i, k], flat_a[i]))
    if hasattr(model, "observation_score"):
        score = model.observation_score(o.unsqueeze(-2), x_next, a_bn)
        assert score.shape == x_next.shape and score.dtype == torch.float32
        torch.testing.assert_close(score[(0,) * len(batch) + (1,)],
                                   model.observation_score(flat_o[0], flat_x[0, 1], flat_a[0]))


def test_outputs_are_finite_along_a_rollout(model, per_test_generator):
    """Ten steps of 16 envs under random actions, and a belief's particles at every step: states,
    observations, rewards and the densities a filter evaluates stay finite."""
    batch = (16,)
    s = model.initial_state(batch, per_test_generator)
    x = model.initial_belief(batch, N, per_test_generator)
    for step in range(10):
        a = actions(model, batch, per_test_generator)
        s_next = model.transition(s, a, per_test_generator)
        o = model.observe(s_next, a, per_test_generator)
        x_next = model.transition(x, per_particle(model, a, (*batch, N)), per_test_generator)
        one = per_belief(model, a)
        values = {
            "state": s_next, "observation": o, "reward": model.reward(s, a, s_next),
            "transition_log_prob": model.transition_log_prob(s_next, s, a),
            "observation_log_prob(truth)": model.observation_log_prob(o, s_next, a),
            "observation_log_prob(particles)": model.observation_log_prob(o.unsqueeze(-2), x_next, one),
            "transition_log_prob(particles)": model.transition_log_prob(x_next, x, one),
        }
        if hasattr(model, "observation_score"):
            values["observation_score"] = model.observation_score(o.unsqueeze(-2), x_next, per_belief(model, a))
        for name, value in values.items():
            assert torch.isfinite(value).all(), f"{name} at step {step}"
        s, x = s_next, x_next


def _autograd_score(model, o, s, a):
    s = s.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(model.observation_log_prob(o, s, a).sum(), s)
    return grad


# observation_score is optional in the protocol: the models that have one
SCORED = [name for name, make in MODELS.items() if hasattr(make(), "observation_score")]


WITHOUT_SCORE: set[str] = {"popgym-cartpole", "popgym-pendulum"}  # models here without a closed-form score


def test_the_scored_models_are_known():
    """A closed form lost by a rename would silently leave the check below: list such models above."""
    assert set(MODELS) - set(SCORED) == WITHOUT_SCORE


@pytest.mark.parametrize("shape", SHAPES, ids=SHAPE_IDS)
@pytest.mark.parametrize("name", SCORED)
def test_observation_score_is_the_autograd_gradient_at_every_batch_shape(name, shape, per_test_generator):
    model = MODELS[name]()
    s = model.initial_state(shape, per_test_generator)
    a = actions(model, shape, per_test_generator)
    s_next = model.transition(s, a, per_test_generator)
    o = model.observe(s_next, a, per_test_generator)
    # score at the truth and at points around it (the likelihood is informative there)
    for x in (s_next, s_next + 0.3 * torch.randn(s_next.shape, generator=per_test_generator)):
        got, want = model.observation_score(o, x, a), _autograd_score(model, o, x, a)
        assert got.shape == x.shape and got.dtype == torch.float32
        assert torch.isfinite(got).all()
        scale = want.abs().amax().clamp_min(1.0).item() if want.numel() else 1.0
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5 * scale)


RANDOM_METHODS = ["initial_state", "initial_belief", "transition", "observe"]


def _draw(model, method: str, g: torch.Generator) -> torch.Tensor:
    shape = (2, 3)
    if method == "initial_state":
        return model.initial_state(shape, g)
    if method == "initial_belief":
        return model.initial_belief(shape, N, g)
    fixed = torch.Generator().manual_seed(12345)  # the inputs do not depend on g
    s = model.initial_state(shape, fixed)
    a = actions(model, shape, fixed)
    if method == "transition":
        return model.transition(s, a, g)
    return model.observe(model.transition(s, a, fixed), a, g)


@pytest.mark.parametrize("method", RANDOM_METHODS)
def test_generator_determinism(model, method, per_test_seed):
    seed = per_test_seed
    first = _draw(model, method, torch.Generator().manual_seed(seed))
    again = _draw(model, method, torch.Generator().manual_seed(seed))
    assert torch.equal(first, again), "the same generator seed must give the same draws"
    g = torch.Generator().manual_seed(seed)
    one, two = _draw(model, method, g), _draw(model, method, g)
    assert torch.equal(one, first)
    assert not torch.equal(one, two), "the generator's stream must advance"
    other = _draw(model, method, torch.Generator().manual_seed(seed + 1))
    assert not torch.equal(first, other), "another seed must give other draws"
    # with a generator, the draws come from it alone: torch's global generator is neither used nor moved
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        expected_global = torch.rand(4)
        torch.manual_seed(seed)
        assert torch.equal(_draw(model, method, torch.Generator().manual_seed(seed)), first)
        assert torch.equal(torch.rand(4), expected_global), f"{method} drew from torch's global generator"
