"""The DeepSets policy's TanhNormal head for continuous actions (escort_rl.modules.make_deepsets_policy
with ``action_box``): its log-probability against torch.distributions' change of variables, samples in
the box, the Monte Carlo entropy ClipPPOLoss reports, and permutation invariance over particles."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torch.distributions import AffineTransform, Normal, TanhTransform, TransformedDistribution
from torchrl.envs.utils import ExplorationType, set_exploration_type

from escort_rl.config import compose
from escort_rl.models import LightDark10DContinuous
from escort_rl.modules import DeepSetsActor, make_deepsets_policy, policy_outputs
from escort_rl.trainers.builders import belief_keys
from escort_rl.trainers.ppo import make_ppo_loss

D = 4  # state_dim of the particles fed to the actor
N = 7  # particles per belief

BOXES = {
    "lightdark": (torch.full((5,), -0.1), torch.full((5,), 0.1)),  # LightDark10DContinuous's
    "asymmetric": (torch.tensor([-1.0, 0.0, 2.0]), torch.tensor([1.0, 0.5, 3.0])),  # midpoints not 0
}


def make_policy(box, seed: int = 0, spread: float = 1.0):
    """A DeepSets TanhNormal policy on the box; ``spread`` scales the head so that loc and scale vary
    over a wider range between the batch's beliefs."""
    torch.manual_seed(seed)
    low, _ = box
    actor = DeepSetsActor(D, 2 * low.shape[0], hidden=16)
    with torch.no_grad():
        actor.head.weight.mul_(spread)
    return actor, make_deepsets_policy(actor, action_box=box, distribution="tanh_normal")


def beliefs(batch: int, seed: int = 1) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"particles": 2.0 * torch.randn(batch, N, D, generator=g),
                       "particle_log_weights": torch.randn(batch, N, generator=g)}, [batch])


def reference(loc: torch.Tensor, scale: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> TransformedDistribution:
    """``low + (high − low)·(tanh(u) + 1)/2``, ``u ~ N(loc, scale)``, per coordinate, in float64 (the
    affine's cache as well as the tanh's: ``log_prob`` of a just-drawn sample then reads the pre-image
    back instead of inverting tanh)."""
    loc, scale, low, high = (t.double() for t in (loc, scale, low, high))
    return TransformedDistribution(Normal(loc, scale), [TanhTransform(cache_size=1),
                                                       AffineTransform((low + high) / 2, (high - low) / 2,
                                                                       cache_size=1)])


def normalised(action: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """``tanh(u)``: the action mapped back to [-1, 1]."""
    return (action.double() - (low.double() + high.double()) / 2) / ((high.double() - low.double()) / 2)


# ---------------------------------------------------------------------------------------------
# the log-probability
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("box_name", list(BOXES))
def test_action_log_prob_is_the_change_of_variables(box_name):
    low, high = BOXES[box_name]
    _, policy = make_policy(BOXES[box_name], spread=2.0)
    torch.manual_seed(2)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):  # sampled (the default is the mode)
        td = policy(beliefs(512))
    loc, scale, action, log_prob = td["loc"], td["scale"], td["action"], td["action_log_prob"]
    a = low.shape[0]
    assert loc.shape == scale.shape == action.shape == (512, a) and log_prob.shape == (512,)
    assert action.dtype == torch.float32 and bool((scale > 0).all())
    # loc and scale vary between the beliefs (the comparison is not at one point)
    assert float(loc.std()) > 0.1 and float(scale.max() / scale.min()) > 1.5
    ref = reference(loc, scale, low, high).log_prob(action.double()).sum(-1)
    # away from the boundary (|tanh u| < 0.95 in every coordinate), where atanh of a float32 action
    # is well conditioned
    inside = (normalised(action, low, high).abs() < 0.95).all(-1)
    assert int(inside.sum()) > 100
    torch.testing.assert_close(log_prob[inside].double(), ref[inside], rtol=1e-5, atol=3e-5)


@pytest.mark.parametrize("box_name", list(BOXES))
def test_the_distribution_scores_given_actions_as_the_reference_does(box_name):
    """``policy.get_dist(td).log_prob(a)`` (what ClipPPOLoss evaluates) on actions chosen inside the
    box, not drawn from the policy: ``a = mid + half·tanh(z)``, ``z ∈ [-2, 2]``."""
    low, high = BOXES[box_name]
    _, policy = make_policy(BOXES[box_name], spread=2.0)
    td = beliefs(256, seed=3)
    with torch.no_grad():
        policy(td)
        dist = policy.get_dist(td)
    g = torch.Generator().manual_seed(4)
    z = -2.0 + 4.0 * torch.rand(256, low.shape[0], generator=g)
    action = ((low + high) / 2 + (high - low) / 2 * torch.tanh(z)).float()
    got = dist.log_prob(action)
    assert got.shape == (256,)
    ref = reference(td["loc"], td["scale"], low, high).log_prob(action.double()).sum(-1)
    torch.testing.assert_close(got.double(), ref, rtol=1e-5, atol=3e-5)
    # and against the formula written out: log N(u) − Σ log(1 − tanh²u) − Σ log(half)
    u = torch.atanh(normalised(action, low, high))
    by_hand = (Normal(td["loc"].double(), td["scale"].double()).log_prob(u) - torch.log1p(-torch.tanh(u) ** 2)
               - torch.log((high.double() - low.double()) / 2)).sum(-1)
    torch.testing.assert_close(got.double(), by_hand, rtol=1e-5, atol=3e-5)


# ---------------------------------------------------------------------------------------------
# samples
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("box_name", list(BOXES))
@pytest.mark.parametrize("bias", [0.0, 20.0, -20.0], ids=["centred", "saturated-high", "saturated-low"])
def test_samples_lie_in_the_box(box_name, bias):
    low, high = BOXES[box_name]
    actor, policy = make_policy(BOXES[box_name])
    with torch.no_grad():  # loc = bias, scale = biased_softplus(0) = 1 for every belief
        actor.head.weight.zero_()
        actor.head.bias.zero_()
        actor.head.bias[: low.shape[0]] += bias  # loc ± 20: tanh saturates in float32
        torch.manual_seed(5)
        with set_exploration_type(ExplorationType.RANDOM):
            td = policy(beliefs(4096, seed=6))
    torch.testing.assert_close(td["scale"], torch.ones_like(td["scale"]))
    action = td["action"]
    assert bool(((action >= low) & (action <= high)).all()), (float(action.min()), float(action.max()))
    assert bool(torch.isfinite(td["action_log_prob"]).all())
    if bias == 0.0:  # u ~ N(0, 1): the samples spread over the box
        assert bool((action.amin(0) < low + 0.2 * (high - low)).all())
        assert bool((action.amax(0) > high - 0.2 * (high - low)).all())
    # the deterministic action is inside the box too
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        det = policy(beliefs(64, seed=7))["action"]
    assert bool(((det >= low) & (det <= high)).all())


def test_make_deepsets_policy_refuses_a_box_that_does_not_fit_the_actor():
    with pytest.raises(ValueError, match="^action_box:"):
        make_deepsets_policy(DeepSetsActor(D, 6, hidden=8), action_box=(torch.zeros(2), torch.ones(2)))
    with pytest.raises(ValueError, match="^action_box:"):
        make_deepsets_policy(DeepSetsActor(D, 6, hidden=8), action_box=(torch.zeros(3), torch.ones(2)))


def test_policy_outputs_of_the_continuous_model():
    n, box = policy_outputs(LightDark10DContinuous())
    assert n == 10
    low, high = box
    assert torch.equal(low, torch.full((5,), -0.1)) and torch.equal(high, torch.full((5,), 0.1))


# ---------------------------------------------------------------------------------------------
# the entropy ClipPPOLoss reports
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("box_name", list(BOXES))
def test_clip_ppo_loss_entropy_agrees_with_a_large_sample_estimate(box_name, per_test_seed):
    """ClipPPOLoss has no closed form for a TanhNormal's entropy and reports ``−mean log p`` over
    ``samples_mc_entropy`` draws per batch row, averaged over the batch. Against an independent
    estimate from torch.distributions with K draws per row, the difference has standard error
    ``sqrt(Σ_b σ_b² (1/M + 1/K)) / B`` (σ_b² the variance of −log p in row b); the bound is six standard
    errors (a sum of this many draws is close to normal: the chance of failing is far below 1e-6)."""
    low, high = BOXES[box_name]
    cfg = compose(["trainer=ppo", "trainer.entropy_coef=0.01"])
    actor, policy = make_policy(BOXES[box_name], spread=2.0)
    critic = DeepSetsActor(D, 1, hidden=8)
    loss = make_ppo_loss(policy, critic, cfg)
    m_loss, k_ref, b = 4096, 65536, 8
    loss.samples_mc_entropy = m_loss

    td = beliefs(b, seed=8)
    torch.manual_seed(per_test_seed)  # the loss's draws (pytest --seed-offset K varies them)
    with torch.no_grad():
        policy(td)
    td["advantage"] = torch.randn(b, 1)
    td["value_target"] = torch.randn(b, 1)
    out = loss(td.clone())
    reported = float(out["entropy"].detach())
    # the loss term is −entropy_coef × the same estimate
    assert float(out["loss_entropy"].detach()) == pytest.approx(-0.01 * reported, rel=1e-5)

    with torch.no_grad():
        dist = reference(td["loc"], td["scale"], low, high)
        y = dist.rsample((k_ref,))  # [K, B, A], drawn after the loss's draws from the same stream
        neg_log_p = -dist.log_prob(y).sum(-1)  # [K, B]
    assert bool(torch.isfinite(neg_log_p).all())
    ref_entropy = neg_log_p.mean(0)  # [B]
    var = neg_log_p.var(0)  # [B]
    se = float(torch.sqrt((var * (1 / m_loss + 1 / k_ref)).sum()) / b)
    assert abs(reported - float(ref_entropy.mean())) < 6 * se, (reported, float(ref_entropy.mean()), se)
    # the bound has power: widening every scale by 10 % moves the entropy by more than the bound
    assert 6 * se < entropy_change_at_wider_scale(td, low, high, 1.1)


def entropy_change_at_wider_scale(td: TensorDict, low, high, factor: float) -> float:
    """How much the batch-mean entropy changes when every scale is multiplied by ``factor``: Monte Carlo
    with common random numbers (the same ε for both), ``−log p = −log N(u) + log(1 − tanh²u) + Σ log half``
    with ``log(1 − tanh²u) = 2·(log 2 − u − softplus(−2u))``."""
    g = torch.Generator().manual_seed(11)
    loc, scale = td["loc"].double(), td["scale"].double()
    eps = torch.randn(20000, *loc.shape, generator=g, dtype=torch.float64)
    log_half = torch.log((high.double() - low.double()) / 2)

    def entropy(s):
        u = loc + s * eps
        log_det = 2 * (math.log(2) - u - torch.nn.functional.softplus(-2 * u))
        return float(-(Normal(loc, s).log_prob(u) - log_det - log_half).sum(-1).mean())

    return abs(entropy(scale * factor) - entropy(scale))


# ---------------------------------------------------------------------------------------------
# permutation invariance
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("box_name", list(BOXES))
def test_loc_and_scale_are_invariant_to_permuting_the_particles(box_name):
    _, policy = make_policy(BOXES[box_name], spread=2.0)
    td = beliefs(16, seed=12)
    g = torch.Generator().manual_seed(13)
    perm = torch.stack([torch.randperm(N, generator=g) for _ in range(16)])  # a permutation per belief
    shuffled = TensorDict({
        "particles": torch.gather(td["particles"], 1, perm.unsqueeze(-1).expand(16, N, D)),
        "particle_log_weights": torch.gather(td["particle_log_weights"], 1, perm)}, [16])
    assert not torch.equal(shuffled["particles"], td["particles"])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        a, b = policy(td.clone()), policy(shuffled)
    torch.testing.assert_close(a["loc"], b["loc"], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(a["scale"], b["scale"], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(a["action"], b["action"], rtol=1e-5, atol=1e-6)
    # permuting the particles alone (not their weights) is another belief: the output changes
    alone = TensorDict({"particles": shuffled["particles"], "particle_log_weights": td["particle_log_weights"]}, [16])
    with torch.no_grad():
        c = policy(alone)
    assert not torch.allclose(a["loc"], c["loc"], atol=1e-4)


def test_belief_keys_of_the_config_are_read():
    """``make_deepsets_policy`` reads the config's renamed belief keys, as PPO builds it."""
    cfg = compose(["trainer=ppo", "env=lightdark10d_continuous", "keys.particles=bx", "keys.log_weights=bw"])
    n, box = policy_outputs(LightDark10DContinuous())
    policy = make_deepsets_policy(DeepSetsActor(10, n, hidden=8), *belief_keys(cfg), action_box=box,
                                  distribution="tanh_normal")
    td = TensorDict({"bx": torch.randn(3, 5, 10), "bw": torch.zeros(3, 5)}, [3])
    out = policy(td)
    assert out["action"].shape == (3, 5)


def test_the_scale_never_falls_below_actor_min_scale():
    from escort_rl.trainers.builders import build_policy

    torch.manual_seed(0)
    actor = DeepSetsActor(state_dim=D, n_actions=2 * 5, hidden=8)
    with torch.no_grad():  # a head that asks for a tiny scale everywhere: softplus(-30) is about 1e-13
        actor.head.weight[5:] = 0.0
        actor.head.bias[5:] = -30.0
    td = TensorDict({"particles": torch.randn(6, N, D), "particle_log_weights": torch.zeros(6, N)}, [6])
    floor = make_deepsets_policy(actor, action_box=BOXES["lightdark"], min_scale=0.3)(td.clone())["scale"]
    assert bool((floor >= 0.3).all())
    cfg = compose(["env=lightdark10d_continuous", "actor.min_scale=0.25"])
    _, policy = build_policy(cfg, LightDark10DContinuous())
    td = TensorDict({"particles": torch.randn(6, N, 10), "particle_log_weights": torch.zeros(6, N)}, [6])
    assert bool((policy(td)["scale"] >= 0.25).all())
    with pytest.raises(Exception, match="actor.min_scale"):
        compose(["env=lightdark10d_continuous", "actor.min_scale=0"])
