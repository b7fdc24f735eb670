"""Importance weights, their ESS and tempering (escort_rl.belief.importance), and the correlation
projections built on them (escort_rl.belief.projections): closed forms and known directions."""

import math

import pytest
import torch

from escort_rl.belief import ESCORTFilter, SIRFilter
from escort_rl.belief.importance import (
    effective_sample_size,
    normalised_weights,
    tempered_log_weights,
    weighted_quantile_points,
)
from escort_rl.belief.projections import (
    correlation_force,
    correlation_projections,
    max_sliced_directions,
    projection_shape,
    projector,
    random_deflated_projections,
)
from escort_rl.models import LinearGaussian


def test_ess_closed_forms():
    assert float(effective_sample_size(torch.zeros(7))) == pytest.approx(7.0)
    # two particles with weights p, 1 − p: ESS = 1 / (p² + (1 − p)²)
    p = 0.8
    ell = torch.tensor([math.log(p), math.log(1 - p)])
    assert float(effective_sample_size(ell)) == pytest.approx(1 / (p * p + (1 - p) ** 2), rel=1e-6)
    # k equal weights among N (the rest impossible): ESS = k
    ell = torch.tensor([0.0, 0.0, 0.0, -math.inf, -math.inf])
    assert float(effective_sample_size(ell)) == pytest.approx(3.0)
    # a row that is all impossible gets equal weights, never NaN
    w = normalised_weights(torch.full((2, 4), -math.inf))
    torch.testing.assert_close(w, torch.full((2, 4), 0.25))


def test_ess_of_gaussian_importance_weights_matches_the_closed_form(per_test_generator):
    """q = N(0, 1), p = N(0, s²) with s² < 2: E_q[(p/q)²] = 1 / (s sqrt(2 − s²)), so ESS/N → s sqrt(2 − s²)."""
    s = 0.7
    n = 200_000
    y = torch.randn(n, generator=per_test_generator, dtype=torch.float64)
    ell = -0.5 * (y / s) ** 2 - math.log(s) + 0.5 * y**2
    expected = s * math.sqrt(2 - s * s)
    assert float(effective_sample_size(ell)) / n == pytest.approx(expected, rel=0.03)


def test_tempering_reaches_the_floor_and_leaves_good_weights_alone(per_test_generator):
    ell = 8.0 * torch.randn(5, 100, generator=per_test_generator, dtype=torch.float64)
    tempered, beta, ess = tempered_log_weights(ell, 0.3)
    assert bool((ess < 30).all())  # these weights are degenerate
    reached = effective_sample_size(tempered)
    assert bool((reached >= 30 - 1e-6).all()) and bool((reached <= 30 * 1.01).all())  # the largest such β
    assert bool(((beta > 0) & (beta < 1)).all())
    torch.testing.assert_close(tempered, beta.unsqueeze(-1) * (ell - ell.amax(-1, keepdim=True)))
    # ESS non-increasing in β
    betas = torch.linspace(0, 1, 21, dtype=torch.float64)
    curve = torch.stack([effective_sample_size(b * ell[0]) for b in betas])
    assert bool((curve[1:] <= curve[:-1] + 1e-9).all())
    flat = torch.zeros(2, 50)
    same, beta1, _ = tempered_log_weights(flat, 0.3)
    assert bool((beta1 == 1).all()) and torch.equal(same, flat)
    with pytest.raises(ValueError, match="ess_floor"):
        tempered_log_weights(flat, 1.5)


def test_tempering_keeps_impossible_samples_impossible():
    ell = torch.tensor([[0.0, -30.0, -math.inf, -math.inf]])
    tempered, beta, _ = tempered_log_weights(ell, 0.5)
    w = normalised_weights(tempered)
    assert float(w[0, 2:].sum()) == 0.0 and 0 < float(beta) < 1


def test_weighted_quantile_points_hold_the_weighted_quantiles():
    y = torch.tensor([[[0.0], [1.0], [2.0], [3.0]]])
    ell = torch.log(torch.tensor([[0.5, 0.25, 0.25, 0.0]]))
    pts = weighted_quantile_points(y, ell)[0, :, 0]
    torch.testing.assert_close(pts, torch.tensor([0.0, 0.0, 1.0, 2.0]))  # levels 1/8, 3/8, 5/8, 7/8


def test_projection_shape_caps_the_frame_at_the_dimension():
    assert projection_shape(20, 5, 2) == (5, 2)
    assert projection_shape(7, 5, 2) == (3, 2)
    assert projection_shape(1, 5, 3) == (1, 1)


def test_deflated_projections_are_orthonormal(per_test_generator):
    g = per_test_generator
    x = torch.randn(3, 80, 9, generator=g)
    y = torch.randn(3, 80, 9, generator=g) * torch.linspace(0.5, 3, 9)
    a, w = correlation_projections(x, y, torch.randn(3, 80, generator=g), n_proj=4, proj_dim=2)
    frame = a.transpose(-1, -2).reshape(3, 8, 9)  # every column of every A_k
    torch.testing.assert_close(frame @ frame.transpose(-1, -2), torch.eye(8).expand(3, 8, 8), atol=1e-5, rtol=0)
    torch.testing.assert_close(w.sum(-1), torch.ones(3))
    r = random_deflated_projections((3,), 9, 4, 2, g)
    frame = r.transpose(-1, -2).reshape(3, 8, 9)
    torch.testing.assert_close(frame @ frame.transpose(-1, -2), torch.eye(8).expand(3, 8, 8), atol=1e-5, rtol=0)


def _unit(d: int, g: torch.Generator) -> torch.Tensor:
    u = torch.randn(d, generator=g, dtype=torch.float64)
    return u / u.norm()


def test_max_sliced_ascent_finds_the_direction_of_difference_between_two_gaussians(per_test_generator):
    """x ~ N(0, I), y ~ N(0, I + 8 u uᵀ): the projected W1 is largest along ±u, and the deflated second
    direction is orthogonal to it."""
    g = per_test_generator
    d, n = 8, 2000
    u = _unit(d, g)
    x = torch.randn(1, n, d, generator=g, dtype=torch.float64)
    z = torch.randn(1, n, d, generator=g, dtype=torch.float64)
    y = z + (math.sqrt(9.0) - 1.0) * (z @ u).unsqueeze(-1) * u
    theta0 = torch.linalg.qr(torch.randn(d, 2, generator=g, dtype=torch.float64))[0].T.unsqueeze(0)
    theta, w = max_sliced_directions(x, y, theta0, ascent_steps=30, deflate=True)
    assert abs(float(theta[0, 0] @ u)) > 0.95
    assert abs(float(theta[0, 0] @ theta[0, 1])) < 1e-8
    assert float(w[0, 0]) > float(w[0, 1])


def test_correlation_projections_find_a_shift_of_the_importance_weighted_target(per_test_generator):
    """The target samples are a broad cloud reweighted toward a shifted Gaussian (weights p/q): the first
    projection direction is the shift's."""
    g = per_test_generator
    d, n = 6, 400
    u = _unit(d, g).to(torch.float32)
    x = torch.randn(1, n, d, generator=g)  # the particles: N(0, I)
    y = 2.0 * torch.randn(1, n, d, generator=g)  # q = N(0, 4 I)
    mu = 2.5 * u
    ell = -0.5 * ((y - mu) ** 2).sum(-1) + 0.5 * (y**2).sum(-1) / 4.0  # log p − log q, p = N(mu, I)
    a, w = correlation_projections(x, y, ell, n_proj=1, proj_dim=1, ascent_steps=20)
    assert abs(float(a[0, 0, :, 0] @ u)) > 0.9


def test_correlation_force_is_minus_lambda_times_the_gradient_of_r_corr(per_test_generator):
    """F_corr(x_i) = −λ N ∂R/∂φ(x_i) for R = (1/N) Σ_i Σ_k w_k |A_kᵀ(φ_i − φ̄)|² (the factor 2 included)."""
    g = per_test_generator
    n, d = 30, 6
    a = random_deflated_projections((), d, 3, 2, g)
    w = torch.tensor([0.5, 0.3, 0.2])
    phi = torch.randn(n, d, generator=g, requires_grad=True)
    centred = phi - phi.mean(0, keepdim=True)
    r = sum(w[k] * ((centred @ a[k]) ** 2).sum(-1) for k in range(3)).mean()
    (grad,) = torch.autograd.grad(r, phi)
    force = correlation_force(phi.detach(), a, w, 0.3)
    torch.testing.assert_close(force, -0.3 * n * grad, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(force.sum(0), torch.zeros(d), atol=1e-5, rtol=0)  # sums to zero
    assert projector(a, w).shape == (d, d)


def test_fit_weighs_its_target_samples_by_p_over_q(per_test_generator):
    """The projections' weights are p/q: when the start samples the target exactly, they are equal (ESS N)."""
    g = per_test_generator
    x0 = torch.randn(2, 100, 3, generator=g)

    def log_p(z):
        return -0.5 * (z * z).sum(-1)

    filt = ESCORTFilter(num_steps=2)
    filt.fit(log_p, x0, proposal_log_prob=log_p, generator=g)
    diag = filt.importance_diagnostics()
    assert diag["mean_ess_fraction"] == pytest.approx(1.0) and diag["tempered_fraction"] == 0.0
    # a narrow target seen from the broad start: degenerate weights, tempered up to the floor
    filt = ESCORTFilter(num_steps=2, ess_floor=0.25)
    filt.fit(lambda z: -50.0 * ((z - 1.0) ** 2).sum(-1), x0, generator=g)
    diag = filt.importance_diagnostics()
    assert diag["mean_ess_fraction"] < 0.25 and diag["tempered_fraction"] == 1.0 and diag["mean_beta"] < 1
    with pytest.raises(ValueError, match="ess_floor"):
        ESCORTFilter(ess_floor=2.0)


def test_filters_report_the_ess_of_their_weights(per_test_generator):
    model = LinearGaussian()
    g = per_test_generator
    for filt in (SIRFilter(), ESCORTFilter(num_steps=3)):
        assert filt.importance_diagnostics() == {}
        b = filt.init(model, (4,), 50, generator=g)
        s = model.initial_state((4,), g)
        a = torch.zeros(4, dtype=torch.long)
        s = model.transition(s, a, g)
        filt.update(model, b, a, model.observe(s, a, g), generator=g)
        diag = filt.importance_diagnostics()
        assert diag["count"] == 4 and 0 < diag["min_ess_fraction"] <= diag["mean_ess_fraction"] <= 1


def test_the_velocity_form_rests_where_svgd_rests_and_the_position_form_contracts():
    """DESIGN's fixed-point analysis: at λ < 1/2 the velocity form cannot move SVGD's fixed point; the
    position form does, toward a narrower belief."""
    from escort_rl.bench.calibration import fixed_point_check

    kw = dict(d=3, n=100, batch=2, num_steps=400)
    svgd = fixed_point_check(ESCORTFilter(lambda_corr=0.0), **kw)
    velocity = fixed_point_check(ESCORTFilter(lambda_corr=0.3), **kw)
    position = fixed_point_check(ESCORTFilter(lambda_corr=0.1, corr_form="position"), **kw)
    assert velocity[0] == pytest.approx(svgd[0], rel=0.02) and velocity[1] == pytest.approx(svgd[1], abs=0.02)
    assert position[0] < 0.5 * svgd[0]
    with pytest.warns(UserWarning, match="lambda_corr=1.0: with the velocity form"):
        ESCORTFilter(lambda_corr=1.0)
