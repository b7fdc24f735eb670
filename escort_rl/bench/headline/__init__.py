"""The headline RL table: the default job over several training seeds beside PPO on SIR beliefs
only, the scripted controller at its best gain and a random policy.

- :mod:`~escort_rl.bench.headline.spec`: every setting (:class:`HeadlineSpec`);
- :mod:`~escort_rl.bench.headline.cells`: one training seed of a row, one fixed policy's evaluation;
- :mod:`~escort_rl.bench.headline.run`: the grid and its aggregation (:func:`run_headline`);
- :mod:`~escort_rl.bench.headline.report`: the Markdown;
- :mod:`~escort_rl.bench.headline.cli`: ``escort-rl bench headline``.
"""

from escort_rl.bench.headline.cli import main, register
from escort_rl.bench.headline.run import run_headline
from escort_rl.bench.headline.spec import HeadlineSpec

__all__ = ["HeadlineSpec", "main", "register", "run_headline"]
