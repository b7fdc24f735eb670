"""Sweeps of overrides, as Hydra's ``--multirun`` writes them: ``seed=0,1,2`` is three runs."""

from __future__ import annotations

import itertools

from escort_rl.config.errors import ConfigError


def expand_sweep(overrides: list[str]) -> list[list[str]]:
    """One override list per combination of the sweeps in ``overrides`` (Hydra's syntax: ``a=1,2``,
    ``range(0,3)``, ``choice(x,y)``), in the order Hydra's basic sweeper runs them (the last sweep
    varies fastest); overrides without a sweep go into every run unchanged. A malformed override
    raises :class:`ConfigError` naming it.

    Examples:
        >>> expand_sweep(["seed=0,1", "filter=sir", "trainer.lr=0.001,0.0003"])  # doctest: +NORMALIZE_WHITESPACE
        [['seed=0', 'filter=sir', 'trainer.lr=0.001'], ['seed=0', 'filter=sir', 'trainer.lr=0.0003'],
         ['seed=1', 'filter=sir', 'trainer.lr=0.001'], ['seed=1', 'filter=sir', 'trainer.lr=0.0003']]
        >>> expand_sweep(["seed=range(0,3)"])
        [['seed=0'], ['seed=1'], ['seed=2']]
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    choices = []
    for item in overrides:
        try:
            override = parser.parse_override(item)
        except HydraException as err:
            raise ConfigError(f"overrides: cannot parse '{item}' ({str(err).splitlines()[0]})") from None
        if override.is_sweep_override():
            key = override.get_key_element()
            choices.append([f"{key}={value}" for value in override.sweep_string_iterator()])
        else:
            choices.append([item])
    return [list(combo) for combo in itertools.product(*choices)]
