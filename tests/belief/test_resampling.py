"""The resampling schemes (escort_rl.belief.resampling): each unbiased (mean offspring count N·wᵢ, within a
confidence bound), the variance ordering of Douc & Cappé (2005) and the closed-form variances, batched over
[*B], and what a degenerate row does."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from escort_rl.belief.resampling import SCHEMES, effective_sample_size, resample_indices, systematic

WEIGHTS = torch.tensor([0.31, 0.02, 0.17, 0.005, 0.245, 0.09, 0.12, 0.04])
"""A fixed weight vector with fractional parts of N·wᵢ spread over (0, 1)."""
ROWS = 20000
"""Independent resamplings of the same weights, drawn as one batch."""


def offspring_counts(scheme: str, weights: torch.Tensor = WEIGHTS, rows: int = ROWS, seed: int = 0,
                     num_samples: int | None = None) -> torch.Tensor:
    """``[rows, N]`` offspring counts of ``rows`` independent resamplings (one batched call)."""
    n = weights.shape[-1]
    log_w = weights.log().expand(rows, n)
    idx = resample_indices(log_w, scheme, torch.Generator().manual_seed(seed), num_samples)
    return torch.zeros(rows, n, dtype=torch.float64).scatter_add_(1, idx, torch.ones_like(idx, dtype=torch.float64))


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
@pytest.mark.parametrize("num_samples", [None, 13])
def test_every_scheme_is_unbiased_within_a_confidence_bound(scheme, num_samples):
    counts = offspring_counts(scheme, num_samples=num_samples)
    m = WEIGHTS.shape[0] if num_samples is None else num_samples
    assert torch.all(counts.sum(1) == m)  # always M offspring in all
    expected = m * WEIGHTS.double()
    se = counts.std(0) / math.sqrt(ROWS)
    # a scheme with Var Nᵢ = 0 for some i (systematic at an integer M·wᵢ) has se 0 there: exact
    assert torch.all((counts.mean(0) - expected).abs() <= 5 * se + 1e-9), (counts.mean(0), expected)


def test_the_variance_ordering_of_douc_and_cappe_holds_and_matches_the_closed_forms():
    var = {scheme: offspring_counts(scheme, seed=1).var(0) for scheme in SCHEMES}
    n = WEIGHTS.shape[0]
    w = WEIGHTS.double()
    multinomial = n * w * (1 - w)
    frac = n * w - torch.floor(n * w)
    left = frac.sum()  # R, the residual draws
    residual = left * (frac / left) * (1 - frac / left)
    systematic = frac * (1 - frac)
    # sample variances of 20000 draws are within about ±2% (4.5 relative s.e. of a variance with
    # light tails: sqrt(2/ROWS)); 15% leaves room for the kurtosis of small counts
    for scheme, exact in (("multinomial", multinomial), ("residual", residual), ("systematic", systematic)):
        assert torch.allclose(var[scheme], exact, rtol=0.15, atol=2e-3), (scheme, var[scheme], exact)
    assert torch.all(var["residual"] <= multinomial * 1.02)
    assert torch.all(var["stratified"] <= multinomial * 1.02)
    assert torch.all(var["systematic"] <= var["stratified"] * 1.02 + 2e-3)
    assert var["multinomial"].sum() > 1.5 * var["residual"].sum()  # the ordering is strict on these weights


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_schemes_are_batched_over_leading_dimensions(scheme):
    """A [3, 4, N] batch gives [3, 4, M] indices, each row drawn from its own weights."""
    g = torch.Generator().manual_seed(2)
    log_w = torch.randn(3, 4, 6, generator=g)
    log_w[1, 2] = torch.tensor([0.0, *[-math.inf] * 5])  # all weight on particle 0
    idx = resample_indices(log_w, scheme, g, num_samples=9)
    assert idx.shape == (3, 4, 9) and idx.dtype == torch.int64
    assert int(idx.min()) >= 0 and int(idx.max()) < 6
    assert torch.all(idx[1, 2] == 0)


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_a_row_that_is_not_finite_resamples_as_if_equal_and_zero_weights_are_never_drawn(scheme):
    g = torch.Generator().manual_seed(3)
    log_w = torch.tensor([[-math.inf] * 4, [float("nan"), 0.0, 0.0, 0.0], [0.0, -math.inf, 0.0, -math.inf]])
    idx = resample_indices(log_w.expand(500, 3, 4), scheme, g)
    assert set(idx[:, 0].unique().tolist()) == {0, 1, 2, 3}
    assert set(idx[:, 2].unique().tolist()) <= {0, 2}


def test_an_unknown_scheme_is_named_with_the_choices():
    with pytest.raises(ValueError, match=r"resampling: unknown scheme 'sobol'; expected one of \['multinomial'"):
        resample_indices(torch.zeros(3), "sobol")


def test_effective_sample_size_is_n_for_equal_weights_and_one_for_a_single_particle():
    assert effective_sample_size(torch.zeros(2, 5)).tolist() == pytest.approx([5.0, 5.0])
    assert effective_sample_size(torch.tensor([3.0, -math.inf, -math.inf])).item() == 1.0
    w = WEIGHTS.double()
    assert effective_sample_size(w.log()).item() == pytest.approx(1 / (w * w).sum().item())


# ------------------------------------------------------------------- systematic: counts within one of N·wᵢ


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


weight_lists = st.lists(
    st.one_of(st.just(0.0), st.floats(min_value=1e-6, max_value=1.0)), min_size=1, max_size=60
).filter(lambda ws: sum(ws) > 0)


@settings(max_examples=150, deadline=None)
@given(weights=weight_lists, seed=st.integers(0, 2**31 - 1))
def test_systematic_resample_counts_are_within_one_of_n_w(weights, seed):
    """Each particle is drawn floor(N w_i) or ceil(N w_i) times; zero-weight ones never (float64)."""
    w = torch.tensor(weights, dtype=torch.float64)
    n = w.numel()
    log_w = torch.log(w / w.sum())
    idx = systematic(log_w.expand(8, n), gen(seed))
    assert idx.shape == (8, n) and idx.dtype == torch.int64
    assert bool(((idx >= 0) & (idx < n)).all())
    expected = n * w / w.sum()
    for row in idx:
        counts = torch.bincount(row, minlength=n).double()
        assert counts.sum() == n
        assert bool(((counts - expected).abs() < 1 + 1e-9).all()), (counts, expected)
        assert bool((counts[w == 0] == 0).all())
        # systematic resampling returns the indices in order
        assert bool((row[1:] >= row[:-1]).all())


@settings(max_examples=60, deadline=None)
@given(weights=weight_lists, seed=st.integers(0, 2**31 - 1))
def test_systematic_resample_counts_float32_interior(weights, seed):
    """The same count property for float32 log-weights (small sets, where round-off stays small)."""
    w = torch.tensor(weights, dtype=torch.float64)
    n = w.numel()
    log_w = torch.log(w / w.sum()).float()
    idx = systematic(log_w.expand(4, n), gen(seed))
    expected = n * torch.softmax(log_w.double(), -1)
    for row in idx:
        counts = torch.bincount(row, minlength=n).double()
        assert bool(((counts - expected).abs() < 1 + 1e-3).all()), (counts, expected)


def test_systematic_resample_uniform_weights_is_identity():
    n = 37
    idx = systematic(torch.full((5, n), -math.log(n)), gen(1))
    assert torch.equal(idx, torch.arange(n).expand(5, n))


def test_systematic_resample_degenerate_weight():
    log_w = torch.full((3, 10), -float("inf"))
    log_w[torch.arange(3), torch.tensor([0, 4, 9])] = 0.0
    idx = systematic(log_w, gen(2))
    assert torch.equal(idx, torch.tensor([0, 4, 9]).unsqueeze(-1).expand(3, 10))


def test_systematic_resample_draws_any_number_of_indices():
    # M = 8 draws from weights (1/2, 0, 1/4, 1/4): exactly M w_i of each, whatever the offset
    log_w = torch.log(torch.tensor([0.5, 0.0, 0.25, 0.25], dtype=torch.float64))
    for seed in range(5):
        idx = systematic(log_w, gen(seed), num_samples=8)
        assert idx.shape == (8,)
        assert torch.bincount(idx, minlength=4).tolist() == [4, 0, 2, 2]




def _largest_rand(monkeypatch):
    """Make torch.rand return the largest value below 1 of the requested dtype (a legal draw)."""
    real_rand = torch.rand

    def fake_rand(*size, generator=None, dtype=None, device=None, **kwargs):
        dtype = dtype or torch.get_default_dtype()
        one = torch.tensor(1.0, dtype=dtype)
        top = torch.nextafter(one, torch.tensor(0.0, dtype=dtype)).item()
        real_rand(*size, generator=generator, dtype=dtype, device=device)  # keep the stream moving
        shape = size[0] if len(size) == 1 and isinstance(size[0], (tuple, list, torch.Size)) else size
        return torch.full(tuple(shape), top, dtype=dtype, device=device)

    monkeypatch.setattr(torch, "rand", fake_rand)


@pytest.mark.parametrize("n", [2, 5, 20_000])
def test_systematic_resample_largest_u_with_positive_weights(monkeypatch, n):
    """With u just below 1 and all weights positive the counts are still floor/ceil of N w."""
    w = torch.linspace(1.0, 2.0, n, dtype=torch.float64)
    log_w = torch.log(w / w.sum())
    _largest_rand(monkeypatch)
    idx = systematic(log_w, gen(0))
    counts = torch.bincount(idx, minlength=n).double()
    assert bool(((counts - n * w / w.sum()).abs() < 1 + 1e-9).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_systematic_resample_never_picks_a_trailing_zero_weight_particle(monkeypatch, dtype):
    n = 20_000
    log_w = torch.zeros(n, dtype=dtype)
    log_w[-1] = -float("inf")  # the last particle is impossible
    _largest_rand(monkeypatch)
    idx = systematic(log_w, gen(0))
    assert int((idx == n - 1).sum()) == 0


def test_the_scheme_is_a_config_key_and_a_bad_one_is_named():
    from conftest import config_error
    from escort_rl import make_filter
    from escort_rl.config import compose

    cfg = compose(["filter=sir", "filter.resampling=residual"])
    assert cfg.filter.resampling == "residual"
    assert make_filter("sir", resampling="stratified").resampling == "stratified"
    assert "filter.resampling" in config_error(["filter=sir", "filter.resampling=sobol"])
