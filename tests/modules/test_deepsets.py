"""DeepSetsActor: permutation invariance, weighted pooling, and the TorchRL policy wrapper."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from escort_rl.modules import DeepSetsActor, make_deepsets_policy


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 40), batch=st.integers(1, 4), seed=st.integers(0, 2**31 - 1), weighted=st.booleans())
def test_permutation_invariance(n, batch, seed, weighted):
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(0)
    actor = DeepSetsActor(state_dim=6, n_actions=5, hidden=16)
    x = torch.randn(batch, n, 6, generator=g)
    log_w = torch.randn(batch, n, generator=g) if weighted else None
    perm = torch.randperm(n, generator=g)
    out = actor(x, log_w)
    out_perm = actor(x[:, perm], None if log_w is None else log_w[:, perm])
    assert out.shape == (batch, 5)
    torch.testing.assert_close(out, out_perm, rtol=1e-5, atol=1e-5)


def test_equal_weights_pool_is_the_mean():
    torch.manual_seed(0)
    actor = DeepSetsActor(state_dim=3, n_actions=4, hidden=8)
    x = torch.randn(2, 7, 3)
    torch.testing.assert_close(actor(x), actor(x, torch.zeros(2, 7)))


def test_weights_change_the_output():
    torch.manual_seed(0)
    actor = DeepSetsActor(state_dim=3, n_actions=4, hidden=8)
    x = torch.randn(1, 2, 3)
    one = torch.tensor([[0.0, -1e9]])  # all weight on particle 0
    torch.testing.assert_close(actor(x, one), actor(x[:, :1]), rtol=1e-5, atol=1e-5)
    assert not torch.allclose(actor(x, one), actor(x))


def test_wrong_state_dim_names_the_field():
    actor = DeepSetsActor(state_dim=3, n_actions=4)
    try:
        actor(torch.zeros(1, 5, 4))
    except ValueError as err:
        assert str(err).startswith("particles:")
    else:
        raise AssertionError("expected a ValueError")


def test_policy_writes_integer_actions_and_log_probs():
    actor = DeepSetsActor(state_dim=10, n_actions=10)
    policy = make_deepsets_policy(actor)
    td = TensorDict({"particles": torch.randn(4, 20, 10), "particle_log_weights": torch.zeros(4, 20)}, [4])
    out = policy(td)
    assert out["action"].dtype == torch.int64 and out["action"].shape == (4,)
    assert ((out["action"] >= 0) & (out["action"] < 10)).all()
    expected = torch.distributions.Categorical(logits=out["logits"]).log_prob(out["action"])
    torch.testing.assert_close(out["action_log_prob"], expected)


# ---------------------------------------------------------------- outputs per group of coordinates
GROUPS = tuple((i, 5 + i) for i in range(5))  # Light-Dark's (x_i, v_i)


def _group_outputs_by_hand(actor, particles, log_weights):
    """The per-group head written out: ``g_c(c_j + e_j, ρ(…))`` with ``c_j`` the weighted mean of
    ``φ_c`` over the particles' coordinates of group ``j``; ``[B, G, m]``."""
    z = (particles - actor.input_loc) / actor.input_scale
    w = torch.softmax(log_weights, -1)
    rows = []
    for j, coords in enumerate(GROUPS):
        c = (w[..., None] * actor.encode_group(z[..., list(coords)])).sum(-2) + actor.group_embedding[j]
        rows.append(actor.group_head(torch.cat([c, actor.pool(particles, log_weights)], -1)))
    return torch.stack(rows, -2)


def test_group_head_is_one_network_per_group_in_action_order():
    torch.manual_seed(0)
    actor = DeepSetsActor(10, 10, hidden=8, input_loc=1.0, input_scale=2.0, coordinate_groups=GROUPS)
    torch.nn.init.normal_(actor.group_embedding)
    x, lw = torch.randn(3, 7, 10), torch.randn(3, 7)
    by_hand = _group_outputs_by_hand(actor, x, lw)  # [3, 5, 2]
    # discrete: actions 2j and 2j+1 are group j's two outputs
    torch.testing.assert_close(actor(x, lw), by_hand.flatten(-2))
    cont = DeepSetsActor(10, 10, hidden=8, input_loc=1.0, input_scale=2.0, coordinate_groups=GROUPS,
                         group_layout="output_major")
    cont.load_state_dict(actor.state_dict())
    # continuous: [loc_1..loc_5, scale_1..scale_5]
    torch.testing.assert_close(cont(x, lw), by_hand.transpose(-1, -2).flatten(-2))


def test_group_head_reads_only_its_group_besides_the_pooled_belief():
    """Changing group 3's coordinates moves group 0's outputs only through the pooled context: with the
    context's network fixed to zero, they do not move at all."""
    torch.manual_seed(1)
    actor = DeepSetsActor(10, 10, hidden=8, coordinate_groups=GROUPS)
    with torch.no_grad():
        for p in actor.rho.parameters():
            p.zero_()
    x = torch.randn(2, 9, 10)
    y = x.clone()
    y[..., [3, 8]] += torch.randn(2, 9, 2)
    out_x, out_y = actor(x, None), actor(y, None)
    torch.testing.assert_close(out_x[:, :6], out_y[:, :6])
    assert not torch.allclose(out_x[:, 6:8], out_y[:, 6:8])


@given(n=st.integers(1, 12), seed=st.integers(0, 10_000))
@settings(max_examples=20, deadline=None)
def test_group_head_is_permutation_invariant(n, seed):
    g = torch.Generator().manual_seed(seed)
    actor = DeepSetsActor(10, 10, hidden=8, coordinate_groups=GROUPS)
    x, lw = torch.randn(2, n, 10, generator=g), torch.randn(2, n, generator=g)
    perm = torch.randperm(n, generator=g)
    torch.testing.assert_close(actor(x, lw), actor(x[:, perm], lw[:, perm]), rtol=1e-5, atol=1e-5)


def test_group_head_bad_groups_name_the_argument():
    import pytest

    for groups, fragment in ((((0, 5), (1,)), "same number"), (((0, 10),), "state indices"),
                             (((0, 5), (1, 6), (2, 7)), "must divide")):
        with pytest.raises(ValueError, match="coordinate_groups") as info:
            DeepSetsActor(10, 10, hidden=8, coordinate_groups=groups)
        assert fragment in str(info.value)
    with pytest.raises(ValueError, match="group_layout"):
        DeepSetsActor(10, 10, hidden=8, coordinate_groups=GROUPS, group_layout="rows")


def test_max_particles_reads_a_strided_subset_of_a_larger_belief_and_all_of_a_smaller_one():
    from escort_rl.config import compose
    from escort_rl.models import LightDark10D
    from escort_rl.trainers.builders import build_actor

    torch.manual_seed(0)
    full = DeepSetsActor(state_dim=3, n_actions=4, hidden=8, coordinate_groups=((0,), (1,)), group_hidden=4)
    thin = DeepSetsActor(state_dim=3, n_actions=4, hidden=8, coordinate_groups=((0,), (1,)), group_hidden=4,
                         max_particles=4)
    thin.load_state_dict(full.state_dict())
    x, log_w = torch.randn(2, 10, 3), torch.randn(2, 10)
    torch.testing.assert_close(thin(x, log_w), full(x[:, 0:8:2], log_w[:, 0:8:2]))  # every 2nd, the first 4
    torch.testing.assert_close(thin(x[:, :4], log_w[:, :4]), full(x[:, :4], log_w[:, :4]))
    assert not torch.allclose(thin(x, log_w), full(x, log_w))
    actor = build_actor(compose(["actor.max_particles=25"]), 10, 10, LightDark10D())
    assert actor.max_particles == 25 and build_actor(compose([]), 10, 10, LightDark10D()).max_particles is None


def _attention_actor(seed: int = 0, **kwargs) -> DeepSetsActor:
    """An attention-pooled actor whose scores are not at their zero start (so that attention is not a mean)."""
    torch.manual_seed(seed)
    actor = DeepSetsActor(state_dim=4, n_actions=6, hidden=8, pooling="attention", attention_heads=2, **kwargs)
    torch.nn.init.normal_(actor.attention_scores.weight, std=2.0)
    return actor


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 30), seed=st.integers(0, 2**31 - 1), weighted=st.booleans())
def test_attention_pooling_is_permutation_invariant(n, seed, weighted):
    g = torch.Generator().manual_seed(seed)
    actor = _attention_actor(coordinate_groups=((0,), (1,), (2,)), group_hidden=4)
    x, log_w = torch.randn(3, n, 4, generator=g), torch.randn(3, n, generator=g) if weighted else None
    perm = torch.randperm(n, generator=g)
    torch.testing.assert_close(actor(x, log_w), actor(x[:, perm], None if log_w is None else log_w[:, perm]),
                               rtol=1e-5, atol=1e-5)


def test_attention_pooling_starts_as_the_weighted_mean_of_its_values():
    torch.manual_seed(0)
    actor = DeepSetsActor(state_dim=4, n_actions=6, hidden=8, pooling="attention", attention_heads=2)
    x, log_w = torch.randn(2, 9, 4), torch.randn(2, 9)
    h = actor.phi(actor.features(x))
    mean = (torch.softmax(log_w, -1).unsqueeze(-1) * actor.attention_values(h)).sum(-2)
    torch.testing.assert_close(actor.attend(h, log_w), mean)


def test_attention_pooling_follows_the_weights_and_the_scores():
    actor = _attention_actor()
    x = torch.randn(1, 3, 4)
    one = torch.tensor([[0.0, -1e9, -1e9]])  # all weight on particle 0
    torch.testing.assert_close(actor(x, one), actor(x[:, :1]), rtol=1e-5, atol=1e-5)
    # one head's scores by hand: softmax over particles of u·h + c + log w, then the head's slice of V h
    h, log_w = actor.phi(actor.features(x)), torch.randn(1, 3)
    a = torch.softmax(h @ actor.attention_scores.weight[0] + actor.attention_scores.bias[0]
                      + torch.log_softmax(log_w, -1), dim=-1)  # [1, 3]
    head0 = (a.unsqueeze(-1) * actor.attention_values(h)[..., :4]).sum(-2)
    torch.testing.assert_close(actor.attend(h, log_w)[..., :4], head0)
    assert not torch.allclose(a, torch.softmax(log_w, -1), atol=1e-3)  # the scores moved the weights


def test_attention_pooling_bad_arguments_name_the_field():
    import pytest

    from escort_rl.config import compose
    from escort_rl.models import LightDark10D
    from escort_rl.trainers.builders import build_actor

    with pytest.raises(ValueError, match="attention_heads"):
        DeepSetsActor(4, 6, hidden=8, pooling="attention", attention_heads=3)
    with pytest.raises(ValueError, match="pooling"):
        DeepSetsActor(4, 6, hidden=8, pooling="max")
    actor = build_actor(compose(["actor.pooling=attention", "actor.attention_heads=8"]), 10, 10, LightDark10D())
    assert actor.pooling == "attention" and actor.attention_scores.out_features == 8
    assert build_actor(compose([]), 10, 10, LightDark10D()).pooling == "mean"
