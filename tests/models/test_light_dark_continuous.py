"""Light-Dark 10D with continuous actions (escort_rl.models.LightDark10DContinuous) and the protocol's
helpers for real actions (escort_rl.models.protocol): the dynamics against their closed form and
against the discrete model at the box's vertices, the unchanged observation law and reward, and
``is_continuous``, ``action_shape``, ``per_particle``, ``null_action``, ``check_action_box``."""

from __future__ import annotations

import pytest
import torch

from escort_rl.models import LightDark10D, LightDark10DContinuous, check_model
from escort_rl.models.protocol import (
    action_in_range,
    action_shape,
    check_action_box,
    describe_action_range,
    is_continuous,
    null_action,
    per_particle,
)


def random_states(g: torch.Generator, shape=(64,), n_pos: int = 5) -> torch.Tensor:
    """Positions across the light field, [-1, 11]^n_pos, and velocities in [-0.5, 0.5]."""
    pos = -1.0 + 12.0 * torch.rand(*shape, n_pos, generator=g)
    vel = -0.5 + torch.rand(*shape, n_pos, generator=g)
    return torch.cat([pos, vel], dim=-1)


def random_actions(model, g: torch.Generator, shape=(64,)) -> torch.Tensor:
    u = torch.rand(*shape, model.action_dim, generator=g)
    return model.action_low + (model.action_high - model.action_low) * u


# ---------------------------------------------------------------------------------------------
# dynamics
# ---------------------------------------------------------------------------------------------


def test_transition_mean_is_the_closed_form(per_test_generator):
    m = LightDark10DContinuous()
    g = per_test_generator
    s, a = random_states(g), random_actions(m, g)
    out = m.transition_mean(s, a)
    x, v = s[:, :5], s[:, 5:]
    expected = torch.cat([x + 0.1 * v, (1 - 0.1) * v + a], dim=-1)  # dt = 0.1, damping = 0.1 (paper)
    assert out.shape == (64, 10) and out.dtype == torch.float32
    torch.testing.assert_close(out, expected)
    # the parameters are read from the model, not hard-wired: another dt / damping
    m2 = LightDark10DContinuous(dt=0.3, damping=0.25, force=0.5)
    a2 = random_actions(m2, g)
    torch.testing.assert_close(m2.transition_mean(s, a2), torch.cat([x + 0.3 * v, 0.75 * v + a2], dim=-1))


def test_transition_mean_broadcasts_one_action_over_a_batch_of_states(per_test_generator):
    m = LightDark10DContinuous()
    s = random_states(per_test_generator, (3, 4))
    a = torch.tensor([0.1, -0.1, 0.0, 0.05, -0.02])
    out = m.transition_mean(s, a)
    assert out.shape == (3, 4, 10)
    torch.testing.assert_close(out, m.transition_mean(s, a.expand(3, 4, 5)))
    # and one state against a batch of actions
    acts = random_actions(m, per_test_generator, (7,))
    assert m.transition_mean(s[0, 0], acts).shape == (7, 10)
    torch.testing.assert_close(m.transition_mean(s[0, 0], acts), m.transition_mean(s[0, 0].expand(7, 10), acts))


@pytest.mark.parametrize("n_pos", [5, 6])
def test_at_the_vertices_the_dynamics_are_the_discrete_models(n_pos, per_test_generator):
    """The discrete action 2i pushes velocity i by +force and 2i + 1 by -force: the box's vertices
    ``±force·e_i``. Same mean, same log density, same draw for the same generator seed."""
    cont, disc = LightDark10DContinuous(n_pos=n_pos), LightDark10D(n_pos=n_pos)
    g = per_test_generator
    s = random_states(g, (16,), n_pos)
    s_next = random_states(g, (16,), n_pos)
    force = cont.params.force
    for i in range(n_pos):
        for sign, a_disc in ((1.0, 2 * i), (-1.0, 2 * i + 1)):
            a_cont = torch.zeros(16, n_pos)
            a_cont[:, i] = sign * force
            a_d = torch.full((16,), a_disc)
            torch.testing.assert_close(cont.transition_mean(s, a_cont), disc.transition_mean(s, a_d))
            torch.testing.assert_close(cont.transition_log_prob(s_next, s, a_cont),
                                       disc.transition_log_prob(s_next, s, a_d))
            seed = 1000 * i + a_disc
            torch.testing.assert_close(cont.transition(s, a_cont, torch.Generator().manual_seed(seed)),
                                       disc.transition(s, a_d, torch.Generator().manual_seed(seed)))
    # the vertices are exactly the box's corners along each axis
    assert torch.equal(cont.action_high, torch.full((n_pos,), force))
    assert torch.equal(cont.action_low, -cont.action_high)


def test_the_zero_action_and_a_sum_of_pushes(per_test_generator):
    """Force adds linearly: the continuous model can push every coordinate in one step."""
    m = LightDark10DContinuous()
    s = random_states(per_test_generator, (8,))
    zero = m.transition_mean(s, torch.zeros(8, 5))
    a = random_actions(m, per_test_generator, (8,))
    diff = m.transition_mean(s, a) - zero
    torch.testing.assert_close(diff[:, :5], torch.zeros(8, 5))
    torch.testing.assert_close(diff[:, 5:], a)


# ---------------------------------------------------------------------------------------------
# observation law, reward, goal: the discrete model's
# ---------------------------------------------------------------------------------------------


def test_observation_law_and_reward_are_the_discrete_models(per_test_generator):
    cont, disc = LightDark10DContinuous(), LightDark10D()
    g = per_test_generator
    s = random_states(g, (128,))
    s_next = random_states(g, (128,))
    a_cont, a_disc = random_actions(cont, g, (128,)), torch.randint(0, 10, (128,), generator=g)
    # a third of the next states near the light regions' centres, so that both branches (lit, and the
    # dark's swap mixture) are taken
    centres = cont.light_centres[torch.arange(42) % 7]
    s_next[:42, :5] = centres + 0.3 * torch.randn(42, 5, generator=g)
    assert bool((cont.light(s_next[:, :5]) < cont.dark_threshold).any())
    assert bool((cont.light(s_next[:, :5]) >= cont.dark_threshold).any())

    o_cont = cont.observe(s_next, a_cont, torch.Generator().manual_seed(5))
    o_disc = disc.observe(s_next, a_disc, torch.Generator().manual_seed(5))
    assert o_cont.shape == (128, 5)
    torch.testing.assert_close(o_cont, o_disc, rtol=0, atol=0)

    torch.testing.assert_close(cont.observation_log_prob(o_cont, s_next, a_cont),
                               disc.observation_log_prob(o_cont, s_next, a_disc), rtol=0, atol=0)
    torch.testing.assert_close(cont.observation_score(o_cont, s_next, a_cont),
                               disc.observation_score(o_cont, s_next, a_disc), rtol=0, atol=0)
    torch.testing.assert_close(cont.reward(s, a_cont, s_next), disc.reward(s, a_disc, s_next), rtol=0, atol=0)
    torch.testing.assert_close(cont.reward(s, a_cont, s_next),
                               -0.1 * torch.linalg.vector_norm(s_next[:, :5] - 8.0, dim=-1) - 0.1)
    assert torch.equal(cont.is_terminal(s_next), disc.is_terminal(s_next))
    assert torch.equal(cont.distance_to_goal(s_next), disc.distance_to_goal(s_next))


def test_start_distribution_and_prior_are_the_discrete_models():
    cont, disc = LightDark10DContinuous(), LightDark10D()
    torch.testing.assert_close(cont.initial_state((5,), torch.Generator().manual_seed(3)),
                               disc.initial_state((5,), torch.Generator().manual_seed(3)), rtol=0, atol=0)
    torch.testing.assert_close(cont.initial_belief((2,), 7, torch.Generator().manual_seed(4)),
                               disc.initial_belief((2,), 7, torch.Generator().manual_seed(4)), rtol=0, atol=0)
    assert (cont.state_dim, cont.obs_dim) == (disc.state_dim, disc.obs_dim) == (10, 5)


# ---------------------------------------------------------------------------------------------
# the protocol's helpers for real actions
# ---------------------------------------------------------------------------------------------


def test_check_model_and_the_action_attributes():
    m = LightDark10DContinuous()
    check_model(m)
    assert m.n_actions is None and m.action_dim == 5
    assert m.action_low.shape == m.action_high.shape == (5,)
    assert m.action_low.dtype == m.action_high.dtype == torch.float32
    low, high = check_action_box(m)
    assert torch.equal(low, m.action_low) and torch.equal(high, m.action_high)
    assert is_continuous(m) and not is_continuous(LightDark10D())
    assert action_shape(m) == (5,) and action_shape(LightDark10D()) == ()


def test_n_pos_6_gives_action_dim_6():
    m = LightDark10DContinuous(n_pos=6)
    check_model(m)
    assert (m.state_dim, m.obs_dim, m.action_dim, m.n_actions) == (12, 6, 6, None)
    assert is_continuous(m) and action_shape(m) == (6,)
    assert m.action_low.shape == m.action_high.shape == (6,)
    s = torch.zeros(3, 12)
    assert m.transition_mean(s, torch.full((3, 6), 0.1)).shape == (3, 12)
    # the class attribute is the paper's size; an instance of another size does not change it
    assert LightDark10DContinuous().action_dim == 5 and LightDark10DContinuous.action_dim == 5


def test_force_sets_the_box_and_a_non_positive_force_is_refused():
    m = LightDark10DContinuous(force=0.25)
    assert torch.equal(m.action_high, torch.full((5,), 0.25)) and torch.equal(m.action_low, torch.full((5,), -0.25))
    for bad in (0.0, -0.1):
        with pytest.raises(ValueError, match=r"^LightDark10DContinuous\.force:"):
            LightDark10DContinuous(force=bad)


@pytest.mark.parametrize("batch", [(), (3,), (2, 4)])
def test_per_particle_shapes(batch):
    cont, disc = LightDark10DContinuous(), LightDark10D()
    n = 6
    a = torch.randn(*batch, 5)
    out = per_particle(cont, a, (*batch, n))
    assert out.shape == (*batch, n, 5)
    for k in range(n):
        assert torch.equal(out[..., k, :], a)
    i = torch.randint(0, 10, batch)
    out_d = per_particle(disc, i, (*batch, n))
    assert out_d.shape == (*batch, n)
    assert torch.equal(out_d, i.unsqueeze(-1).expand(*batch, n))
    # a view, no copy
    assert out.data_ptr() == a.data_ptr()


def test_null_action_is_zero_inside_the_box():
    m = LightDark10DContinuous()
    a = null_action(m)
    assert a.shape == (5,) and a.dtype == torch.float32 and torch.equal(a, torch.zeros(5))
    batch = null_action(m, (2, 3))
    assert batch.shape == (2, 3, 5)
    assert bool(action_in_range(m, batch).all())
    d = null_action(LightDark10D(), (4,))
    assert d.shape == (4,) and d.dtype == torch.int64 and torch.equal(d, torch.zeros(4, dtype=torch.int64))


def test_null_action_is_clamped_into_a_box_without_zero():
    m = LightDark10DContinuous()
    m.action_low = torch.tensor([0.5, -2.0, -1.0, 0.1, -0.3])
    m.action_high = torch.tensor([1.0, -1.0, 1.0, 0.2, 0.3])
    a = null_action(m, (3,))
    assert a.shape == (3, 5)
    assert torch.equal(a[0], torch.tensor([0.5, -1.0, 0.0, 0.1, 0.0]))
    assert bool(action_in_range(m, a).all())


def test_action_in_range_and_its_message():
    m = LightDark10DContinuous()
    a = torch.tensor([[0.1, -0.1, 0.0, 0.05, 0.0],  # on the boundary: inside (the box is closed)
                      [0.11, 0.0, 0.0, 0.0, 0.0],  # above high
                      [0.0, float("nan"), 0.0, 0.0, 0.0],  # NaN
                      [0.0, 0.0, 0.0, 0.0, float("-inf")]])  # -inf
    assert action_in_range(m, a).tolist() == [True, False, False, False]
    message = describe_action_range(m, a)
    assert "model.action_low" in message and "NaN" in message
    d = LightDark10D()
    assert action_in_range(d, torch.tensor([0, 9, 10, -1])).tolist() == [True, True, False, False]


def _bad(**attrs) -> LightDark10DContinuous:
    m = LightDark10DContinuous()
    for k, v in attrs.items():
        setattr(m, k, v)
    return m


@pytest.mark.parametrize("attrs, field", [
    ({"action_low": torch.full((4,), -0.1)}, r"model\.action_low:"),  # wrong shape
    ({"action_high": torch.full((5, 1), 0.1)}, r"model\.action_high:"),  # wrong shape
    ({"action_high": torch.ones(5, dtype=torch.int64)}, r"model\.action_high:"),  # not a float tensor
    ({"action_low": [-0.1] * 5}, r"model\.action_low:"),  # not a tensor
    ({"action_low": None}, r"model\.action_low:"),  # missing
    ({"action_low": torch.full((5,), 0.1)}, r"model\.action_low, model\.action_high:"),  # low == high
    ({"action_low": torch.tensor([-0.1, -0.1, 0.2, -0.1, -0.1])}, r"model\.action_low, model\.action_high:"),
    ({"action_high": torch.tensor([0.1, 0.1, float("inf"), 0.1, 0.1])}, r"model\.action_low, model\.action_high:"),
    ({"action_dim": 0}, r"model\.action_dim:"),
    ({"action_dim": 2.5}, r"model\.action_dim:"),
    ({"action_dim": True}, r"model\.action_dim:"),
])
def test_a_bad_box_is_refused_naming_the_field(attrs, field):
    m = _bad(**attrs)
    with pytest.raises(TypeError, match="^" + field):
        check_action_box(m)
    with pytest.raises(TypeError, match="^" + field):
        check_model(m)


def test_a_model_with_neither_n_actions_nor_action_dim_is_refused():
    m = _bad(action_dim=None)
    assert not is_continuous(m)
    with pytest.raises(TypeError, match=r"^model\.n_actions:"):
        check_model(m)
