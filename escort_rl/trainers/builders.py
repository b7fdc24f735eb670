"""Build models, filters, environments and policies from a config (the only place that maps
config names to classes)."""

from __future__ import annotations

from functools import partial

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import TransformedEnv

from escort_rl.belief import ESCORTFilter, SIRFilter, SVGDFilter
from escort_rl.config import ConfigError
from escort_rl.envs import POMDPEnv
from escort_rl.models import DOMAINS, LightDark1D
from escort_rl.modules import DeepSetsActor
from escort_rl.transforms import BeliefTransform

# The benchmark domains, and the 1-D planning test problem (no env config; built by name for
# `escort-rl bench planner-budget --domain lightdark1d`).
MODELS = {**DOMAINS, "lightdark1d": LightDark1D}
FILTERS = {"sir": SIRFilter, "svgd": SVGDFilter, "escort": ESCORTFilter}


def _kwargs(node: DictConfig, exclude: tuple[str, ...] = ("name",)) -> dict:
    data = OmegaConf.to_container(node, resolve=True)
    return {k: v for k, v in data.items() if k not in exclude}


def build_model(env_cfg: DictConfig, device: str | torch.device = "cpu"):
    """The POMDP model named by ``env.name`` with the keyword arguments in ``env.model``."""
    if env_cfg.name not in MODELS:
        raise ConfigError(f"env.name: unknown environment '{env_cfg.name}'; choose one of {sorted(MODELS)}")
    try:
        return MODELS[env_cfg.name](**_kwargs(env_cfg.model), device=device)
    except TypeError as err:
        raise ConfigError(f"env.model: {err}") from None


def build_filter(filter_cfg: DictConfig):
    """The belief filter of class ``filter.kind`` with the keys other than ``name`` and ``kind`` as
    keyword arguments (``name`` labels a configuration, e.g. ``escort_nocorr``)."""
    kind = filter_cfg.get("kind", filter_cfg.name)
    if kind not in FILTERS:
        raise ConfigError(f"filter.kind: unknown filter '{kind}'; choose one of {sorted(FILTERS)}")
    try:
        return FILTERS[kind](**_kwargs(filter_cfg, exclude=("name", "kind")))
    except (TypeError, ValueError) as err:
        raise ConfigError(f"filter: {str(err).splitlines()[0]}") from None


def make_env(cfg: DictConfig, num_envs: int, seed: int | None = None) -> TransformedEnv:
    """``TransformedEnv(POMDPEnv(model, (num_envs,)), BeliefTransform(model, filter, N))``.

    Module-level (and picklable through ``functools.partial``) so that spawned collector workers
    can build it. The belief transform shares the env's generator, so ``env.set_seed`` seeds both.
    """
    model = build_model(cfg.env, cfg.device)
    base = POMDPEnv(model, batch_size=(num_envs,), device=cfg.device, seed=seed, max_steps=cfg.env.max_steps)
    return TransformedEnv(base, BeliefTransform(model, build_filter(cfg.filter), int(cfg.num_particles)))


def env_factory(cfg: DictConfig, num_envs: int, seed: int | None = None):
    """A picklable zero-argument factory for :func:`make_env`."""
    plain = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    return partial(make_env, plain, num_envs, seed)


def build_actor(cfg: DictConfig, state_dim: int, n_actions: int) -> DeepSetsActor:
    return DeepSetsActor(
        state_dim,
        n_actions,
        hidden=int(cfg.actor.hidden),
        input_loc=cfg.actor.input_loc,
        input_scale=cfg.actor.input_scale,
    )
