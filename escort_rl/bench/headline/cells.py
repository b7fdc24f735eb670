"""The cells of ``bench headline``: one training seed of a row, trained and then evaluated
(:class:`TrainedCell`), and one evaluation of the scripted controller or a random policy
(:class:`FixedPolicyCell`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from escort_rl.bench.core.runner import Cell, ConfigCell
from escort_rl.reporting.paths import safe_name
from escort_rl.reporting.stats import mean_se


def row_overrides(base, row) -> list[str]:
    """``base`` (the run's sizes) then a row's own ``row``, without the base overrides the row
    replaces: the same key, or every key under a group the row picks (``filter=sir_rough`` drops
    ``filter.compile=false``)."""
    from escort_rl.trainers.resume import merge_override_lists

    return merge_override_lists(list(base), list(row))


def dropped_overrides(base, row) -> list[str]:
    """The overrides of ``base`` that ``row`` drops without naming their key, which :func:`row_overrides`
    leaves out because the row picks their group: ``trainer=recurrent_ppo`` drops the run's
    ``trainer.iterations=100`` unless the row gives ``trainer.iterations`` too.

    Example:
        >>> dropped_overrides(["trainer.iterations=100", "trainer.epochs=4", "env=hidden_goal"],
        ...                   ["trainer=recurrent_ppo", "trainer.epochs=2"])
        ['trainer.iterations=100']
    """
    kept = set(row_overrides(base, row))
    named = {o.split("=", 1)[0].lstrip("+~") for o in row}
    return [o for o in base if o not in kept and o.split("=", 1)[0].lstrip("+~") not in named]


BELIEF_KEYS = ("filter", "num_particles")
"""The config keys that make a belief: the filter group and its particle count."""
CONTROLLER_KEY = "env.scripted_options"
"""The one other key a ``--scripted-on`` entry may set: the controller's options on that belief (the hidden
goal's look-first rule, ``env.scripted_options={confidence:0.9}``), for a second controller on the same belief."""


def belief_overrides(belief: str) -> tuple[str, ...]:
    """A belief of the table as the overrides that pick it: a filter config name (``escort_train``) is
    ``("filter=escort_train",)``; a belief written as overrides (``"filter=sir num_particles=3000"``, space
    separated) is those.

    Examples:
        >>> belief_overrides("sir_rough")
        ('filter=sir_rough',)
        >>> belief_overrides("filter=sir num_particles=3000")
        ('filter=sir', 'num_particles=3000')
    """
    words = tuple(belief.split())
    return words if any("=" in w for w in words) else (f"filter={belief}",)


def check_belief(belief: str) -> None:
    """Raise a ``ValueError`` naming ``--scripted-on`` where ``belief`` sets more than a belief's keys
    (:data:`BELIEF_KEYS`: ``filter``, ``filter.*`` and ``num_particles``): a run override such as
    ``env=...`` given after ``--scripted-on`` lands there, and would run the controller on another task.

    Example:
        >>> check_belief("filter=sir num_particles=3000")  # a belief: nothing to say
        >>> try:
        ...     check_belief("env=lightdark10d_continuous")
        ... except ValueError as err:
        ...     print(str(err)[:66])
        --scripted-on: 'env=lightdark10d_continuous' sets env, which is no
    """
    for word in belief_overrides(belief):
        key = word.split("=", 1)[0].lstrip("+~")
        if key.split(".", 1)[0] not in BELIEF_KEYS and key != CONTROLLER_KEY:
            raise ValueError(f"--scripted-on: '{belief}' sets {key}, which is not part of a belief (a filter name, or "
                             f"overrides of filter, filter.* and num_particles) nor the controller's "
                             f"{CONTROLLER_KEY}; put the run's own overrides ({key}=...) before --scripted-on")


def belief_identity(config: dict) -> str:
    """What a composed config's belief is (its :data:`BELIEF_KEYS`, resolved; ``filter.compile`` left out: it
    changes the time, not the belief), as one comparable string: a trained row and a scripted controller act
    on the same belief when theirs are equal."""
    import json

    belief = {k: config.get(k) for k in BELIEF_KEYS}
    belief["filter"] = {k: v for k, v in (belief["filter"] or {}).items() if k != "compile"}
    return json.dumps(belief, sort_keys=True, default=str)


def per_episode(metrics: dict) -> dict:
    """The per-episode lists the table aggregates: success, final distance (NaN without a goal),
    return and env steps."""
    return {"success": metrics["success"].double().tolist(),
            "final_distance": metrics["final_distance"].double().tolist(),
            "episode_return": metrics["episode_return"].double().tolist(),
            "steps": metrics["steps"].double().tolist()}


@dataclass(frozen=True, kw_only=True)
class TrainedCell(Cell):
    """One training seed of a row: ``escort-rl train`` with ``overrides`` and ``seed`` into
    ``run_dir`` (a killed cell resumes there from its last checkpoint), then the final policy, greedy,
    on ``episodes`` episodes from env seed ``eval_seed``. With ``curve_every = k > 0`` the run keeps a
    checkpoint every ``k`` iterations and each one is evaluated the same way: the cell's ``curve``
    (success, steps and return against training frames)."""

    label: str
    overrides: tuple[str, ...]
    seed: int
    run_dir: str
    episodes: int
    eval_seed: int
    curve_every: int = 0

    def key(self) -> str:
        return f"trained/{safe_name(self.label)}/seed{self.seed}"

    def overrides_with_run(self) -> list[str]:
        curve = [f"trainer.checkpoint_every={self.curve_every}", "trainer.keep_checkpoints=100000"] \
            if self.curve_every > 0 else []
        return [*self.overrides, *curve, f"seed={self.seed}", f"output_dir={self.run_dir}"]

    def spec(self) -> dict:
        """The cell's fields and the config they compose to: a changed config file is a new cell. Where the run
        is written (``run_dir``, the config's ``output_dir``) is left out, so that a relative and an absolute
        ``--output`` for the same folder, or a moved folder, name the same cell."""
        from omegaconf import OmegaConf

        from escort_rl.config import compose

        config = OmegaConf.to_container(compose(self.overrides_with_run()), resolve=True)
        config.pop("output_dir", None)
        fields = {k: v for k, v in super().spec().items() if k != "run_dir"}
        return {**fields, "config": config}

    def run(self) -> dict:
        from omegaconf import OmegaConf
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        from escort_rl.trainers.builders import build_model
        from escort_rl.trainers.checkpointing import list_checkpoints, load_checkpoint, resolve_checkpoint
        from escort_rl.trainers.evaluate import first_episode_metrics, run_episodes, trained_policy
        from escort_rl.trainers.resume import train_config
        from escort_rl.trainers.training import train

        overrides = self.overrides_with_run()
        if (Path(self.run_dir) / "checkpoints").is_dir():
            overrides.append(f"resume={self.run_dir}")
        cfg, saved = train_config(overrides)
        if saved is None or saved["trainer_state"]["iteration"] < int(cfg.trainer.iterations):
            train(cfg, resume_state=saved, progress=False)
        model = build_model(cfg.env, cfg.device)

        def evaluate(checkpoint) -> tuple[dict, float]:
            policy, make, estimates = trained_policy(cfg, checkpoint)
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                rollout, step_s = run_episodes(cfg, policy, self.episodes, self.eval_seed, make=make)
            return per_episode(first_episode_metrics(rollout, model, estimates(rollout))), step_s

        checkpoint = resolve_checkpoint(self.run_dir)
        state = load_checkpoint(checkpoint)["trainer_state"]
        final, step_s = evaluate(checkpoint)
        curve = []
        if self.curve_every > 0:
            for earlier in list_checkpoints(Path(self.run_dir) / "checkpoints"):
                frames = int(load_checkpoint(earlier)["trainer_state"].get("frames", 0))
                episodes = final if frames == int(state.get("frames", 0)) else evaluate(earlier)[0]
                curve.append({"frames": frames, **{k: mean_se(v)[0] for k, v in episodes.items()}})
        return {"label": self.label, "seed": self.seed, "filter": str(cfg.filter.name),
                "run_dir": self.run_dir, "config": OmegaConf.to_container(cfg, resolve=True), **final,
                "frames": int(state.get("frames", 0)), "train_seconds": float(state.get("seconds", float("nan"))),
                "seconds_per_step": step_s, "curve": sorted(curve, key=lambda point: point["frames"])}


@dataclass(frozen=True, kw_only=True)
class FixedPolicyCell(ConfigCell):
    """The scripted controller at velocity gain ``gain`` on the belief ``filter`` (a filter config name,
    or the overrides that pick the belief: :func:`belief_overrides`; ``gain=None``: uniform-random
    actions), on ``episodes`` episodes from env seed ``eval_seed``; ``overrides`` are the run's sizes."""

    filter: str
    gain: float | None
    overrides: tuple[str, ...]
    episodes: int
    eval_seed: int

    def config(self):
        from escort_rl.config import compose

        return compose(row_overrides(self.overrides, belief_overrides(self.filter)))

    def key(self) -> str:
        policy = "random" if self.gain is None else f"scripted-gain{self.gain:g}"
        return f"fixed/{safe_name(self.filter)}/{policy}-seed{self.eval_seed}"

    def run(self) -> dict:
        from escort_rl.trainers.builders import build_model, scripted_policy
        from escort_rl.trainers.evaluate import first_episode_metrics, run_episodes

        cfg = self.config()
        model = build_model(cfg.env, cfg.device)
        policy = None if self.gain is None else scripted_policy(cfg, model, gain_v=self.gain)  # env.scripted_options
        if self.gain is not None and policy is None:
            raise ValueError(f"bench headline: {type(model).__name__} has no scripted controller")
        rollout, step_s = run_episodes(cfg, policy, self.episodes, self.eval_seed)
        return {"filter": self.filter, "gain": self.gain, "eval_seed": self.eval_seed,
                **per_episode(first_episode_metrics(rollout, model)), "seconds_per_step": step_s}
