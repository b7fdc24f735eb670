"""The domain benchmark, protocol (b) "closed loop": what a row is, its run config, its training and
its evaluation, as one cell per (domain, method) (:class:`ClosedLoopCell`).

For each domain and method (a filter config name under ``configs/filter/``) the trainer named by
``trainer`` in ``configs/bench/closed_loop.yaml`` (PPO; without the key, the config's default,
PPO) trains a DeepSets policy on that filter's beliefs, with the yaml's budget (per domain, the
same for every method: equal frames), and the trained policy then drives its own filter for
``episodes`` evaluation episodes: env seeds ``eval_seed + 0 .. episodes - 1``, the same for every
method, run as one batch. A uniform-random policy on the SIR belief is each domain's reference row
(its actions ignore the belief, so only its position error depends on the filter). The other rows
are named in the yaml (:func:`method_spec`):

- planner rows (``planners``, e.g. ``pomcpow_sir``) train nothing: POMCPOW with
  ``configs/planner/<domain>.yaml`` plans every decision on the named filter's belief;
- scripted rows (``scripted``, e.g. ``scripted_sir``) train nothing: the domain's PD controller
  (:class:`escort_rl.planners.ScriptedBeliefController`) acts on the named filter's belief mean. A
  domain without one (Kidnapped Robot: no goal) gives a row marked not applicable, with the reason;
- learned-belief rows (``learned``, e.g. ``dvrl``) train DVRL with its own trainer and the same
  budget; their position error is that of DVRL's state readout (see :mod:`escort_rl.trainers.dvrl_a2c`);
- recurrent rows (``recurrent``, e.g. ``recurrent_ppo``) train a GRU on the raw observations with
  their own trainer and the same budget: no belief, so no position error (NaN, printed "—").

Learned and recurrent rows are both of the ``learned`` policy kind (their own trainer, evaluated by
:func:`escort_rl.trainers.evaluate.trained_policy`); only the ``learned`` section is a learned
*belief* (protocol (a) reads it, see :func:`escort_rl.bench.methods.learned_methods`).

Each (domain, method) row is one cell (:class:`ClosedLoopCell`) of :mod:`escort_rl.bench.core.runner`,
so the rows run on any backend (``--backend process --workers K``, ``--backend ray``).

Equal frames: every trainer's iteration is ``num_envs`` episodes of ``env.max_steps`` steps, so the
budget ``{iterations, num_envs}`` means the same frames for every trained row. PPO and recurrent PPO
update every ``rollout_steps`` steps; :func:`run_config` sets ``rollout_steps`` to a divisor of the
episode length (:func:`batch_length`) and recurrent PPO's ``minibatches`` (whole env rows) to at most
``num_envs``, unless the budget sets them.

Metrics, mean ± standard error over the episodes: the final and time-averaged position error
``‖E_b[pos] − pos_true‖₂`` (the definition of protocol (a), ``escort_rl.models.position_error``), the
final distance to goal and success rate where the domain has a goal, the return, and the wall-clock
per step (policy + env + belief update for the batch, over steps 2..T; the first step, which compiles
with ``compile=true``, is timed apart). Each row also records its training frames and seconds.

Nothing is lost to a killed run: each (domain, method) trains in ``<output>/runs/<domain>/<method>``
with the trainer's checkpoints, and a rerun with the same ``output`` resumes every run from its last
checkpoint and skips the finished ones (it refuses a run folder that holds another configuration).
Each finished evaluation is saved as ``evaluation.json`` in its run folder, with everything it
depended on (the run's config, the planner's settings, the episodes, seeds and checkpoint); a rerun
reuses it when all of that is unchanged, so a killed benchmark repeats only the row it was in.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import OmegaConf

from escort_rl.bench.core.runner import Cell
from escort_rl.bench.methods import RANDOM, SECTIONS, applied_filter_set
from escort_rl.bench.trajectories import belief_failures
from escort_rl.trainers.evaluate import scripted_policy, trained_policy

REFERENCE_FILTER = "sir"  # the belief the random-policy row is scored on


class NotApplicable(ValueError):
    """A row that cannot run on a domain (a scripted row where the domain has no controller); the
    benchmark records it with the reason instead of failing."""


def method_spec(method: str, settings: dict) -> dict:
    """What a row name means: ``{"kind", "section", "filter", "trainer"}``.

    ``kind``: ``random``, ``planner``, ``scripted``, ``learned`` (the ``learned`` and ``recurrent``
    sections) or ``trained`` (any other name: a filter config, trained with the yaml's ``trainer``).
    ``filter``: the filter config the row's run config names (the belief a planner or scripted row acts
    on; the unused :data:`REFERENCE_FILTER` for learned rows, whose belief is their own or none).
    ``trainer``: the trainer config (``None``: the config's default)."""
    if method == RANDOM:
        return {"kind": RANDOM, "section": None, "filter": REFERENCE_FILTER, "trainer": settings.get("trainer")}
    for section, kind in SECTIONS.items():
        row = (settings.get(section) or {}).get(method)
        if row is not None:
            return {"kind": kind, "section": section,
                    "filter": row["filter"] if "filter" in row else REFERENCE_FILTER,
                    "trainer": row.get("trainer", settings.get("trainer"))}
    return {"kind": "trained", "section": None, "filter": method, "trainer": settings.get("trainer")}


def batch_length(steps: int, rollout_steps: int) -> int:
    """The PPO batch length for an episode of ``steps`` steps, so that an iteration is exactly
    ``num_envs × steps`` frames: ``rollout_steps`` when it divides ``steps``, else the largest divisor
    of ``steps`` in ``[rollout_steps / 2, rollout_steps]``, else ``steps`` (one batch per iteration)."""
    if steps <= rollout_steps:
        return steps
    return next((d for d in range(rollout_steps, (rollout_steps + 1) // 2 - 1, -1) if steps % d == 0), steps)


def run_config(domain: str, method: str, n: int, run_dir: Path, train: dict,
               filter_set: tuple = (), steps: int | None = None, seed: int = 0, trainer: str | None = None):
    """The training config of one (domain, method) run: ``env=domain filter=method`` with the
    budget ``train`` (trainer keys), the ``filter_set`` keys the
    method's filter has, and ``steps`` (when given) as the episode length. ``trainer``: a config of
    ``configs/trainer/`` (default: the config's, PPO). A trainer with ``rollout_steps`` (PPO,
    recurrent PPO) gets :func:`batch_length` unless ``train`` sets it, and recurrent PPO at most
    ``num_envs`` minibatches (they are whole env rows) unless ``train`` sets them."""
    from escort_rl.config import compose, registry

    overrides = [f"env={domain}", f"filter={method}", f"num_particles={n}", f"output_dir={run_dir}",
                 f"seed={seed}", *([f"trainer={trainer}"] if trainer else [])]
    overrides += [f"trainer.{k}={v}" for k, v in train.items()]
    overrides += [f"filter.{k}={v}" for k, v in applied_filter_set(method, filter_set).items()]
    if steps is not None:
        overrides.append(f"env.max_steps={steps}")
    cfg = compose(overrides)
    t = cfg.trainer
    if "rollout_steps" in t and "rollout_steps" not in train:
        t.rollout_steps = batch_length(int(cfg.env.max_steps), int(t.rollout_steps))
    if registry.resolve("trainer", t.algorithm).model_free and "minibatches" not in train:  # whole rows
        t.minibatches = min(int(t.minibatches), int(t.num_envs))
    if t.get("warm_start_filter") and "warm_start_filter" not in train:
        t.warm_start_filter = None  # each row trains on its own filter's beliefs only
    return cfg


def _comparable(config: dict) -> dict:
    """A run's config without the keys that may change between a run and its resumption."""
    config = json.loads(json.dumps(config))
    config.pop("resume", None)
    config.get("trainer", {}).pop("iterations", None)
    return config


def train_run(cfg, progress: bool = False) -> dict:
    """Train (or resume, or skip when finished) the run in ``cfg.output_dir``. Returns the frames,
    iterations, training seconds (summed over sessions) and the iteration it resumed from."""
    from escort_rl.reporting.paths import display_path
    from escort_rl.trainers.checkpointing import CheckpointLoadError, load_checkpoint, resolve_checkpoint
    from escort_rl.trainers.training import train

    run_dir = Path(cfg.output_dir)
    saved = None
    if (run_dir / "checkpoints").is_dir():
        try:
            saved = load_checkpoint(resolve_checkpoint(run_dir))
        except CheckpointLoadError:
            saved = None  # no complete checkpoint yet: start over
    if saved is not None and _comparable(saved["config"]) != _comparable(OmegaConf.to_container(cfg, resolve=True)):
        raise ValueError(f"--output: '{run_dir}' holds a run with another configuration; pass another --output "
                         "or delete that folder")
    resumed_from = int(saved["trainer_state"]["iteration"]) if saved is not None else 0
    train(cfg, resume_state=saved, progress=progress)
    final = load_checkpoint(resolve_checkpoint(run_dir))
    history = final["trainer_state"]["history"]
    return {"iterations": int(final["trainer_state"]["iteration"]), "frames": int(final["trainer_state"]["frames"]),
            "seconds": float(sum(h["seconds"] for h in history)), "resumed_from_iteration": resumed_from,
            "checkpoint": display_path(Path(final["path"])),
            "last_iteration_return": float(history[-1]["episode_return"]) if history else float("nan")}


def scripted_row_policy(cfg):
    """The domain's scripted controller on the belief mean of ``cfg``'s filter
    (:func:`escort_rl.trainers.evaluate.scripted_policy`); raises :class:`NotApplicable` with the
    reason where the domain has none."""
    from escort_rl.planners import scripted_controller_for
    from escort_rl.trainers.builders import build_model

    model = build_model(cfg.env, cfg.device)
    policy = scripted_policy(cfg, model)
    if policy is None:
        try:
            scripted_controller_for(model)
            reason = f"no scripted controller for {type(model).__name__}"
        except ValueError as e:
            reason = str(e).splitlines()[0].removeprefix("scripted_controller_for: ")
        raise NotApplicable(f"not applicable: {reason}")
    return policy


def planner_policy(cfg, domain: str, seed: int):
    """POMCPOW with ``configs/planner/<domain>.yaml``, planning on the belief of ``cfg``'s filter."""
    from escort_rl.planners import POMCPOWPolicy, build_planner
    from escort_rl.trainers.builders import build_model

    return POMCPOWPolicy(build_model(cfg.env, cfg.device), build_planner(domain), seed=seed)


def evaluate_run(cfg, policy, episodes: int, eval_seed: int, greedy: bool, make=None, estimates=None) -> dict:
    """Roll ``policy`` (uniform-random actions when ``None``) on ``episodes`` seeded episodes of
    ``cfg``'s env and filter. Returns the summary (mean ± s.e.), the mean position error at each step,
    and the seconds per step; for a planner, also its seconds per decision. ``make``, ``estimates``:
    the env maker and belief-mean function of :func:`escort_rl.trainers.evaluate.trained_policy`
    (default: ``cfg``'s filter in the env, the particles' mean)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from escort_rl.trainers.builders import build_model, make_env
    from escort_rl.trainers.evaluate import first_episode_metrics, run_episodes, summarise_episodes

    model = build_model(cfg.env, cfg.device)
    timing: dict = {}
    mode = ExplorationType.DETERMINISTIC if greedy else ExplorationType.RANDOM
    with set_exploration_type(mode):
        rollout, per_step = run_episodes(cfg, policy, episodes, eval_seed, timing, make=make or make_env)
    metrics = first_episode_metrics(rollout, model, estimates(rollout) if estimates is not None else None)
    err = metrics["position_error"]  # [E, T], NaN after an episode ends
    seen = (~torch.isnan(err)).sum(0)
    over_time = torch.where(seen > 0, torch.nan_to_num(err).sum(0) / seen.clamp_min(1), torch.nan)
    summary = summarise_episodes(metrics)
    per_episode = {"final_position_error": err[torch.arange(err.shape[0]), metrics["length"] - 1].tolist(),
                   "episode_return": metrics["episode_return"].tolist()}
    out = {"summary": summary, "per_episode": per_episode, "error_over_time": over_time.tolist(),
           "seconds_per_step": per_step, "first_step_seconds": timing.get("first_step_seconds", float("nan"))}
    if getattr(policy, "decisions", 0):
        out["seconds_per_decision"] = policy.planning_seconds / policy.decisions
    return out


EVALUATION_FILE = "evaluation.json"


def _evaluation_key(cfg, kind: str, domain: str, episodes: int, eval_seed: int, greedy: bool,
                    checkpoint: str | None) -> dict:
    """What an evaluation row depends on, as plain JSON (compared in full on reuse)."""
    key = {"config": OmegaConf.to_container(cfg, resolve=True), "policy": kind, "episodes": episodes,
           "eval_seed": eval_seed, "greedy": greedy, "checkpoint": checkpoint}
    key["config"].pop("resume", None)
    if kind == "planner":
        from escort_rl.planners import load_planner_config

        key["planner"] = load_planner_config(domain)
    if kind == "scripted":
        from escort_rl.planners.scripted import DEFAULT_GAIN_V

        key["controller"] = {"gain_v": DEFAULT_GAIN_V}
    return json.loads(json.dumps(key))


def _saved_evaluation(run_dir: Path, key: dict) -> dict | None:
    """The evaluation saved in ``run_dir`` under ``key``, or ``None`` (none, unreadable or stale)."""
    path = run_dir / EVALUATION_FILE
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return saved.get("result") if saved.get("key") == key else None


def _save_evaluation(run_dir: Path, key: dict, result: dict) -> None:
    """Write atomically (a killed write leaves the previous file or none)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    tmp = run_dir / (EVALUATION_FILE + ".tmp")
    tmp.write_text(json.dumps({"key": key, "result": result}))
    tmp.replace(run_dir / EVALUATION_FILE)


@dataclass(frozen=True)
class ClosedLoopCell(Cell):
    """One row of protocol (b): train (or resume, or reuse) the (domain, method) run in ``run_dir``,
    then evaluate it on ``episodes`` seeded episodes (or reuse the saved evaluation).

    ``kind``, ``section``, ``filter``, ``trainer``: the row's :func:`method_spec`; ``budget``: the
    trainer keys, as ``(key, value)`` pairs. The run folder is the cell's store (checkpoints and
    ``evaluation.json``), so the runner keeps no copy (``stored = False``); on a cluster, ``run_dir``
    must be on a filesystem every node sees."""

    domain: str
    method: str
    kind: str
    section: str | None
    filter: str
    trainer: str | None
    particles: int
    episodes: int
    steps: int | None
    budget: tuple
    filter_set: tuple
    run_dir: str
    eval_seed: int
    greedy: bool
    train_progress: bool = False
    stored = False

    def key(self) -> str:
        return f"closed_loop/{self.domain}/{self.method}"

    def run(self) -> dict:
        d, m, kind = self.domain, self.method, self.kind
        # the learned rows' filter config is unused (their belief is their own, or none)
        cfg = run_config(d, self.filter, self.particles, Path(self.run_dir), dict(self.budget),
                         self.filter_set if kind != "learned" else (), self.steps, trainer=self.trainer)
        trains = kind in ("trained", "learned")
        belief = {"learned": m, "recurrent": "none"}.get(self.section, self.filter)
        row = {"domain": d, "method": m, "filter": belief, "particles": self.particles, "episodes": self.episodes,
               "steps": int(cfg.env.max_steps), "policy": kind,
               "trainer": str(cfg.trainer.algorithm) if trains else None, "train": None, "failed": None}
        try:
            policy = make = estimates = None
            if kind == "scripted":
                policy = scripted_row_policy(cfg)  # NotApplicable before anything runs
            if trains:
                row["train"] = train_run(cfg, progress=self.train_progress)
            key = _evaluation_key(cfg, kind, d, self.episodes, self.eval_seed, self.greedy,
                                  (row["train"] or {}).get("checkpoint"))
            evaluation = _saved_evaluation(Path(cfg.output_dir), key)
            row["evaluation_reused"] = evaluation is not None
            if evaluation is None:
                if trains:
                    policy, make, estimates = trained_policy(cfg, row["train"]["checkpoint"])
                elif kind == "planner":
                    policy = planner_policy(cfg, d, self.eval_seed)
                evaluation = evaluate_run(cfg, policy, self.episodes, self.eval_seed, self.greedy, make, estimates)
                _save_evaluation(Path(cfg.output_dir), key, evaluation)
            row.update(evaluation)
        except NotApplicable as e:
            row["failed"] = {"message": str(e).splitlines()[0], "not_applicable": True}
        except belief_failures() as e:
            row["failed"] = {"message": str(e).splitlines()[0]}
        return row
