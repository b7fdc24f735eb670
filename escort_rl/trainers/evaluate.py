"""Evaluate a trained policy beside its baselines on the same seeded episodes: the scripted
controller on the same filter's belief (where the domain has one) and a uniform-random policy."""

from __future__ import annotations

import json
import numbers
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from escort_rl.config import ConfigError, registry
from escort_rl.config.schema import check_output_dir
from escort_rl.models import TaskSpaces, has_goal, position_dims, position_error, velocity_dims
from escort_rl.reporting.metadata import with_metadata
from escort_rl.reporting.paths import display_path
from escort_rl.reporting.plots import plot_belief_projection, plot_learning_curve
from escort_rl.trainers.builders import build_model, make_env, scripted_gain, scripted_policy
from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint
from escort_rl.trainers.resume import run_config
from escort_rl.trainers.training import algorithm
from escort_rl.transforms import action_repeat_of


def first_episode_metrics(rollout: TensorDict, model, belief_mean: torch.Tensor | None = None) -> dict:
    """Per-env metrics of the first episode in a rollout ``[E, T]``.

    Returns tensors: ``final_distance`` ``[E]``, ``success`` ``[E]``, ``episode_return`` ``[E]``,
    ``length`` ``[E]`` (rollout steps: decisions), ``steps`` ``[E]`` (env steps: ``length`` times a
    policy's action repeat, less where the episode ended inside a decision) and ``position_error``
    ``[E, T]`` (NaN after the episode ends), where the position error is ``‖E_b[pos] − pos_true‖₂``
    of the belief after each rollout step. ``belief_mean``
    ``[E, T, d]``: the state estimate after each step when the rollout carries no particles (DVRL's
    readout); default: the weighted mean of ``("next", "particles")``. For a model without a goal
    (:func:`~escort_rl.models.has_goal`) ``final_distance`` and ``success`` are NaN.
    """
    done = rollout["next", "done"].squeeze(-1)  # [E, T]
    e, t = done.shape
    has_done = done.any(1)
    end = torch.where(has_done, done.float().argmax(1), torch.full((e,), t - 1))
    steps = torch.arange(t).expand(e, t)
    inside = steps <= end.unsqueeze(1)
    rewards = rollout["next", "reward"].squeeze(-1)
    true_state = rollout["next"].get("true_state", None)  # None: an env without one (POPGym's own)
    if true_state is None:
        true_state = torch.full((e, t, model.state_dim), float("nan"))
    final_state = true_state[torch.arange(e), end]
    if belief_mean is None:
        belief_w = torch.softmax(rollout["next", "particle_log_weights"], -1).unsqueeze(-1)
        belief_mean = (belief_w * rollout["next", "particles"]).sum(-2)  # [E, T, d]
    pos_err = (position_error(model, belief_mean, true_state) if model.state_dim  # no state: no error (NaN)
               else torch.full((e, t), float("nan")))
    goal = has_goal(model)
    return {
        "final_distance": model.distance_to_goal(final_state) if goal else torch.full((e,), float("nan")),
        "success": (rollout["next", "terminated"].squeeze(-1)[torch.arange(e), end].double() if goal
                    else torch.full((e,), float("nan"), dtype=torch.float64)),
        "episode_return": (rewards * inside).sum(1),
        "length": end + 1,
        # env steps: with an action repeat a decision spans several
        "steps": (rollout["next", "repeats"].squeeze(-1).cumsum(1)[torch.arange(e), end]
                  if ("next", "repeats") in rollout.keys(True) else end + 1),
        "position_error": torch.where(inside, pos_err, torch.full_like(pos_err, float("nan"))),
    }


def summarise_episodes(metrics: dict) -> dict:
    """Mean and standard error over episodes of the :func:`first_episode_metrics` (the final and the
    time-averaged position error, final distance to goal, success, return, length); a metric that
    does not apply (no goal: distance and success) is ``None``."""
    n = metrics["final_distance"].numel()

    def mean_se(x: torch.Tensor) -> tuple[float, float]:
        x = x.double()
        return float(x.mean()), float(x.std() / n**0.5) if n > 1 else 0.0

    def goal_mean_se(x: torch.Tensor) -> tuple[float | None, float | None]:
        # a model without a goal has no distance or success (all NaN): None in JSON
        return (None, None) if x.double().isnan().all() else mean_se(x)

    fd, fd_se = goal_mean_se(metrics["final_distance"])
    ret, ret_se = mean_se(metrics["episode_return"])
    sr, sr_se = goal_mean_se(metrics["success"].double())
    pe = metrics["position_error"]
    pe_final = pe[torch.arange(pe.shape[0]), metrics["length"] - 1]
    pe_m, pe_se = mean_se(pe_final)
    pe_avg, pe_avg_se = mean_se(torch.nanmean(pe, dim=1))  # each episode's average over its steps
    return {"episodes": n, "final_distance": fd, "final_distance_se": fd_se, "success_rate": sr,
            "success_rate_se": sr_se, "episode_return": ret, "episode_return_se": ret_se,
            "final_position_error": pe_m, "final_position_error_se": pe_se,
            "mean_position_error": pe_avg, "mean_position_error_se": pe_avg_se,
            "mean_length": float(metrics.get("steps", metrics["length"]).double().mean())}


def run_episodes(cfg, policy, episodes: int, seed: int, timing: dict | None = None,
                 make=make_env, desc: str | None = None, on_step=None) -> tuple[TensorDict, float]:
    """Roll ``policy`` (or uniform-random actions when ``None``) for one episode in each of
    ``episodes`` envs seeded with ``seed``. Returns the rollout ``[E, T]`` and the seconds per
    batched step (policy + env + belief update) over steps 2..T: the first step is a warm-up (with
    ``filter.compile=true`` it compiles) and its seconds go to ``timing["first_step_seconds"]``.
    ``make(cfg, num_envs, seed)`` builds the env (default: the env with ``cfg``'s belief filter). With
    an :class:`~escort_rl.transforms.ActionRepeat` of ``k`` in the env, ``T = ⌈max_steps / k⌉``
    decisions, and the seconds are per env step (a decision's seconds over ``k``). ``desc``: a progress
    bar of the steps under that name (the first step compiles a compiled filter: seconds). ``on_step(t, td)``
    sees each step's tensordict ``[E]`` as it joins the rollout (``t = 0..T−2``; the last step is not shown):
    it may read it, and the keys it deletes from it are not kept (a bench that needs the particles at a
    few steps only keeps the rollout from holding all ``T × E × N`` of them). With ``on_step`` the steps are
    stacked lazily, so that they may differ in their keys: the last step keeps what the others lost."""
    from tqdm import tqdm

    env = make(cfg, episodes, seed=seed)
    repeat = action_repeat_of(env)
    torch.manual_seed(seed)
    stamps = []
    steps = -(-int(cfg.env.max_steps) // repeat)
    bar = tqdm(total=steps, desc=desc, disable=desc is None, leave=False, dynamic_ncols=True)

    def tick(_env, td) -> None:
        if on_step is not None:
            on_step(len(stamps), td)
        stamps.append(time.perf_counter())
        bar.update(1)

    t0 = time.perf_counter()
    try:
        with torch.no_grad():
            rollout = env.rollout(steps, policy, break_when_any_done=False, callback=tick,
                                  return_contiguous=on_step is None)
    finally:
        bar.close()
    env.close()
    if len(stamps) > 1:
        per_step = (stamps[-1] - stamps[0]) / (len(stamps) - 1)
        first = stamps[0] - t0
    else:
        per_step = first = (time.perf_counter() - t0) / max(rollout.shape[1], 1)
    if timing is not None:
        timing["first_step_seconds"] = first
    return rollout, per_step / repeat


def policy_summary(cfg, model, policy, episodes: int, seed: int, make=make_env,
                   estimates=None, desc: str | None = None) -> tuple[dict, TensorDict, torch.Tensor]:
    """One policy on ``episodes`` seeded episodes (:func:`run_episodes`; ``policy=None``: uniform-random
    actions). Returns its :func:`summarise_episodes` with ``seconds_per_step`` and
    ``first_step_seconds``, the rollout ``[E, T]``, and the position error per step averaged over the
    episodes ``[T]``. ``estimates(rollout)``: the belief means when the rollout carries no particles
    (see :func:`trained_policy`); ``desc``: a progress bar's name (``None``: none)."""
    timing: dict = {}
    rollout, step_s = run_episodes(cfg, policy, episodes, seed, timing, make=make, desc=desc)
    metrics = first_episode_metrics(rollout, model, None if estimates is None else estimates(rollout))
    summary = {**summarise_episodes(metrics), "seconds_per_step": step_s, **timing}
    return summary, rollout, torch.nanmean(metrics["position_error"], 0)


def trained_policy(cfg, checkpoint):
    """The trained policy of a checkpoint of any trainer, the env maker it runs in, and a function
    ``rollout -> belief_mean [E, T, d]`` (``None``: the rollout's particles give the belief mean): the
    trainer class's :meth:`~escort_rl.trainers.algorithm.Algorithm.trained_policy`. A belief trainer's
    is the DeepSets policy in the env with ``cfg``'s belief filter; DVRL's, its policy with its state
    primer and its readout's estimate; recurrent PPO's, its GRU on raw observations."""
    return registry.resolve("trainer", algorithm(cfg)).trained_policy(cfg, checkpoint)


def planned_beliefs(cfg) -> list[str]:
    """What each iteration of ``cfg``'s run collects on (the trainer's ``Algorithm.belief_of``):
    e.g. ``["sir_rough"] * 30 + ["escort_train"] * 3`` for the default job."""
    from escort_rl.config import registry
    from escort_rl.trainers.algorithm import trainer_params

    cls = registry.resolve("trainer", algorithm(cfg))
    params = trainer_params(cls.Params, cfg.trainer) if cls.Params is not None else None
    return [cls.belief_of(cfg, params, i) for i in range(int(cfg.trainer.iterations))]


def training_record(trainer_state: dict, beliefs: list[str]) -> dict:
    """``metrics.json``'s ``"training"``: ``frames_by_filter`` (the frames each belief was trained on,
    from the history; :func:`~escort_rl.trainers.scaffold.frames_by_belief`) and ``wall_s`` (the
    training's seconds)."""
    from escort_rl.trainers.scaffold import frames_by_belief, training_plan

    return {"frames_by_filter": frames_by_belief(trainer_state.get("history", []), training_plan(beliefs)),
            "wall_s": float(trainer_state.get("seconds", float("nan")))}


def evaluate(checkpoint: str | Path, episodes: int | None = None, output: str | Path | None = None,
             greedy: bool | None = None, progress: bool = False) -> dict:
    """Evaluate the checkpointed policy, the scripted controller on the same filter's belief (where the
    domain has one) and a uniform-random policy on the same seeded episodes; ``progress``: a progress
    bar per policy (the first step of a compiled filter compiles it).

    Writes ``summary.md``, ``metrics.json``, ``learning_curve.png`` and ``belief_projection.png``
    into ``output`` (default: ``<run>/evaluation``) and returns the metrics.
    """
    if episodes is not None and (isinstance(episodes, bool) or not isinstance(episodes, numbers.Integral)
                                 or episodes < 1):
        raise ConfigError(f"episodes: expected a positive int (or None: the config's evaluate.episodes), got "
                          f"{episodes!r}")
    problem = None if output is None else check_output_dir(str(output))
    if problem is not None:
        raise ConfigError(f"output: {problem}")
    ckpt_path = resolve_checkpoint(checkpoint)
    meta = load_checkpoint(ckpt_path)  # reads config and history without restoring modules
    cfg = run_config(meta)
    model = build_model(cfg.env, cfg.device)
    policy, make, estimates = trained_policy(cfg, ckpt_path)
    episodes = int(episodes if episodes is not None else cfg.evaluate.episodes)
    greedy = bool(cfg.evaluate.greedy if greedy is None else greedy)
    seed = int(cfg.evaluate.seed)
    out = Path(output) if output is not None else ckpt_path.parent.parent / "evaluation"
    out.mkdir(parents=True, exist_ok=True)

    def bar(name: str) -> str | None:
        return f"evaluate {name} ({episodes} episodes)" if progress else None

    mode = ExplorationType.DETERMINISTIC if greedy else ExplorationType.RANDOM
    with set_exploration_type(mode):
        rows = {}
        rows["trained"], trained, trained_error = policy_summary(cfg, model, policy, episodes, seed, make=make,
                                                                 estimates=estimates, desc=bar("trained"))
    model_free = isinstance(model, TaskSpaces)  # env=popgym: no model, no filter, no scripted controller
    scripted = None if model_free else scripted_policy(cfg, model)
    if scripted is not None:
        rows["scripted"] = policy_summary(cfg, model, scripted, episodes, seed, desc=bar("scripted"))[0]
        rows["scripted_gain"] = scripted_gain(cfg)
        rows["scripted_rule"] = getattr(scripted.controller, "rule", None)  # None: the PD rule at scripted_gain
    in_own_env = {"make": make, "estimates": estimates} if model_free else {}
    rows["random"] = policy_summary(cfg, model, None, episodes, seed, **in_own_env, desc=bar("random"))[0]
    beliefs = planned_beliefs(cfg)
    result = {
        "checkpoint": display_path(ckpt_path),
        "env": cfg.env.name,
        "filter": beliefs[-1] if beliefs else str(cfg.filter.name),
        "num_particles": int(cfg.num_particles),
        "episodes": episodes,
        "eval_seed": seed,
        "greedy": greedy,
        "trained_iterations": int(meta["trainer_state"]["iteration"]),
        "trainer": algorithm(cfg),
        "frames": int(meta["trainer_state"].get("frames", 0)),
        "train_seconds": float(meta["trainer_state"].get("seconds", float("nan"))),
        "training": training_record(meta["trainer_state"], beliefs),
        **rows,
    }
    (out / "metrics.json").write_text(json.dumps(with_metadata(result), indent=2))
    history = meta["trainer_state"].get("history", [])
    if history:
        plot_learning_curve(history, out / "learning_curve.png")
    pos = (list(position_dims(model)) + list(velocity_dims(model)) + list(range(model.state_dim)))[:2]
    if "particles" in trained["next"].keys() and "true_state" in trained["next"].keys() and len(set(pos)) == 2:
        # the first episode alone: after it ends the env resets and the next one starts elsewhere
        done = trained["next", "done"][0].reshape(-1)
        length = int(done.float().argmax()) + 1 if bool(done.any()) else done.numel()
        plot_belief_projection(trained["next", "particles"][0, :length][..., pos],
                               trained["next", "true_state"][0, :length, pos], out / "belief_projection.png",
                               position_error=trained_error)
    (out / "summary.md").write_text(_markdown(result))
    return result


def _scripted_rule(r: dict) -> str:
    """What the scripted row ran: ``metrics.json``'s ``scripted_rule``, or the PD rule at ``scripted_gain``."""
    return r.get("scripted_rule") or (f"the domain's PD controller (velocity gain {r['scripted_gain']:g}) on the "
                                      "belief mean of the same filter")


def _training_sentence(training: dict | None) -> str:
    """`` Trained on 256000 frames of sir_rough, 256000 of escort_train (7.1 minutes).``"""
    if not training or not training.get("frames_by_filter"):
        return ""
    parts = [f"{frames} frames of {name}" if i == 0 else f"{frames} of {name}"
             for i, (name, frames) in enumerate(training["frames_by_filter"].items())]
    return f" Trained on {', '.join(parts)} ({training['wall_s'] / 60:.1f} minutes)."


def _markdown(r: dict) -> str:
    rows = []
    returns = [abs(r[name]["episode_return"]) for name in ("trained", "scripted", "random") if name in r]
    digits = 3 if max(returns, default=0.0) < 10 else 1  # POPGym's returns lie in [-1, 1]
    for name in ("trained", "scripted", "random"):
        if name not in r:
            continue
        m = r[name]

        def cell(key: str, digits: int) -> str:
            value = m[key]
            if value is None or value != value:  # not applicable: no goal, or no state to estimate (NaN)
                return "—"
            return f"{value:.{digits}f} ± {m[f'{key}_se']:.{digits}f}"

        rows.append(
            f"| {name} | {cell('final_distance', 3)} | {cell('success_rate', 3)} | {cell('episode_return', digits)} | "
            f"{cell('final_position_error', 3)} | "
            f"{m['mean_length']:.0f} | {1e3 * m['seconds_per_step']:.2f} |"
        )
    return "\n".join([
        f"# Evaluation: {r['env']}, belief filter {r['filter']}"
        + ("" if registry.resolve("trainer", r.get("trainer", "reinforce")).belief_label else
           f" (N={r['num_particles']})"),
        "",
        f"Checkpoint `{r['checkpoint']}` ({r.get('trainer', 'reinforce')}) after {r['trained_iterations']} "
        f"iterations ({r.get('frames', 0)} frames); {r['episodes']} episodes with env seed {r['eval_seed']}, "
        f"the same for every policy; trained policy {'greedy' if r['greedy'] else 'sampled'}. "
        + (f"scripted: {_scripted_rule(r)}. " if "scripted" in r else "")
        + "Mean ± standard error; — where the model has no goal or no state."
        + _training_sentence(r.get("training")),
        "",
        "| policy | final distance to goal | success rate | return | final position error | steps | "
        "ms per step (batch) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        *rows,
        "",
        "Position error: ‖E_b[pos] − pos_true‖₂ of the belief at the episode's last step. ms per step: "
        "policy + env + belief update for the whole batch, over steps 2..T (the first step, which "
        f"compiles with `filter.compile=true`, took {r['trained'].get('first_step_seconds', float('nan')):.2f} s "
        "for the trained policy).",
        "",
    ])
