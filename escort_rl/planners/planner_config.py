"""The planner defaults of each domain, from ``configs/planner/<domain>.yaml``."""

from __future__ import annotations

from omegaconf import OmegaConf
from torch import Tensor

from escort_rl.config import ConfigError, config_dir
from escort_rl.config.params import build_params
from escort_rl.planners.pomcpow import POMCPOW, POMCPOWParams


def planner_domains() -> list[str]:
    """The domains with a planner config (the file names in ``configs/planner/``)."""
    return sorted(path.stem for path in (config_dir() / "planner").glob("*.yaml"))


def load_planner_config(domain: str) -> dict:
    """The POMCPOW keyword arguments for ``domain`` (e.g. ``"lightdark10d"``), as a plain dict.

    Raises :class:`escort_rl.config.ConfigError` (a ``ValueError``) for an unknown domain, a key
    that is not a :class:`POMCPOWParams` field or a value out of its range.
    """
    path = config_dir() / "planner" / f"{domain}.yaml"
    if not path.is_file():
        raise ConfigError(f"domain: no planner config for '{domain}'; choose one of {planner_domains()}")
    values = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    check_planner_settings(values, f"configs/planner/{domain}.yaml")
    return values


def build_planner(domain: str, **overrides) -> POMCPOW:
    """A :class:`POMCPOW` with ``domain``'s defaults, any of them replaced by ``overrides``
    (e.g. ``build_planner("lightdark10d", n_sim=100, max_depth=5)``; ``leaf_value`` too)."""
    leaf_value = overrides.pop("leaf_value", None)
    params = check_planner_settings({**load_planner_config(domain), **overrides}, "build_planner")
    return POMCPOW(params, leaf_value=leaf_value)


def check_planner_settings(values: dict, where: str) -> POMCPOWParams:
    """The :class:`POMCPOWParams` of ``values``, checked (keys and ranges). Raises
    :class:`ConfigError` ``"<where>: POMCPOW.<field>: ..."``, or naming the known settings for an
    unknown key."""
    try:
        return build_params(POMCPOWParams, None, values, owner="POMCPOW")
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None


def zero_leaf_value(state: Tensor, depth: int) -> float:
    """A leaf value of 0 for every state (POMCPOW's ``leaf_value``)."""
    return 0.0


LIGHTDARK1D_PLANNER = dict(max_depth=5, exploration_constant=100.0, k_action=3.0, alpha_action=0.0,
                           k_observation=2.0, alpha_observation=0.1, discount=0.9, leaf_value=zero_leaf_value)
"""POMCPOW's settings (all its arguments but ``n_sim`` and ``time_budget_s``) for the 1-D test
problem :class:`escort_rl.models.LightDark1D`, used by the tests and by ``escort-rl bench
planner-budget``: depth 5 reaches the light and comes back; an exploration constant of the order of
the rewards; all three actions at once (``k_a = 3``, ``α_a = 0``); few observation children
(``k_o = 2``, ``α_o = 0.1``) so that each holds many weighted particles; and a zero leaf value,
since random rollouts (which declare at random) mostly add noise."""
