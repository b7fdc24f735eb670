"""The base class of every training algorithm: the hooks that the training scaffold
(:func:`escort_rl.trainers.scaffold.run_training`) calls, and what each receives and returns.

The scaffold drives an :class:`Algorithm` through three hooks, in this order:

1. :attr:`Algorithm.components`, read once before the first iteration: ``{name: object}``, the
   modules and optimisers (and any object with ``state_dict`` / ``load_state_dict``) that a
   checkpoint holds. A resume restores each in place; every checkpoint saves each under its name.
   The names are the checkpoint's keys, so they never change (old checkpoints must load):
   ``actor``, ``critic``, ``optimizer``, ``readout_optimizer``, ``games``.
2. :meth:`Algorithm.iteration` ``(index, seed) -> dict``, once per iteration ``index`` (0-based,
   from the iteration the run starts at), with torch's global generator already seeded with
   ``seed``. It collects and learns, and returns the iteration's record: ``"frames"`` (an int, the
   env steps it took, which the scaffold sums), the scalars to log (floats: its loss terms, whose
   names start with ``loss`` where they must be finite, ``"fps"``, and the episode statistics of
   :func:`escort_rl.trainers.scaffold.episode_stats`).
3. :meth:`Algorithm.close`, once, when the run ends or fails: shut collectors and envs down.

An algorithm that collects through a :class:`~escort_rl.trainers.scaffold.StagedCollector` keeps it
as ``collectors`` (``None`` otherwise, as set here): when an iteration fails, the scaffold reads it
to name a collector worker process that died.

Every attribute a method reads is set in the ``__init__`` of the class that defines the method or of
one of its bases, and every ``__init__`` calls its parent's: the base sets ``cfg``, ``model`` and
``collectors``. A subclass that lacks a hook cannot be instantiated (``TypeError`` naming it).

Example::

    >>> class Mine(Algorithm):                                       # doctest: +SKIP
    ...     def __init__(self, cfg, model):
    ...         super().__init__(cfg, model)
    ...         self.actor = ...; self.optimizer = ...
    ...     @property
    ...     def components(self):
    ...         return {"actor": self.actor, "optimizer": self.optimizer}
    ...     def iteration(self, index, seed):
    ...         ...
    ...         return {"frames": frames, "loss": loss, "episode_return": mean_return}
    ...     def close(self):
    ...         ...
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from omegaconf import DictConfig, OmegaConf

from escort_rl.config.params import build_params


def trainer_params(params: type, trainer_cfg):
    """``params`` (a trainer's parameters dataclass) from a config's ``trainer`` group, checked;
    errors name ``trainer.<key>``."""
    values = (OmegaConf.to_container(trainer_cfg, resolve=True) if OmegaConf.is_config(trainer_cfg)
              else dict(trainer_cfg))
    values.pop("algorithm", None)
    return build_params(params, None, values, owner="trainer")


def algorithm(cfg: DictConfig) -> str:
    """``cfg.trainer.algorithm``, a registered trainer (configs saved before the key existed are
    ``reinforce``); an unknown name raises a ``ConfigError`` naming the choices."""
    from escort_rl.config import registry

    name = cfg.trainer.get("algorithm", "reinforce")
    registry.target("trainer", name)
    return name


def typed_trainer(cfg: DictConfig):
    """``cfg.trainer`` as the ``Params`` dataclass of its trainer (``trainer.algorithm``), checked."""
    from escort_rl.config import registry

    return trainer_params(registry.params("trainer", str(cfg.trainer.algorithm)), cfg.trainer)


class Algorithm(ABC):
    """A training algorithm of the scaffold (see the module docstring for the hooks).

    ``cfg``: the run config; ``model``: the POMDP model trained on (``None`` for an algorithm that
    has none, e.g. Atari's A2C). An algorithm whose class names a ``Params`` dataclass
    (:mod:`escort_rl.trainers.params`) owns ``self.params``, built from ``cfg.trainer`` and checked
    (a key the config lacks takes its default; an unknown key is an error naming it)."""

    Params: type | None = None

    def __init__(self, cfg: DictConfig, model=None) -> None:
        self.cfg, self.model = cfg, model
        self.collectors = None  # a StagedCollector, for an algorithm that collects through one
        self.params = None if self.Params is None else trainer_params(self.Params, cfg.trainer)

    @property
    @abstractmethod
    def components(self) -> dict:
        """``{name: module | optimizer | object with state_dict}``: what a checkpoint holds."""

    @abstractmethod
    def iteration(self, index: int, seed: int) -> dict:
        """Collect and learn for iteration ``index`` (0-based), seeded with ``seed``; return
        ``{"frames": int, **scalars}``."""

    belief_label: str | None = None
    """What the policy acts on when it is not a belief filter's particles (e.g. recurrent PPO's
    ``"none (GRU on raw observations)"``); ``None``: the particles of a filter of the config."""

    model_free: bool = False
    """Whether the algorithm trains without a model of the task (recurrent PPO's GRU on raw
    observations): the only kind that trains on an env group with no model (``env=popgym``)."""

    watch: tuple[str, ...] | None = None
    """The history keys the progress bar shows; ``None``: the return, and the final distance and
    success rate on a model with a goal."""

    @classmethod
    def reads_true_state(cls, params) -> bool:
        """Whether training reads the simulator's true state (an asymmetric critic,
        ``trainer.critic_input=state``), which an env without one (POPGym's own) cannot give."""
        return getattr(params, "critic_input", None) == "state"

    @classmethod
    def trained_policy(cls, cfg: DictConfig, checkpoint):
        """The trained policy of ``checkpoint``, the env maker it runs in, and a function ``rollout ->
        belief_mean [E, T, d]`` (``None``: the rollout's particles give the belief mean)."""
        raise NotImplementedError(f"{cls.__name__}.trained_policy: this trainer's policies are not evaluated "
                                  "by escort-rl evaluate")

    @classmethod
    def belief_of(cls, cfg: DictConfig, params, index: int) -> str:
        """What iteration ``index`` (0-based) of a run of ``cfg`` collects on, as
        ``evaluation/metrics.json``'s ``"filter"`` names it: the config name of the filter whose
        beliefs the policy reads (the warm-start filter during a warm start, then ``filter.name``), or
        :attr:`belief_label`. ``params``: the run's ``Params`` (``None`` without)."""
        if cls.belief_label is not None:
            return cls.belief_label
        run_filter = str(cfg.filter.name)
        filter_at = getattr(params, "filter_at", None)  # trainers with a warm start (BeliefTrainerParams)
        return run_filter if filter_at is None else filter_at(index, run_filter)

    def belief_at(self, index: int) -> str:
        """:meth:`belief_of` this run's iteration ``index``."""
        return self.belief_of(self.cfg, self.params, index)

    def plan_note(self) -> str:
        """What the run's plan line adds after the filters of its iterations (e.g. a teacher); ``""``: nothing."""
        return ""

    @abstractmethod
    def close(self) -> None:
        """Shut the algorithm's collectors and envs down (called once, also after a failure)."""
