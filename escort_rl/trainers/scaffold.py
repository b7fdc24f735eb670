"""The training scaffold: one loop that owns a run, whatever the algorithm.

The scaffold owns the run directory (``config.yaml``, ``checkpoints/``, ``logs/``, ``history.json``),
per-iteration seeding, checkpoint rotation, the logger, the progress bar and the history (kept
once, in the trainer state that every checkpoint carries). It drives an
:class:`~escort_rl.trainers.algorithm.Algorithm`: ``components`` (what a checkpoint holds),
``iteration(index, seed) -> dict`` and ``close()`` (see :mod:`escort_rl.trainers.algorithm` for
what each receives and returns). :class:`CollectorAlgorithm` is the base of the algorithms that
collect through a :class:`StagedCollector`, so that a collector worker process that dies ends the
run with one line naming the worker and the last checkpoint (:class:`CollectorWorkerDied`).

Every iteration ``i`` is seeded with :func:`iteration_seed` (torch's global generator and the
envs), so a resumed run collects exactly the data an uninterrupted run would have, and reaches the
same parameters. Where a run starts from (a new run, or a checkpoint and its run directory) is
decided by :mod:`escort_rl.trainers.resume`. Every start removes the temporary folders of a
checkpoint write that a kill interrupted, and cuts the logs back to the iteration it starts from, so
that every iteration is logged once. Checkpoints are verified before they are read (see
:mod:`escort_rl.trainers.checkpointing`).

Example::

    >>> algorithm = PPO(cfg, model)                       # doctest: +SKIP
    >>> run_dir = run_training(cfg, algorithm)            # doctest: +SKIP
"""

from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.checkpoint import CheckpointRotation
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.record.loggers import TensorboardLogger
from tqdm import tqdm

from escort_rl.models import has_goal
from escort_rl.trainers.algorithm import Algorithm
from escort_rl.trainers.checkpointing import checkpoint_dir, remove_interrupted_writes, save_checkpoint
from escort_rl.trainers.resume import restore


def iteration_seed(base: int, iteration: int) -> int:
    """The seed of iteration ``i``: every iteration is reproducible on its own, so a resumed run
    collects exactly the data an uninterrupted run would have."""
    return (int(base) * 1_000_003 + int(iteration) * 7_919) % (2**31 - 1)


def truncate_scalar_logs(log_dir: Path, iteration: int) -> None:
    """Cut every CSV scalar log under ``log_dir/scalars`` back to the rows of steps ``<= iteration``.

    A run killed after its last checkpoint has logged iterations that its resume runs again; this
    drops them (and a half-written last row), so that each iteration appears once. A file is
    rewritten through a temporary file and a rename, so a kill here leaves the old or the new one."""
    for path in sorted((Path(log_dir) / "scalars").glob("*.csv")):
        lines = path.read_text().splitlines(keepends=True)
        kept = [line for line in lines if _csv_step(line) is not None and _csv_step(line) <= iteration]
        if kept != lines:
            partial = path.with_name(path.name + ".truncating")
            partial.write_text("".join(kept))
            os.replace(partial, path)


def _csv_step(line: str) -> int | None:
    """The step of a complete ``step,value`` row of TorchRL's CSV logger (``None``: not one)."""
    step, _, value = line.rstrip("\n").partition(",")
    if not line.endswith("\n") or not value:
        return None
    try:
        float(value)
        return int(step)
    except ValueError:
        return None


class ResumingTensorboardLogger(TensorboardLogger):
    """TorchRL's TensorBoard logger whose writer drops the events at steps ``>= purge_step`` that an
    earlier, interrupted session of the run wrote (``SummaryWriter(purge_step=...)``)."""

    def __init__(self, exp_name: str, log_dir: str, purge_step: int) -> None:
        self.purge_step = purge_step
        super().__init__(exp_name=exp_name, log_dir=log_dir)

    def _create_experiment(self):
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter(log_dir=os.path.join(self.log_dir, self.exp_name), purge_step=self.purge_step)


def make_logger(cfg: DictConfig, run_dir: Path, start_iteration: int = 0):
    """TorchRL's CSV logger (or TensorBoard with ``logger.backend=tensorboard``, Weights & Biases
    with ``logger.backend=wandb``) under ``run_dir/logs``, for a run that starts after iteration
    ``start_iteration`` (0: a new run). The steps logged after it by an earlier session are dropped
    (:func:`truncate_scalar_logs`; TensorBoard's ``purge_step``), so that each iteration is logged
    once. W&B logs into project ``logger.project``, offline unless ``logger.offline=false``: an offline
    run lands in ``logs/wandb/`` and ``wandb sync`` uploads it later."""
    from torchrl.record.loggers import CSVLogger

    if cfg.logger.backend == "wandb":
        from torchrl.record.loggers import WandbLogger

        offline = bool(cfg.logger.get("offline", True))
        return WandbLogger(exp_name=run_dir.name, offline=offline, save_dir=str(run_dir / "logs"),
                           project=str(cfg.logger.get("project", "escort-rl")),
                           mode="offline" if offline else "online")
    if cfg.logger.backend == "tensorboard":
        return ResumingTensorboardLogger(exp_name="logs", log_dir=str(run_dir), purge_step=start_iteration + 1)
    truncate_scalar_logs(run_dir / "logs", start_iteration)
    return CSVLogger(exp_name="logs", log_dir=str(run_dir))


def make_collector(cfg: DictConfig, factory, policy, frames_per_batch: int, reset_at_each_iter: bool):
    """A TorchRL ``Collector`` (``collector.workers=1``) or ``MultiSyncCollector`` (K workers, each
    running ``trainer.num_envs / K`` envs) over ``factory(num_envs, seed)``, without a frame limit:
    the scaffold decides when to stop. ``collector.backend=ray``: TorchRL's ``RayCollector`` with K
    remote collectors (:mod:`escort_rl.trainers.ray_collection`)."""
    if cfg.collector.get("backend", "local") == "ray":
        from escort_rl.trainers.ray_collection import make_ray_collector

        return make_ray_collector(cfg, factory, policy, frames_per_batch, reset_at_each_iter)
    workers = int(cfg.collector.workers)
    common = dict(frames_per_batch=frames_per_batch, total_frames=-1, reset_at_each_iter=reset_at_each_iter,
                  device=cfg.device, auto_register_policy_transforms=False)
    if workers == 1:
        return Collector(factory(int(cfg.trainer.num_envs), int(cfg.seed)), policy, **common)
    per_worker = int(cfg.trainer.num_envs) // workers
    factories = [factory(per_worker, int(cfg.seed) + 7919 * k) for k in range(workers)]
    return MultiSyncCollector(factories, policy, cat_results="stack", **common)


def training_plan(beliefs: list[str]) -> list[tuple[int, int, str]]:
    """The stages of a run from the belief of each of its iterations (``Algorithm.belief_at``):
    ``(first, last, belief)`` with 1-based iterations, one tuple per run of equal beliefs.

    Examples:
        >>> training_plan(["sir_rough"] * 3 + ["escort_train"] * 2)
        [(1, 3, 'sir_rough'), (4, 5, 'escort_train')]
    """
    stages: list[tuple[int, int, str]] = []
    for i, belief in enumerate(beliefs, start=1):
        if stages and stages[-1][2] == belief:
            stages[-1] = (stages[-1][0], i, belief)
        else:
            stages.append((i, i, belief))
    return stages


def describe_plan(stages: list[tuple[int, int, str]]) -> str:
    """``"iterations 1–30 on sir_rough, 31–33 on escort_train"``: a :func:`training_plan` in words.

    Examples:
        >>> describe_plan([(1, 30, "sir_rough"), (31, 33, "escort_train")])
        'iterations 1–30 on sir_rough, 31–33 on escort_train'
        >>> describe_plan([(1, 1, "sir")])
        'iteration 1 on sir'
    """
    parts = [f"{a}–{b} on {name}" if b > a else f"{a} on {name}" for a, b, name in stages]
    single = len(stages) == 1 and stages[0][0] == stages[0][1]
    return ("iteration " if single else "iterations ") + ", ".join(parts)


def frames_by_belief(history: list[dict], plan: list[tuple[int, int, str]] | None = None) -> dict[str, int]:
    """The frames each belief was trained on, from a run's history (each record's cumulative
    ``frames`` and its ``filter``); a record without ``filter`` (a run saved before the history named
    it) takes the belief of ``plan``'s stage holding its iteration (``"unknown"`` without one).

    Examples:
        >>> frames_by_belief([{"iteration": 1, "frames": 10, "filter": "sir"},
        ...                   {"iteration": 2, "frames": 30, "filter": "escort_train"}])
        {'sir': 10, 'escort_train': 20}
    """
    out: dict[str, int] = {}
    previous = 0
    for record in history:
        belief = record.get("filter")
        if belief is None:
            it = int(record["iteration"])
            belief = next((name for a, b, name in plan or () if a <= it <= b), "unknown")
        frames = int(record["frames"])
        out[belief] = out.get(belief, 0) + frames - previous
        previous = frames
    return out


def collection_config(cfg: DictConfig, filter_name: str, exploring_starts: bool) -> DictConfig:
    """The config of the envs that collect on ``filter_name``'s beliefs (a ``configs/filter/`` name).

    - ``exploring_starts`` (``trainer.exploring_starts``) applies the env group's ``exploring_starts``
      (model keys, e.g. Light-Dark's ``{start_low: 0.0, start_high: 10.0}``) to the training envs only:
      a start distribution wider than the evaluation's, so that training visits the states near and
      past the goal from the first iteration (the evaluation keeps the env group's own start
      distribution).
    - A ``filter_name`` other than the run's ``filter.name`` (the warm start's,
      ``trainer.warm_start_filter``) replaces the filter group: policies over particles move between
      filters.
    """
    starts = cfg.env.exploring_starts if exploring_starts else None
    other_filter = str(filter_name) != str(cfg.filter.name)
    if not other_filter and not starts:
        return cfg
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    OmegaConf.set_struct(out, False)
    if starts:
        out.env.model = OmegaConf.merge(out.env.model, starts)
    if other_filter:
        from escort_rl.config import compose

        out.filter = compose([f"filter={filter_name}"]).filter
    return out


class StagedCollector:
    """The collector of the current stage (the warm start's filter, or the run's) of a run:
    :meth:`for_iteration` builds it on first use through ``build(cfg)`` with the stage's
    :func:`collection_config` and shuts the previous stage's down. ``filter_at(index)``: the filter
    iteration ``index`` collects on; ``exploring_starts``: ``trainer.exploring_starts``."""

    def __init__(self, cfg: DictConfig, build, filter_at, exploring_starts: bool = False) -> None:
        self.cfg, self.build, self.filter_at, self.exploring_starts = cfg, build, filter_at, bool(exploring_starts)
        self.collector, self.iterator, self.stage = None, None, None

    def for_iteration(self, index: int):
        stage = self.filter_at(index)
        if stage != self.stage:
            self.close()
            self.collector = self.build(collection_config(self.cfg, stage, self.exploring_starts))
            self.stage, self.iterator = stage, iter(self.collector)
        return self.collector

    def next(self):
        return next(self.iterator)

    def update_policy_weights(self, poll_s: float = 0.05) -> None:
        """Send the policy's new weights to the collector's worker processes.

        TorchRL waits for every worker's acknowledgement without a timeout, so a worker that died
        before or during the send would hang the run. With worker processes, the send runs in a
        helper thread while this one watches the workers: a dead worker raises ``RuntimeError``,
        which the scaffold turns into :class:`CollectorWorkerDied` naming the worker (the helper
        thread, blocked on the dead worker's acknowledgement, is a daemon and ends with the process)."""
        collector = self.collector
        if not getattr(collector, "procs", None):
            collector.update_policy_weights_()
            return
        if dead_workers(collector):
            raise RuntimeError("collector: a worker process has ended")
        done, failed = threading.Event(), []

        def send() -> None:
            try:
                collector.update_policy_weights_()
            except BaseException as err:  # noqa: BLE001 - raised again in the calling thread
                failed.append(err)
            finally:
                done.set()

        threading.Thread(target=send, name="policy-weights", daemon=True).start()
        while not done.wait(poll_s):
            if dead_workers(collector):
                raise RuntimeError("collector: a worker process has ended")
        if failed:
            raise failed[0]

    def close(self) -> None:
        if self.collector is not None:
            self.collector.shutdown()
            self.collector = None


class CollectorAlgorithm(Algorithm):
    """The base of an algorithm that collects through a :class:`StagedCollector` (PPO, recurrent
    PPO, REINFORCE; their ``Params`` are :class:`~escort_rl.trainers.params.BeliefTrainerParams`):
    ``collectors`` is built from ``build_collector(cfg) -> collector`` (called on first use for each
    stage, with the stage's config: :func:`collection_config`), and
    :meth:`close` shuts the current collector down. Building it draws nothing from torch's
    generator, so a subclass may build it before or after its networks."""

    @classmethod
    def trained_policy(cls, cfg: DictConfig, checkpoint):
        """The trained policy of ``checkpoint``, the env maker it runs in, and a function ``rollout ->
        belief_mean [E, T, d]`` (``None``: the rollout's particles give the belief mean). Here: the
        DeepSets policy, in the env with ``cfg``'s belief filter (and the run's action repeat)."""
        from functools import partial

        from escort_rl.trainers.builders import build_model, build_policy, make_env, trained_action_repeat
        from escort_rl.trainers.checkpointing import load_checkpoint

        actor, policy = build_policy(cfg, build_model(cfg.env, cfg.device))
        load_checkpoint(checkpoint, actor=actor)
        actor.eval()
        return policy, partial(make_env, action_repeat=trained_action_repeat(cfg)), lambda rollout: None

    def __init__(self, cfg: DictConfig, model, build_collector) -> None:
        super().__init__(cfg, model)
        run_filter = str(cfg.filter.name)
        self.collectors = StagedCollector(cfg, build_collector, lambda i: self.params.filter_at(i, run_filter),
                                          self.params.exploring_starts)

    def close(self) -> None:
        self.collectors.close()


def episode_stats(batch: TensorDictBase, model) -> dict:
    """Mean return, final distance to goal and success rate (NaN for a model without a goal,
    :func:`~escort_rl.models.has_goal`) of the episodes that end in ``batch`` ``[E, T]`` (episode
    returns by one ``index_add`` over episode ids; an episode that started before the batch counts
    only its steps inside it)."""
    done = batch["next", "done"].squeeze(-1)
    reward = batch["next", "reward"].squeeze(-1)
    e, t = done.shape
    episode_in_row = torch.cumsum(done.long(), dim=1) - done.long()  # [E, T]
    episode_id = torch.arange(e, device=done.device).unsqueeze(1) * t + episode_in_row
    returns = torch.zeros(e * t, dtype=reward.dtype, device=reward.device).index_add_(
        0, episode_id.flatten(), reward.flatten())
    rows, steps = done.nonzero(as_tuple=True)  # the last step of every finished episode
    if rows.numel() == 0:
        return {"episode_return": float("nan"), "final_distance": float("nan"), "success_rate": float("nan"),
                "episodes": 0}
    goal = has_goal(model)  # without a goal, distance and success are NaN: the return says it all
    final_state = batch["next", "true_state"][rows, steps] if goal else None
    distance = model.distance_to_goal(final_state) if goal else torch.full((rows.numel(),), float("nan"))
    success = batch["next", "terminated"].squeeze(-1)[rows, steps].float().mean() if goal else float("nan")
    return {
        "episode_return": float(returns[episode_id[rows, steps]].mean()),
        "final_distance": float(distance.mean()),
        "success_rate": float(success),
        "episodes": int(rows.numel()),
    }


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) during an iteration; its message is the one line a run ends with: the iteration
    and how to resume from the last checkpoint (:func:`interrupt_message`)."""


def caused_by_interrupt(err: BaseException) -> bool:
    """Whether ``err`` is a ``KeyboardInterrupt`` or was raised while handling one (a module that wraps
    the interrupt in its own error, as ``TensorDictModule`` does)."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def interrupt_message(iteration: int, last_checkpoint: Path | None, run_dir: Path) -> str:
    """``interrupted at iteration k; resume with: escort-rl train resume=<dir>`` (or that no checkpoint
    was written yet)."""
    if last_checkpoint is None:
        return f"interrupted at iteration {iteration}, before the first checkpoint; start the run again"
    return f"interrupted at iteration {iteration}; resume with: escort-rl train resume={run_dir}"


class CollectorWorkerDied(RuntimeError):
    """A worker process of a multi-process collector ended during training (one line naming the
    worker and the last checkpoint to resume from)."""


def dead_workers(collector) -> list[tuple[int, int, int]]:
    """``(index, pid, exit code)`` of each worker process of ``collector`` that has ended, the ones
    not stopped by TorchRL itself (SIGTERM) first; empty for a single-process collector."""
    found = []
    for index, proc in enumerate(getattr(collector, "procs", None) or []):
        try:
            pid, code = proc.pid, proc.exitcode
        except ValueError:  # closed: TorchRL stopped and closed this survivor after another worker died
            continue
        if code is not None:
            found.append((index, pid, code))
    return sorted(found, key=lambda w: w[2] == -signal.SIGTERM)


def exit_description(code: int) -> str:
    """``killed by SIGKILL`` for a negative exit code (the signal), else ``exited with code N``."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


def worker_death_message(worker: int, pid: int, code: int, iteration: int, last_checkpoint: Path | None,
                         run_dir: Path) -> str:
    """The one line a run ends with when collector worker ``worker`` died during ``iteration``
    (1-based): which worker, how it ended, and the checkpoint to resume from."""
    if last_checkpoint is None:
        where = "no checkpoint was written yet; start the run again"
    else:
        where = f"the last checkpoint is '{last_checkpoint}'; resume with `escort-rl train resume={run_dir}`"
    return f"collector: worker {worker} (pid {pid}) {exit_description(code)} during iteration {iteration}; {where}"


def raise_if_worker_died(algorithm: Algorithm, iteration: int, last_checkpoint: Path | None, run_dir: Path,
                         wait_s: float = 2.0) -> None:
    """Raise :class:`CollectorWorkerDied` when a worker of ``algorithm``'s current collector (a
    :class:`StagedCollector` named ``collectors``) has ended; called when an iteration fails.

    A killed worker's pipe closes a moment before its exit status can be read, so the iteration can
    fail (``EOFError`` on the pipe) while every worker still looks alive: with worker processes, this
    polls for up to ``wait_s`` seconds before concluding that none died (the failure path only)."""
    staged = getattr(algorithm, "collectors", None)
    collector = getattr(staged, "collector", None)
    deadline = time.monotonic() + wait_s
    while True:
        died = dead_workers(collector)
        if died:
            raise CollectorWorkerDied(worker_death_message(*died[0], iteration, last_checkpoint, run_dir))
        if not getattr(collector, "procs", None) or time.monotonic() >= deadline:
            return
        time.sleep(0.02)


def make_run_dir(run_dir: Path) -> None:
    """Create ``run_dir`` (and its parents); a folder that cannot be created raises ``ConfigError``
    naming ``output_dir``."""
    from escort_rl.config import ConfigError

    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"output_dir: cannot create '{run_dir}' ({err.strerror or type(err).__name__}); pass a "
                          "folder you can write to") from None


def run_training(cfg: DictConfig, algorithm: Algorithm, resume_state: dict | None = None, progress: bool = True,
                 desc: str = "train", watch: tuple[str, ...] = ("episode_return", "final_distance",
                                                                 "success_rate")) -> Path:
    """Drive ``algorithm`` for ``cfg.trainer.iterations`` iterations; returns the run directory.

    Writes ``config.yaml``, ``checkpoints/`` (every ``trainer.checkpoint_every`` iterations and after
    the last, keeping ``trainer.keep_checkpoints``), TorchRL logger output under ``logs/`` and
    ``history.json`` into the run directory: ``cfg.output_dir`` for a new run.

    ``resume_state`` (``{"path": checkpoint or run directory}``) restores the components and the
    trainer state and continues where that checkpoint stopped (a run directory falls back past a
    damaged newest checkpoint, with a warning). A resume writes into the run directory that holds
    the checkpoint, which ``cfg.output_dir`` must name (``ConfigError`` otherwise). At the start,
    the temporary folders of a checkpoint write interrupted by a kill are removed, and the logs are
    cut back to the iteration the run starts from, so that each iteration is logged once.

    A collector worker process that dies ends the run with :class:`CollectorWorkerDied`, one line
    naming the worker and the last checkpoint.
    """
    if not isinstance(algorithm, Algorithm):
        raise TypeError(f"run_training: {type(algorithm).__name__} is not an escort_rl.trainers.algorithm.Algorithm; "
                        "derive it from Algorithm (or CollectorAlgorithm) and give it components, iteration and close")
    components = algorithm.components
    state, run_dir, last_checkpoint = restore(cfg, components, resume_state)
    make_run_dir(run_dir)
    remove_interrupted_writes(checkpoint_dir(run_dir))
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    torch.manual_seed(int(cfg.seed))
    n_iter = int(cfg.trainer.iterations)
    if state["iteration"] >= n_iter:
        print(f"{desc}: the run in {run_dir} has finished its {n_iter} iterations; nothing to train (raise "
              "trainer.iterations to train it further)", flush=True)
        return run_dir
    plan = describe_plan(training_plan([algorithm.belief_at(i) for i in range(n_iter)])) + algorithm.plan_note()
    start = f"resuming at iteration {state['iteration'] + 1} of {n_iter}; " if state["iteration"] else ""
    print(f"{desc}: {start}{plan}", flush=True)
    rotation = CheckpointRotation(checkpoint_dir(run_dir), keep_last=int(cfg.trainer.keep_checkpoints))
    config_dict = OmegaConf.to_container(cfg, resolve=True)
    every = int(cfg.trainer.checkpoint_every)
    logger = make_logger(cfg, run_dir, state["iteration"])
    bar = tqdm(total=n_iter, initial=state["iteration"], desc=desc, disable=not progress, dynamic_ncols=True)
    try:
        for it in range(state["iteration"], n_iter):
            try:  # an interrupt anywhere in the iteration, its checkpoint's write included, is caught below
                seed = iteration_seed(cfg.seed, it)
                torch.manual_seed(seed)
                t0 = time.perf_counter()
                stats = algorithm.iteration(it, seed)
                seconds = time.perf_counter() - t0
                state["iteration"] = it + 1
                state["frames"] += int(stats.pop("frames"))
                state["seconds"] += seconds
                record = {"iteration": it + 1, "filter": algorithm.belief_at(it), "frames": state["frames"], **stats,
                          "fps": stats.get("fps", float("nan")), "seconds": seconds,
                          "wall_seconds": state["seconds"]}
                bad = [k for k, v in record.items()
                       if isinstance(v, float) and k.startswith("loss") and not math.isfinite(v)]
                if bad:
                    raise FloatingPointError(f"training: non-finite {', '.join(bad)} at iteration {it + 1}; lower "
                                             "trainer.lr or check the model's rewards (last checkpoint kept)")
                bar.set_postfix({k: f"{record[k]:.2f}" for k in watch if k in record})
                bar.update(1)
                state["history"].append(record)
                for key, value in record.items():
                    if key != "iteration" and isinstance(value, (int, float)):  # the filter's name is history only
                        logger.log_scalar(key, value, step=it + 1)
                if (it + 1) % every == 0 or it + 1 == n_iter:
                    last_checkpoint = save_checkpoint(rotation, it + 1, state, config_dict, **components)
            except BaseException as err:
                if caused_by_interrupt(err):
                    raise TrainingInterrupted(interrupt_message(it + 1, last_checkpoint, run_dir)) from None
                if isinstance(err, Exception):
                    raise_if_worker_died(algorithm, it + 1, last_checkpoint, run_dir)
                raise
    finally:
        bar.close()
        algorithm.close()
    (run_dir / "history.json").write_text(json.dumps(state["history"], indent=1))
    return run_dir
