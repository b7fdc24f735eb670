"""Closed-form observation scores: every model's ``observation_score`` equals the autograd gradient
of its ``observation_log_prob``, and ESCORT gives the same update with or without it."""

import copy

import pytest
import torch

from escort_rl.belief import ESCORTFilter
from escort_rl.models import (
    HiddenGoal,
    KidnappedRobot20D,
    LightDark1D,
    LightDark10D,
    LinearGaussian,
    MultiTargetTracking20D,
)

MODELS = {
    "lineargaussian": LinearGaussian,
    "lightdark1d": LightDark1D,
    "lightdark10d": LightDark10D,
    "kidnapped20d": KidnappedRobot20D,
    "mtt20d": MultiTargetTracking20D,
    "hidden-goal-near-beacon": lambda: HiddenGoal(dim=4, modes=4, beacon_distance=0.3),
    # three soft x-bins, so the middle-bin (log cosh) branch of the zone gradient is exercised too
    "mtt20d-3x2-zones": lambda: MultiTargetTracking20D(
        zone_x_edges=(3.0, 7.0), zone_grid=(("clear", "confusion", "limited"), ("confusion", "blind", "clear"))),
}
B, N = 3, 7


def as_float64(model):
    """A shallow copy of ``model`` with every floating tensor attribute in float64 (the models keep
    float32 constants; the copy evaluates the same formulas in float64 for a tight comparison)."""
    model = copy.copy(model)
    for name, value in vars(model).items():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            setattr(model, name, value.double())
    return model


def autograd_reference(model, o, s, a):
    """``∇_s Σ observation_log_prob(o, s, a)`` by autograd. ``s`` ``[*S, d]`` -> ``[*S, d]``."""
    s = s.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(model.observation_log_prob(o, s, a).sum(), s)
    return grad


def realistic_points(model, g):
    """As in a filter update: particles ``[B, N, d]`` predicted from the prior belief, one action
    per belief broadcast to its particles ``[B, N]``, and the observation of the true next state
    ``[B, 1, obs_dim]``."""
    a = torch.randint(0, model.n_actions, (B, 1), generator=g).expand(B, N)
    truth = model.transition(model.initial_state((B, 1), g), a[:, :1], g)
    o = model.observe(truth, a[:, :1], g)
    s = model.transition(model.initial_belief((B,), N, g), a, g)
    return o, s, a


def near_truth_points(model, g, spread=0.3):
    """Particles scattered around the true next state (where detections and visible slots make the
    likelihood informative). Same shapes as :func:`realistic_points`."""
    a = torch.randint(0, model.n_actions, (B, 1), generator=g).expand(B, N)
    truth = model.transition(model.initial_state((B, 1), g), a[:, :1], g)
    if isinstance(model, KidnappedRobot20D):  # put the robot inside a landmark cluster, facing it
        truth[..., 0:2] = torch.tensor([3.5, 3.5]) + torch.rand(B, 1, 2, generator=g)
        truth[..., 2] = torch.pi / 4 + 0.3 * torch.randn(B, 1, generator=g)
    o = model.observe(truth, a[:, :1], g)
    s = truth + spread * torch.randn(B, N, model.state_dim, generator=g)
    if isinstance(model, LightDark1D):
        s[..., 1] = (torch.rand(B, N, generator=g) < 0.3).float()  # some particles have ended
    return o, s, a


def detected_points(model, g):
    """Multi-target tracking with every slot detected, each report near its target (the zone and
    identity-swap mixtures are active); particles around the truth."""
    o, s, a = near_truth_points(model, g, spread=0.5)
    truth = s[:, :1] + 0.1 * torch.randn(B, 1, model.state_dim, generator=g)
    slots = o[..., 2:].unflatten(-1, (4, 3)).clone()
    slots[..., 0] = 1.0
    slots[..., 1:] = model.target_positions(truth) + 0.2 * torch.randn(B, 1, 4, 2, generator=g)
    return torch.cat([o[..., :2], slots.flatten(-2)], dim=-1), s, a


def light_dark_points(model, g):
    """Light-Dark positions along rays out of each light region ``[7, 7, 10]``: from deep inside
    (bright) through the band ``0.05 < L < 0.1`` (mixture and light gradient both active) to
    outside (clamped, zero light gradient). Observations ``[7, 1, 5]``."""
    frac = torch.tensor([0.1, 0.5, 0.9, 0.95, 0.96, 0.97, 1.2])  # distance / radius
    u = torch.randn(7, 1, 5, generator=g)
    u = u / u.norm(dim=-1, keepdim=True)
    pos = model.light_centres[:, None] + frac[:, None] * model.light_radii[:, None, None] * u  # [7, 7, 5]
    s = torch.cat([pos, 0.1 * torch.randn(7, 7, 5, generator=g)], dim=-1)
    a = torch.randint(0, model.n_actions, (7, 1), generator=g).expand(7, 7)
    o = pos[:, 3:4] + 0.5 * torch.randn(7, 1, 5, generator=g)
    return o, s, a


def point_sets(name, model, g):
    sets = {"prior": realistic_points(model, g), "near-truth": near_truth_points(model, g)}
    if name.startswith("mtt"):
        sets["detected"] = detected_points(model, g)
    if name == "lightdark10d":
        sets["rays"] = light_dark_points(model, g)
    return sets


@pytest.mark.parametrize("name", list(MODELS))
def test_observation_score_matches_autograd(name):
    model = MODELS[name]()
    g = torch.Generator().manual_seed(0)
    for label, (o, s, a) in point_sets(name, model, g).items():
        assert o.shape[-2] == 1 and s.shape[:-1] == a.shape and s.dim() == 3
        # float64: the same formulas to rounding error
        m64 = as_float64(model)
        got = m64.observation_score(o.double(), s.double(), a)
        want = autograd_reference(m64, o.double(), s.double(), a)
        assert got.shape == s.shape and got.dtype == torch.float64, label
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6, msg=lambda m: f"{name}/{label}: {m}")
        # float32, the filters' precision
        got32 = model.observation_score(o, s, a)
        want32 = autograd_reference(model, o, s, a)
        assert got32.dtype == torch.float32 and torch.isfinite(got32).all(), label
        scale = want32.abs().amax().clamp_min(1.0).item()
        torch.testing.assert_close(got32, want32, rtol=1e-4, atol=1e-5 * scale,
                                   msg=lambda m: f"{name}/{label} float32: {m}")


def test_light_dark_rays_cover_every_branch():
    """The Light-Dark test points reach the bright, the mixture-and-gradient band and the clamp."""
    model = LightDark10D()
    _, s, _ = light_dark_points(model, torch.Generator().manual_seed(0))
    light, grad = model.light_and_gradient(s[..., :5])
    torch.testing.assert_close(light, model.light(s[..., :5]))
    dark = light < model.dark_threshold
    assert (~dark).any() and (dark & (light > 0.05)).any() and (light == 0.05).any()
    assert (grad[light == 0.05] == 0).all() and (grad[light > 0.05].norm(dim=-1) > 0).all()


def test_kidnapped_points_have_visible_slots_and_mtt_points_have_misses():
    g = torch.Generator().manual_seed(0)
    o, _, _ = near_truth_points(KidnappedRobot20D(), g)
    assert (o[..., 0::3] > 0.5).any() and (o[..., 0::3] < 0.5).any()
    o, _, _ = realistic_points(MultiTargetTracking20D(), g)
    assert (o[..., 2::3] < 0.5).any()


class WithoutScore:
    """A model that forwards every protocol attribute except ``observation_score`` (a user's model
    without the closed form)."""

    def __init__(self, model) -> None:
        self._model = model

    def __getattr__(self, name: str):
        if name == "observation_score":
            raise AttributeError(name)
        return getattr(self._model, name)


@pytest.mark.parametrize("name", ["lineargaussian", "lightdark10d", "kidnapped20d", "mtt20d"])
@pytest.mark.parametrize("seed", [0, 1])
def test_escort_update_is_the_same_without_the_closed_form(name, seed):
    """One ESCORT update (all regularisers on) from the same seed, with the closed-form score and with
    the autograd fallback. A small step: the AdaGrad-normalised step ``ε v/sqrt(G)`` amplifies the
    float32 rounding difference of the two scores by a factor that grows with ``ε`` (at the default
    ``ε = 0.1``, tenfold per early iteration on multi-target tracking)."""
    model = MODELS[name]()
    plain = WithoutScore(model)
    assert not hasattr(plain, "observation_score") and plain.state_dim == model.state_dim
    results = []
    for m in (model, plain):
        g = torch.Generator().manual_seed(seed)
        filt = ESCORTFilter(num_steps=5, step_size=0.01)
        belief = filt.init(m, (2,), 32, g)
        a = torch.tensor([0, 1])
        o = m.observe(m.transition(m.initial_state((2,), g), a, g), a, g)
        results.append(filt.update(m, belief, a, o, g).particles)
    assert torch.isfinite(results[0]).all()
    torch.testing.assert_close(results[0], results[1], rtol=1e-4, atol=1e-4)


def test_compiled_update_runs_the_closed_form(monkeypatch):
    """Under ``compile=True`` the filter traces the model's ``observation_score`` (autograd is never
    called) and gives the eager update."""
    import escort_rl.belief.scores as scores

    def no_autograd(*args, **kwargs):
        raise AssertionError("the likelihood score went through autograd")

    monkeypatch.setattr(scores, "autograd_score", no_autograd)
    model = MultiTargetTracking20D()
    results = []
    for compile_ in (False, True):
        g = torch.Generator().manual_seed(0)
        filt = ESCORTFilter(num_steps=3, step_size=0.01, lambda_corr=0.0, lambda_temp=0.0, compile=compile_)
        belief = filt.init(model, (2,), 32, g)
        a = torch.tensor([0, 1])
        o = model.observe(model.transition(model.initial_state((2,), g), a, g), a, g)
        results.append(filt.update(model, belief, a, o, g).particles)
    torch.testing.assert_close(results[1], results[0], rtol=1e-4, atol=1e-4)
