"""The paper's own figures for the synthetic benchmark, as printed (mean, standard error), for the
"paper against ours" tables. Table 2 (``tab:belief_assessment``) and the RMSE scaling table
(``tab:rmse_synthetic``) of the appendix. The paper's W1 row of 1D is its "Wasserstein" row; its
other targets report sliced W1 there."""

from __future__ import annotations

TABLE2_METHODS = ("escort", "svgd", "dvrl", "sir")
"""The paper's Table 2 columns, in our method names."""

TABLE2 = {
    "gmm1d": {
        "mmd2": [(0.057, 0.01), (0.012, 0.01), (0.216, 0.05), (0.116, 0.07)],
        "w1": [(0.549, 0.04), (0.305, 0.02), (1.967, 0.07), (0.811, 0.22)],
        "mode_coverage": [(1.0, 0.0), (1.0, 0.0), (0.867, 0.13), (1.0, 0.0)],
    },
    "gmm2d": {
        "mmd2": [(0.052, 0.02), (0.062, 0.01), (0.071, 0.01), (0.2288, 0.04)],
        "sliced_w1": [(0.263, 0.01), (0.383, 0.01), (0.749, 0.14), (1.397, 0.11)],
        "corr_error": [(0.491, 0.16), (0.5178, 0.04), (0.6594, 0.09), (0.8285, 0.28)],
        "mode_coverage": [(1.0, 0.0), (1.0, 0.0), (1.0, 0.0), (1.0, 0.0)],
    },
    "gmm3d": {
        "mmd2": [(0.002, 0.002), (0.008, 0.009), (0.361, 0.01), (0.414, 0.06)],
        "sliced_w1": [(0.305, 0.01), (0.481, 0.02), (1.442, 0.04), (2.656, 0.34)],
        "corr_error": [(0.761, 0.004), (0.819, 0.02), (0.882, 0.01), (1.003, 0.01)],
        "mode_coverage": [(1.0, 0.0), (1.0, 0.0), (1.0, 0.0), (1.0, 0.0)],
    },
    "gmm5d": {
        "mmd2": [(0.05, 0.003), (0.09, 0.07), (0.263, 0.004), (0.394, 0.009)],
        "sliced_w1": [(0.301, 0.01), (0.3987, 0.02), (1.0838, 0.01), (2.939, 0.26)],
        "corr_error": [(0.7224, 0.006), (0.7401, 0.014), (0.823, 0.011), (0.997, 0.003)],
        "mode_coverage": [(1.0, 0.0), (1.0, 0.0), (1.0, 0.0), (0.125, 0.0)],
    },
    "gmm20d": {
        "mmd2": [(0.005, 0.0008), (0.006, 0.0006), (0.264, 0.005), (0.584, 0.008)],
        "sliced_w1": [(0.326, 0.007), (0.393, 0.005), (1.117, 0.025), (2.854, 0.187)],
        "corr_error": [(0.556, 0.03), (0.589, 0.05), (0.708, 0.03), (0.640, 0.01)],
        "mode_coverage": [(1.0, 0.0), (1.0, 0.0), (0.58, 0.04), (0.12, 0.04)],
    },
}
"""target -> metric -> [(mean, s.e.) for each of :data:`TABLE2_METHODS`]."""

RMSE_TABLE = {
    1: ((0.15, 0.02), (0.14, 0.02)),
    5: ((0.35, 0.04), (0.45, 0.05)),
    20: ((0.65, 0.07), (0.88, 0.10)),
    50: ((0.95, 0.09), (1.42, 0.09)),
    100: ((1.35, 0.18), (2.15, 0.28)),
    200: ((1.90, 0.23), (3.35, 0.57)),
}
"""dimension -> ((ESCORT mean, s.e.), (ESCORT-NoCorr mean, s.e.)): the paper's RMSE scaling table."""
