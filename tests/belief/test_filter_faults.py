"""Filters never return NaN or inf silently: a bad input belief, a model method that returns NaN or
+inf, or a result that overflows gets a one-line ``ValueError`` naming the field or the method, the
belief and the fix; a ``-inf`` log-density (zero likelihood) stays legitimate. The checks cost one
host synchronisation per update and do not change the numbers of a finite update."""

from __future__ import annotations

import pytest
import torch

from escort_rl.belief import ESCORTFilter, NonFiniteError, ParticleBelief, SIRFilter, SVGDFilter
from escort_rl.belief.checks import FiniteGuard
from escort_rl.models import LinearGaussian

B, N, D = 2, 12, 3
NAN, INF = float("nan"), float("inf")


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


FILTERS = {
    "sir": lambda: SIRFilter(),
    "svgd": lambda: SVGDFilter(num_steps=3),
    "escort": lambda: ESCORTFilter(num_steps=3),
    "escort_exact": lambda: ESCORTFilter(num_steps=3, prior="exact"),
}
PARTICLE_FILTERS = ("svgd", "escort", "escort_exact")


class Faulty(LinearGaussian):
    """A 3-D linear-Gaussian model whose method ``method`` returns ``value`` for the first ``k``
    particles of belief ``belief`` (rows of the ``[B, N, ...]`` output), and is exact otherwise.
    ``closed_form=False`` removes ``observation_score``, so the filters take autograd scores."""

    def __init__(self, method: str, value: float, k: int = 3, belief: int = 0, closed_form: bool = True) -> None:
        super().__init__(state_dim=D)
        self.method, self.value, self.k, self.belief = method, value, k, belief
        if not closed_form:
            self.observation_score = None

    def _spoil(self, name: str, out: torch.Tensor) -> torch.Tensor:
        if name != self.method:
            return out
        out = out.clone()
        out[self.belief, : self.k] = self.value
        return out

    def initial_belief(self, shape, n, generator=None):
        return self._spoil("initial_belief", super().initial_belief(shape, n, generator))

    def transition(self, s, a, generator=None):
        mean = LinearGaussian.transition_mean(self, s, a)  # not the spoilt transition_mean
        return self._spoil("transition", mean + self._noise(mean.shape[:-1], self._q_tril, generator))

    def transition_mean(self, s, a):
        return self._spoil("transition_mean", super().transition_mean(s, a))

    def transition_scale_tril(self):
        tril = super().transition_scale_tril().clone()
        if self.method == "transition_scale_tril":
            tril[0, 0] = self.value
        return tril

    def transition_log_prob(self, s_next, s, a):
        return self._spoil("transition_log_prob", super().transition_log_prob(s_next, s, a))

    def observation_log_prob(self, o, s_next, a):
        return self._spoil("observation_log_prob", super().observation_log_prob(o, s_next, a))

    def observation_score(self, o, s_next, a):
        return self._spoil("observation_score", super().observation_score(o, s_next, a))


def _inputs(model, filt, seed: int = 0):
    belief = filt.init(model, (B,), N, gen(seed))
    return belief, torch.tensor([0, 3]), torch.full((B, D), 0.3)


def _error(filt, model, belief, action, obs) -> str:
    with pytest.raises(ValueError) as info:
        filt.update(model, belief, action, obs, gen(1))
    message = str(info.value)
    assert isinstance(info.value, NonFiniteError), message
    assert "\n" not in message, message
    return message


# ---------------------------------------------------------------------------------------------
# The input belief
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("value, label", [(NAN, "NaN"), (INF, "inf"), (-INF, "inf")], ids=["nan", "inf", "neginf"])
def test_a_non_finite_particle_names_belief_particles(name, value, label):
    model, filt = LinearGaussian(state_dim=D), FILTERS[name]()
    belief, action, obs = _inputs(model, filt)
    particles = belief.particles.clone()
    particles[1, 4, 2] = value
    message = _error(filt, model, ParticleBelief(particles, belief.log_weights), action, obs)
    assert message.startswith(f"belief.particles: {label} for 1 particle of belief 1;"), message
    assert "check the previous update or the prior" in message


@pytest.mark.parametrize("name", sorted(FILTERS))
@pytest.mark.parametrize("value, label", [(NAN, "NaN"), (INF, "+inf")], ids=["nan", "posinf"])
def test_a_bad_log_weight_names_belief_log_weights(name, value, label):
    model, filt = LinearGaussian(state_dim=D), FILTERS[name]()
    belief, action, obs = _inputs(model, filt)
    log_w = belief.log_weights.clone()
    log_w[0, [1, 5]] = value
    message = _error(filt, model, ParticleBelief(belief.particles, log_w), action, obs)
    assert message.startswith(f"belief.log_weights: {label} for 2 particles of belief 0;"), message
    assert "check the previous update or the prior" in message


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_a_belief_without_weight_names_belief_log_weights(name):
    model, filt = LinearGaussian(state_dim=D), FILTERS[name]()
    belief, action, obs = _inputs(model, filt)
    log_w = belief.log_weights.clone()
    log_w[1] = -INF
    message = _error(filt, model, ParticleBelief(belief.particles, log_w), action, obs)
    assert message.startswith("belief.log_weights: every log-weight -inf in belief 1 (no particle has weight)"), message


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_a_zero_weight_particle_is_legitimate(name):
    """``-inf`` log-weights of some particles are zero weights: no error, a finite normalised result."""
    model, filt = LinearGaussian(state_dim=D), FILTERS[name]()
    belief, action, obs = _inputs(model, filt)
    log_w = belief.log_weights.clone()
    log_w[:, :3] = -INF
    log_w = torch.log_softmax(log_w, -1)
    post = filt.update(model, ParticleBelief(belief.particles, log_w), action, obs, gen(1))
    assert bool(torch.isfinite(post.particles).all())
    lse = torch.logsumexp(post.log_weights, -1)
    torch.testing.assert_close(lse, torch.zeros_like(lse), rtol=0, atol=1e-5)


def test_escort_names_the_input_not_the_failed_factorisation():
    """A NaN particle makes the smoothed prior's Cholesky factorisation fail inside the update; the
    error names the input, and carries no traceback from inside torch."""
    model, filt = LinearGaussian(state_dim=D), ESCORTFilter(num_steps=3)
    belief, action, obs = _inputs(model, filt)
    particles = belief.particles.clone()
    particles[0, 0, 0] = NAN
    with pytest.raises(NonFiniteError) as info:
        filt.update(model, ParticleBelief(particles, belief.log_weights), action, obs, gen(1))
    assert str(info.value).startswith("belief.particles: NaN for 1 particle of belief 0;")
    assert info.value.__cause__ is None and info.value.__suppress_context__


# ---------------------------------------------------------------------------------------------
# What the model returns
# ---------------------------------------------------------------------------------------------

MODEL_FAULTS = [
    # (method, value, filters, message prefix)
    ("transition", NAN, sorted(FILTERS), "model.transition returned NaN for 3 particles of belief 0;"),
    ("transition", INF, sorted(FILTERS), "model.transition returned inf for 3 particles of belief 0;"),
    ("transition", -INF, sorted(FILTERS), "model.transition returned inf for 3 particles of belief 0;"),
    ("observation_log_prob", NAN, sorted(FILTERS),
     "model.observation_log_prob returned NaN for 3 particles of belief 0;"),
    ("observation_log_prob", INF, sorted(FILTERS),
     "model.observation_log_prob returned +inf for 3 particles of belief 0;"),
    ("transition_mean", NAN, PARTICLE_FILTERS, "model.transition_mean returned NaN for 3 particles of belief 0;"),
    ("transition_scale_tril", NAN, ("svgd", "escort"), "model.transition_scale_tril returned NaN in 1 of 9 entries;"),
    ("transition_scale_tril", INF, ("svgd", "escort"), "model.transition_scale_tril returned inf in 1 of 9 entries;"),
    ("observation_score", NAN, PARTICLE_FILTERS,
     "model.observation_score returned NaN for up to 3 particles of belief 0 during the particle evolution;"),
    ("observation_score", INF, PARTICLE_FILTERS,
     "model.observation_score returned inf for up to 3 particles of belief 0 during the particle evolution;"),
    ("observation_score", -INF, PARTICLE_FILTERS,
     "model.observation_score returned inf for up to 3 particles of belief 0 during the particle evolution;"),
    ("transition_log_prob", NAN, ("escort_exact",),
     "model.transition_log_prob (in the exact prior's mixture) returned NaN for up to 3 particles of belief 0 during "
     "the particle evolution;"),
    ("transition_log_prob", INF, ("escort_exact",),
     "model.transition_log_prob (in the exact prior's mixture) returned +inf for up to 3 particles of belief 0 "
     "during the particle evolution;"),
]
MODEL_CASES = [pytest.param(method, value, name, prefix, id=f"{method}-{value}-{name}")
               for method, value, names, prefix in MODEL_FAULTS for name in names]


@pytest.mark.parametrize("method, value, name, prefix", MODEL_CASES)
def test_a_model_method_returning_nan_or_inf_is_named(method, value, name, prefix):
    model, filt = Faulty(method, value), FILTERS[name]()
    belief, action, obs = _inputs(LinearGaussian(state_dim=D), filt)
    message = _error(filt, model, belief, action, obs)
    assert message.startswith(prefix), message


@pytest.mark.parametrize("name", PARTICLE_FILTERS)
def test_the_autograd_path_names_observation_log_prob(name):
    """Without a closed-form score the likelihood score comes from autograd: a NaN log-likelihood
    is named, not replaced by a zero gradient."""
    model, filt = Faulty("observation_log_prob", NAN, k=2, belief=1, closed_form=False), FILTERS[name]()
    belief, action, obs = _inputs(LinearGaussian(state_dim=D), filt)
    message = _error(filt, model, belief, action, obs)
    assert message.startswith("model.observation_log_prob returned NaN for 2 particles of belief 1;"), message


class _NaNGradient(LinearGaussian):
    """A finite log-likelihood whose gradient is NaN at the first 3 particles of belief 0 only: there
    it adds ``sqrt(x − x) = 0``, whose derivative is ∞·0; elsewhere ``sqrt(1) − 1 = 0``, flat."""

    observation_score = None

    def observation_log_prob(self, o, s_next, a):
        lp = super().observation_log_prob(o, s_next, a)
        mask = torch.zeros(lp.shape, dtype=torch.bool)
        mask[0, :3] = True
        x0 = s_next[..., 0].expand(lp.shape)
        inside = torch.where(mask, x0 - x0, torch.ones_like(lp))
        return lp + torch.sqrt(inside) - torch.where(mask, torch.zeros_like(lp), torch.ones_like(lp))


@pytest.mark.parametrize("name", PARTICLE_FILTERS)
def test_a_nan_gradient_of_a_finite_log_likelihood_is_named(name):
    model, filt = _NaNGradient(state_dim=D), FILTERS[name]()
    belief, action, obs = _inputs(model, filt)
    message = _error(filt, model, belief, action, obs)
    assert message.startswith("model.observation_log_prob has a NaN or infinite gradient for up to 3 particles of "
                               "belief 0 during the particle evolution;"), message


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_neg_inf_log_likelihood_is_a_zero_likelihood(name):
    """``-inf`` from ``observation_log_prob`` is legitimate: no error, a finite belief."""
    model, filt = Faulty("observation_log_prob", -INF, k=5), FILTERS[name]()
    belief, action, obs = _inputs(model, filt)
    post = filt.update(model, belief, action, obs, gen(1))
    assert bool(torch.isfinite(post.particles).all())
    assert not bool(torch.isnan(post.log_weights).any())


def test_init_names_initial_belief():
    model = Faulty("initial_belief", NAN, k=4, belief=1)
    for filt in (SIRFilter(), ESCORTFilter()):
        with pytest.raises(NonFiniteError, match=r"^model\.initial_belief returned NaN for 4 particles of belief 1;"):
            filt.init(model, (B,), N, gen(0))


# ---------------------------------------------------------------------------------------------
# Zero likelihood everywhere
# ---------------------------------------------------------------------------------------------


class _ImpossibleForBelief0(LinearGaussian):
    """Every particle of belief 0 has zero likelihood: ``log(0·x) = −inf``, whose autograd gradient is
    0·∞ = NaN. With ``flat=True``, belief 0 gets a constant log-likelihood instead (a zero score)."""

    observation_score = None

    def __init__(self, flat: bool) -> None:
        super().__init__(state_dim=D)
        self.flat = flat

    def observation_log_prob(self, o, s_next, a):
        lp = super().observation_log_prob(o, s_next, a)
        x0 = s_next[:1, ..., 0].expand(lp[:1].shape)  # belief 0 only: no 0·∞ in the others' gradients
        first = 0.0 * x0 if self.flat else torch.log(0.0 * x0)
        return torch.cat([first, lp[1:]], dim=0)


@pytest.mark.parametrize("name", PARTICLE_FILTERS)
def test_all_impossible_particles_follow_the_prior(name):
    """Documented fallback: when every particle of a belief has zero likelihood, the likelihood score
    is 0 and the target weights are equal, so the belief moves exactly as under a flat likelihood
    (not frozen by a NaN gradient, and without NaN)."""
    results = []
    for flat in (False, True):
        model, filt = _ImpossibleForBelief0(flat), FILTERS[name]()
        belief, action, obs = _inputs(model, filt)
        results.append(filt.update(model, belief, action, obs, gen(1)).particles)
    assert bool(torch.isfinite(results[0]).all())
    torch.testing.assert_close(results[0], results[1], rtol=0, atol=0)


def test_sir_all_impossible_particles_keep_the_prior_weights():
    model, filt = _ImpossibleForBelief0(flat=False), SIRFilter(resample_threshold=0.0)
    belief, action, obs = _inputs(model, filt)
    post = filt.update(model, belief, action, obs, gen(1))
    torch.testing.assert_close(post.log_weights[0], belief.log_weights[0])
    assert bool(torch.isfinite(post.log_weights).all())


# ---------------------------------------------------------------------------------------------
# Results that overflow; fit
# ---------------------------------------------------------------------------------------------


def test_an_overflowing_result_is_named():
    """Finite inputs and model outputs, but a roughening so large that float32 overflows (the
    observations are uninformative, so the resampled particles stay spread out)."""
    model = LinearGaussian(state_dim=D, observation_cov=1e20 * torch.eye(D))
    filt = SIRFilter(resample_threshold=1.0, roughening=1e30)
    belief, action, obs = _inputs(model, filt)
    belief = ParticleBelief(belief.particles * 1e9, belief.log_weights)
    message = _error(filt, model, belief, action, obs)
    assert message.startswith("SIRFilter.update: its result's belief.particles have"), message
    assert "overflowed" in message


def test_fit_names_log_prob_and_the_particles():
    filt = ESCORTFilter(num_steps=3)
    x0 = torch.randn(2, 10, 2, generator=gen(0))

    def log_prob(z):
        lp = -(z**2).sum(-1)
        return torch.where(z[..., 0] > 0, torch.full_like(lp, NAN), lp)

    with pytest.raises(NonFiniteError, match=r"^log_prob returned NaN for \d+ particles? of belief \d"):
        filt.fit(log_prob, x0)
    bad = x0.clone()
    bad[1, 2, 0] = INF
    with pytest.raises(NonFiniteError, match=r"^particles: inf for 1 particle of belief 1;"):
        filt.fit(lambda z: -(z**2).sum(-1), bad)


# ---------------------------------------------------------------------------------------------
# check_finite: off switch, cost, no change to the numbers
# ---------------------------------------------------------------------------------------------


def test_check_finite_can_be_turned_off():
    model = LinearGaussian(state_dim=D)
    filt = SIRFilter()
    filt.check_finite = False
    belief, action, obs = _inputs(model, filt)
    particles = belief.particles.clone()
    particles[0, 0, 0] = NAN
    post = filt.update(model, ParticleBelief(particles, belief.log_weights), action, obs, gen(1))
    assert bool(torch.isnan(post.log_weights[0]).all())  # unchecked: the caller validates elsewhere
    assert "check_finite=False" in repr(filt) and "check_finite" not in repr(SIRFilter())
    for make in (SIRFilter, ESCORTFilter, SVGDFilter):
        with pytest.raises(ValueError, match=rf"^{make.__name__}\.check_finite: must be True or False, got 'yes'"):
            make().check_finite = "yes"
    assert SVGDFilter().check_finite is True


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_checks_do_not_change_a_finite_update(name):
    model = LinearGaussian(state_dim=D)
    out = []
    for check in (True, False):
        filt = FILTERS[name]()
        filt.check_finite = check
        belief, action, obs = _inputs(model, filt)
        post = filt.update(model, belief, action, obs, gen(1))
        out.append((post.particles, post.log_weights))
    for a, b in zip(*out):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


class _SyncCounter:
    """Counts the calls that read a tensor's value on the host (``bool``, ``int``, ``float``,
    ``item``, ``tolist``)."""

    NAMES = ("__bool__", "__int__", "__float__", "__index__", "item", "tolist")

    def __init__(self, monkeypatch) -> None:
        self.calls = 0
        for name in self.NAMES:
            original = getattr(torch.Tensor, name)
            monkeypatch.setattr(torch.Tensor, name, self._wrap(original))

    def _wrap(self, original):
        def counted(t, *args, **kwargs):
            self.calls += 1
            return original(t, *args, **kwargs)

        return counted


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_the_checks_cost_one_host_synchronisation(name, monkeypatch):
    model = LinearGaussian(state_dim=D)
    filters = {check: FILTERS[name]() for check in (True, False)}
    inputs = {}
    for check, filt in filters.items():
        filt.check_finite = check
        inputs[check] = _inputs(model, filt)
    counter = _SyncCounter(monkeypatch)
    calls = {}
    for check, filt in filters.items():
        counter.calls = 0
        filt.update(model, *inputs[check], gen(1))
        calls[check] = counter.calls
    assert calls[True] - calls[False] == 1, calls


def test_a_failure_that_is_not_a_non_finite_value_passes_unchanged():
    guard = FiniteGuard("SIRFilter", (2,))
    guard.values("belief.particles:", torch.zeros(2, 3, 1), "fix")
    with pytest.raises(KeyError, match="unrelated"):
        with guard.diagnosing():
            raise KeyError("unrelated")
    guard.verify()  # all finite: no error
    guard.values("model.transition returned", torch.tensor([[[0.0], [NAN]], [[0.0], [0.0]]]), "fix it")
    with pytest.raises(NonFiniteError, match=r"^model\.transition returned NaN for 1 particle of belief 0; fix it$"):
        guard.verify()
    # a matrix is counted per entry, even when its first dimension equals the batch size
    guard = FiniteGuard("ESCORTFilter", (2,))
    guard.model_values("model.transition_scale_tril", torch.tensor([[1.0, 0.0], [INF, 1.0]]), per_particle=False)
    with pytest.raises(NonFiniteError, match=r"^model\.transition_scale_tril returned inf in 1 of 4 entries;"):
        guard.verify()


def test_input_validation_reads_the_host_once(monkeypatch):
    """The action range and the observation's finiteness are checked with one host read; the
    messages are built only when the check fails."""
    from escort_rl.belief.base import validate_update_inputs

    model = LinearGaussian(state_dim=D)
    filt = FILTERS["sir"]()
    belief, action, observation = _inputs(model, filt)
    counter = _SyncCounter(monkeypatch)
    validate_update_inputs(model, belief, action, observation)
    assert counter.calls == 1
    with pytest.raises(ValueError, match=r"^action: values must lie in \[0, "):
        validate_update_inputs(model, belief, torch.full_like(action, model.n_actions), observation)
    with pytest.raises(ValueError, match=r"^observation: contains NaN or Inf \(flat batch indices \[0\]\)"):
        validate_update_inputs(model, belief, action, torch.cat([observation[:1] * NAN, observation[1:]]))


@pytest.mark.parametrize("shape", [(0,), (5,), (3, 4, 2)])
@pytest.mark.parametrize("seed", range(6))
def test_the_one_pass_checks_agree_with_isfinite(shape, seed):
    """``all_finite`` and ``below_inf`` (one pass each) say what ``torch.isfinite`` says, with NaN, ±inf or
    neither planted anywhere, and near the float32 limit (where a sum would overflow)."""
    from escort_rl.belief.checks import all_finite, below_inf

    g = gen(seed)
    t = torch.randn(shape, generator=g) * 3e38 if seed % 2 else torch.randn(shape, generator=g)
    if t.numel():
        flat = t.view(-1)
        for value in torch.tensor([NAN, INF, -INF])[torch.rand(3, generator=g) < 0.4]:
            flat[torch.randint(t.numel(), (1,), generator=g)] = value
    assert bool(all_finite(t)) == bool(torch.isfinite(t).all())
    assert bool(below_inf(t)) == bool((torch.isfinite(t) | torch.isneginf(t)).all())
    assert bool(all_finite(t > 0)) and bool(below_inf(t.to(torch.int64) if t.isfinite().all() else t > 0))
