"""``escort-rl bench atari``: the flickering games, Atari's (the paper's Table 4) and MinAtar's.

Each (game, agent, seed) is one cell: an A2C training run (:class:`escort_rl.trainers.atari_a2c.AtariA2C`)
on the training scaffold, in ``<output>/runs/<game>/<agent>/seed<k>``, or, for the ``random`` agent,
games played with uniform-random actions. The scaffold checkpoints a run every iteration, so a killed
or stopped benchmark resumes each unfinished cell from its last checkpoint when the same command runs
again, and a larger ``--frames`` continues finished cells. The cells run on the runner's backends
(``--backend inprocess | process | ray``).

- :mod:`~escort_rl.bench.atari.settings`: ``configs/bench/atari.yaml`` and ``minatar.yaml``, and a
  cell's run config;
- :mod:`~escort_rl.bench.atari.cells`: a training cell and a random-policy cell;
- :mod:`~escort_rl.bench.atari.report`: the table (at equal frames and at equal wall-clock, beside
  random's and the paper's) and the learning curves;
- :mod:`~escort_rl.bench.atari.cli`: the command.
"""

from escort_rl.bench.atari.cells import AtariCell, run_atari_cell, run_random_cell
from escort_rl.bench.atari.cli import main, register
from escort_rl.bench.atari.report import LAST_GAMES, markdown_table, plot_curves, summarise
from escort_rl.bench.atari.settings import cell_config, frames_per_update, load_settings, settings_path

__all__ = ["LAST_GAMES", "AtariCell", "cell_config", "frames_per_update", "load_settings", "main", "markdown_table",
           "plot_curves", "register", "run_atari_cell", "run_random_cell", "settings_path", "summarise"]
