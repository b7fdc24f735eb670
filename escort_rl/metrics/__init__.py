"""Distances between particle sets and to a reference posterior, and the reference itself.

- :mod:`.distances`: MMD², exact 1-D and sliced Wasserstein distances, weighted and batched;
- :mod:`.modes`: mode coverage of a mixture target's components;
- :mod:`.moments`: moments and correlations of particle sets and mixtures, and their errors;
- :mod:`.reference`: the reference posterior (a large bootstrap particle filter, or the model's
  exact posterior) and each belief's distances to it;
- :mod:`.rao_blackwell`: the Rao-Blackwellised particle filter a reference runs where a model's state
  is a Gaussian sum given part of it;
- :mod:`.checks`: the input checks they share.
"""

from escort_rl.metrics.distances import (
    kernel_mean,
    median_gamma,
    mmd_squared,
    sliced_wasserstein,
    sphere_directions,
    squared_distances,
    wasserstein_1d,
    weighted_mmd_squared,
    weighted_sliced_wasserstein,
    weighted_wasserstein_1d,
)
from escort_rl.metrics.modes import (
    chi2_quantile,
    mode_coverage,
    mode_coverage_mahalanobis,
    mode_fractions,
    mode_fractions_mahalanobis,
)
from escort_rl.metrics.moments import (
    correlation_error,
    correlation_matrix,
    mixture_correlation,
    mixture_mean_and_covariance,
    rmse_of_mean,
    safe_correlation,
    weighted_moments,
)
from escort_rl.metrics.reference import (
    DamagedReferenceError,
    Reference,
    exact_posterior_start,
    exact_posterior_update,
    exact_reference,
    has_exact_posterior,
    reference_posterior,
    state_parts,
    summarize_series,
)

__all__ = [
    "DamagedReferenceError",
    "Reference",
    "chi2_quantile",
    "correlation_error",
    "correlation_matrix",
    "exact_posterior_start",
    "exact_posterior_update",
    "exact_reference",
    "has_exact_posterior",
    "kernel_mean",
    "median_gamma",
    "mixture_correlation",
    "mixture_mean_and_covariance",
    "mmd_squared",
    "mode_coverage",
    "mode_coverage_mahalanobis",
    "mode_fractions",
    "mode_fractions_mahalanobis",
    "reference_posterior",
    "rmse_of_mean",
    "safe_correlation",
    "sliced_wasserstein",
    "sphere_directions",
    "squared_distances",
    "state_parts",
    "summarize_series",
    "wasserstein_1d",
    "weighted_mmd_squared",
    "weighted_moments",
    "weighted_sliced_wasserstein",
    "weighted_wasserstein_1d",
]
