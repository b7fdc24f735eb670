"""The accuracy–cost frontier: for any model, each filter over its cost knobs against the
reference posterior, and the Pareto front of distance against time per update.

- :mod:`~escort_rl.bench.frontier.spec`: every setting of a run (:class:`FrontierSpec`,
  :class:`RegimeSpec`, :class:`DecisionsSpec`) and their defaults;
- :mod:`~escort_rl.bench.frontier.cells`: the model spec, the reference and one filter's cell;
- :mod:`~escort_rl.bench.frontier.pareto`: the front and the best point within each budget (pure);
- :mod:`~escort_rl.bench.frontier.run`: the grid (:func:`run_frontier`);
- :mod:`~escort_rl.bench.frontier.report`: the Markdown and the advice line;
- :mod:`~escort_rl.bench.frontier.cli`: ``escort-rl bench frontier``.
"""

from escort_rl.bench.frontier.cli import main, register
from escort_rl.bench.frontier.pareto import best_at_budgets, pareto_front
from escort_rl.bench.frontier.run import run_frontier
from escort_rl.bench.frontier.spec import DecisionsSpec, FrontierSpec, RegimeSpec

__all__ = ["DecisionsSpec", "FrontierSpec", "RegimeSpec", "best_at_budgets", "main", "pareto_front", "register",
           "run_frontier"]
