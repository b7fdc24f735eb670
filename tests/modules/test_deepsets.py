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
