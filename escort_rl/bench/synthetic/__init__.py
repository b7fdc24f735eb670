"""The synthetic benchmark: the paper's GMM targets (Table 2) and the 5-mode
scalability targets (the RMSE scaling table), under a static and a tracking protocol.

- :mod:`~escort_rl.bench.synthetic.spec`: every setting of a run (:class:`SyntheticSpec`,
  :class:`ScalingSpec`) and their defaults;
- :mod:`~escort_rl.bench.synthetic.cells`: the starts, the fits, the scores and the cells;
- :mod:`~escort_rl.bench.synthetic.tracking`: the tracking protocol's model and its error;
- :mod:`~escort_rl.bench.synthetic.run`: the grids (:func:`run_synthetic`, :func:`run_scaling`);
- :mod:`~escort_rl.bench.synthetic.paper` and :mod:`~escort_rl.bench.synthetic.report`: the paper's
  figures and the Markdown, with a verdict per row;
- :mod:`~escort_rl.bench.synthetic.cli`: ``escort-rl bench synthetic`` and ``bench scaling``.
"""

from escort_rl.bench.synthetic.cells import (
    INITS,
    SyntheticCell,
    TrackingCell,
    fit_particles,
    initial_particles,
    row_filter,
    scaled,
    score_particles,
    start_distribution,
)
from escort_rl.bench.synthetic.cli import filter_arguments, main, register
from escort_rl.bench.synthetic.run import run_scaling, run_synthetic
from escort_rl.bench.synthetic.spec import PROTOCOLS, SCALING_DIMS, SYNTHETIC_TARGETS, ScalingSpec, SyntheticSpec

__all__ = ["INITS", "PROTOCOLS", "SCALING_DIMS", "SYNTHETIC_TARGETS", "ScalingSpec", "SyntheticCell", "SyntheticSpec",
           "TrackingCell", "filter_arguments", "fit_particles", "initial_particles", "main", "row_filter", "register",
           "run_scaling", "run_synthetic", "scaled", "score_particles", "start_distribution"]
