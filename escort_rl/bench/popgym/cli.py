"""``escort-rl bench popgym``: PPO on SIR, EnKF and ESCORT beliefs from the known models of POPGym's
noisy control tasks, beside a GRU (recurrent PPO), DVRL and random, scored by POPGym's MMER."""

from __future__ import annotations

import time
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.bench.core.runner import CellStore, backend_from_args, run_cells
from escort_rl.bench.popgym.spec import COMMON, CONTINUOUS, DEFAULT_OUTPUT, TASKS, POPGymSpec
from escort_rl.reporting.paths import write_results


def register(subparsers) -> None:
    full, quick = POPGymSpec(), POPGymSpec.quick()
    p = subparsers.add_parser(
        "popgym", help="POPGym's noisy CartPole and Pendulum: belief policies beside a GRU, DVRL and random",
        description="Train PPO on SIR, EnKF and ESCORT beliefs (the filters run the verified torch model of the "
        "task), a GRU by recurrent PPO and DVRL (discrete actions: CartPole only) on POPGym's Noisy Stateless "
        "CartPole and Pendulum at its three difficulties, for the same frames per seed; report POPGym's MMER "
        "(mean ± s.e. over seeds) beside a random policy. A killed run "
        "resumes: finished cells are loaded and a training cell continues from its last checkpoint.")
    options.add_overrides_argument(p, "overrides under every row, e.g. num_particles=200")
    p.add_argument("--tasks", nargs="+", default=None, help=f"POPGym task names (default: {' '.join(TASKS)})")
    p.add_argument("--rows", nargs="+", default=None,
                   help="labels of the rows to train (default: all: " + "; ".join(r[0] for r in full.rows) + ")")
    p.add_argument("--frames", type=int, default=None, help=f"env steps per run (default: {full.frames:,})")
    p.add_argument("--popgym-env", action="store_true",
                   help="act in POPGym's own envs (TorchRL's GymEnv) instead of the verified models' simulators; "
                   "DVRL sits out (its readout reads the true state)")
    options.add_seeds_option(p, None, "training seeds 0..N-1 per row and task", str(full.seeds))
    options.add_quick_option(p, f"{quick.seeds} seed of {quick.frames} frames on the two Easy tasks")
    options.add_output_option(p, DEFAULT_OUTPUT, "popgym.md, popgym.json, cells/ and runs/")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)


def spec_from_args(args) -> POPGymSpec:
    base = POPGymSpec.quick() if args.quick else POPGymSpec()
    changes = options.given(args, "seeds", "frames", "threads")
    if args.tasks is not None:
        changes["tasks"] = tuple(args.tasks)
    if args.rows is not None:
        known = dict(base.rows)
        unknown = [r for r in args.rows if r not in known]
        if unknown:
            raise ValueError(f"--rows: unknown row '{unknown[0]}'; choose from {'; '.join(known)}")
        changes["rows"] = tuple((r, known[r]) for r in args.rows)
    overrides = (*base.overrides, *getattr(args, "overrides", ()))
    return base.replace(output=Path(args.output), overrides=overrides,
                        popgym_env=bool(getattr(args, "popgym_env", False)), **changes)


def grid(spec: POPGymSpec) -> tuple[list, list]:
    """The training cells (every row but DVRL on a task with continuous actions) and the random cells."""
    from escort_rl.bench.popgym.cells import POPGymRandomCell, POPGymTrainCell, safe_name, task_overrides
    from escort_rl.models import popgym_model_class
    from escort_rl.models.protocol import is_continuous

    trained, randoms = [], []
    for task in spec.tasks:
        continuous = is_continuous(popgym_model_class(task))
        base = (*task_overrides(task), *COMMON, *spec.overrides)
        trainer = (*task_overrides(task), *COMMON, *(CONTINUOUS if continuous else ()), *spec.overrides)
        own = (f"env.popgym_task={task}",) if spec.popgym_env else ()
        for label, row in spec.rows:
            if "trainer=dvrl_a2c" in row and (continuous or spec.popgym_env):
                continue  # DVRL takes discrete actions, and its readout reads the simulator's true state
            trained += [POPGymTrainCell(task=task, label=label, overrides=(*trainer, *own, *row), seed=seed,
                                        frames=spec.frames,
                                        run_dir=str(spec.output / "runs" / task / f"{safe_name(label)}-seed{seed}"),
                                        threads=spec.threads)
                        for seed in range(spec.seeds)]
        randoms.append(POPGymRandomCell(task=task, overrides=base, episodes=spec.random_episodes))
    return trained, randoms


def main(args) -> None:
    from escort_rl.bench.popgym.report import GRU, markdown_table, summarise, versus_table

    spec = spec_from_args(args)
    trained, randoms = grid(spec)
    t0 = time.perf_counter()
    store = CellStore(spec.output / "cells")
    results = run_cells(trained + randoms, backend_from_args(args), store, desc="popgym cells")
    trained_results, random_results = results[: len(trained)], results[len(trained):]
    rows = summarise(trained_results, random_results)
    markdown = (f"# POPGym's noisy control tasks: {spec.frames:,} frames per run, {spec.seeds} seeds\n\n"
                + markdown_table(rows)
                + "\nMMER: each run's best per-iteration mean episode return (POPGym scales an episode's return "
                "into [-1, 1]), mean ± s.e. over training seeds; random: its episodes' mean ± s.e. The belief "
                "rows' filters run the task's torch model with a small process noise (POPGym's dynamics are "
                "deterministic); the agents act "
                + ("in POPGym's own envs (TorchRL's GymEnv); DVRL sits out (its readout reads the true state).\n"
                   if spec.popgym_env else "in the model without it, which equals POPGym's env step for step "
                   "(tests/models/test_popgym_models.py). DVRL takes discrete actions: CartPole only.\n")
                + (f"On the tasks with continuous actions (Pendulum) every row runs with `{' '.join(CONTINUOUS)}`: "
                   "PPO's importance ratio capped as dual-clip PPO does (docs/DESIGN.md).\n")
                + f"\n## Beside the {GRU}\n\n" + versus_table(rows)
                + "\nEach row's MMER less the GRU's on the same task, with the standard error of the difference "
                "(the rows' seeds are independent runs); in s.e.: that difference over its standard error.\n")
    write_results(spec.output, "popgym", {"spec": {"tasks": list(spec.tasks), "frames": spec.frames,
                                                   "seeds": spec.seeds, "overrides": list(spec.overrides),
                                                   "popgym_env": spec.popgym_env},
                                          "rows": rows, "runs": trained_results}, markdown, time.perf_counter() - t0)
