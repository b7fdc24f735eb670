"""POPGym's noisy control tasks: belief policies from known models beside memory models.

- :mod:`~escort_rl.bench.popgym.spec`: every setting (:class:`POPGymSpec`);
- :mod:`~escort_rl.bench.popgym.cells`: one row's training run, a random policy's episodes;
- :mod:`~escort_rl.bench.popgym.report`: MMER and the Markdown;
- :mod:`~escort_rl.bench.popgym.cli`: ``escort-rl bench popgym``.
"""

from escort_rl.bench.popgym.cli import main, register
from escort_rl.bench.popgym.spec import POPGymSpec

__all__ = ["POPGymSpec", "main", "register"]
