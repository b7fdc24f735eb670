"""The domain benchmark (``escort-rl bench domains``) on Light-Dark, Kidnapped Robot and
Multi-Target Tracking, under protocol (a) "shared trajectories" (every method filters the same
seeded action/observation sequences from the same seeded priors) and protocol (b) "closed loop"
(each method trains its own policy and drives it).

- :mod:`~escort_rl.bench.domains.spec`: :class:`DomainsSpec`, every setting of a run, with the
  defaults (:meth:`DomainsSpec.full`) and ``--quick`` (:meth:`DomainsSpec.quick`);
- :mod:`~escort_rl.bench.domains.cells`: protocol (a)'s cells (:class:`FilterCell`, :class:`LearnedCell`);
- :mod:`~escort_rl.bench.domains.rows`: a row from its cells' results;
- :mod:`~escort_rl.bench.domains.grid`: the grid of cells and the reference posteriors;
- :mod:`~escort_rl.bench.domains.equal_time`: the equal wall-clock table;
- :mod:`~escort_rl.bench.domains.closed_loop_cells`: protocol (b)'s rows, runs and cell (:class:`ClosedLoopCell`);
- :mod:`~escort_rl.bench.domains.run`: the runs (:func:`run_domains`, :func:`run_closed_loop`);
- :mod:`~escort_rl.bench.domains.report`: the Markdown and the plots of both protocols;
- :mod:`~escort_rl.bench.domains.cli`: the command line.
"""

from escort_rl.bench.domains.cells import FilterCell, LearnedCell, train_learned_beliefs
from escort_rl.bench.domains.cli import main, register, spec_from_args
from escort_rl.bench.domains.closed_loop_cells import (
    EVALUATION_FILE,
    ClosedLoopCell,
    batch_length,
    method_spec,
    run_config,
    train_run,
)
from escort_rl.bench.domains.report import (
    closed_loop_markdown,
    domains_markdown,
    plot_closed_loop_error,
    plot_error_over_time,
)
from escort_rl.bench.domains.run import run_closed_loop, run_domains
from escort_rl.bench.domains.spec import PARTICLE_GRID, DomainsSpec

__all__ = ["EVALUATION_FILE", "PARTICLE_GRID", "ClosedLoopCell", "DomainsSpec", "FilterCell", "LearnedCell",
           "batch_length", "closed_loop_markdown", "domains_markdown", "main", "method_spec", "plot_closed_loop_error",
           "plot_error_over_time", "register", "run_closed_loop", "run_config", "run_domains", "spec_from_args",
           "train_learned_beliefs", "train_run"]
