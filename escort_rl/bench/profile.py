"""Where a belief update's time goes inside a training rollout: ``escort-rl bench profile``.

The rollout is the training's own: :func:`~escort_rl.trainers.builders.make_env` (the POMDP env with
the belief transform; ``filter=escort_train`` and Light-Dark 10D unless overridden) with ``B`` envs,
stepped by TorchRL's ``env.rollout`` with the DeepSets policy sampling actions. After ``warmup`` steps
(the compile), two timed rollouts of ``steps`` steps each:

1. **Timed, not profiled.** The env step's wall-clock, and the filter's parts
   (:meth:`~escort_rl.belief.base.BeliefFilter.timed_parts`, listed in :mod:`escort_rl.belief.timing`):
   ``predict`` (transition, prior, likelihood weights), ``bandwidth`` (the kernel's median heuristic),
   ``projections`` (the correlation projections), ``temporal_reference``, ``iterations`` (the K
   compiled iterations: the kernel, the scores, ``F_corr`` and ``F_temp`` fused), ``checks``
   (validation, the finiteness guard and its host sync), ``jitter``, and what lies between them.
2. **Under ``torch.profiler``**, whose events group by those parts (``filter::<part>`` scopes). Each
   update's time is then split by what ran:

   - ``matmul``: the batched matmuls (``aten::bmm``, ``aten::baddbmm``, ``aten::mm``, ...);
   - ``fused kernels``: the compiled graphs' generated kernels (inductor's ``cpp_fused_*``, timed
     apart by ``torch._inductor.config.cpp.enable_kernel_profile``);
   - ``sort and select``: ``aten::sort``, ``aten::kthvalue``, ``aten::topk``, ``aten::argsort``;
   - ``linear algebra``: QR, ``eigh``, Cholesky and the triangular solves;
   - ``other ops``: every other aten op;
   - ``guards``: torch.compile's guard checks before each compiled call (``TorchDynamo Cache Lookup``);
   - ``Python``: the update's wall-clock less all of the above (the interpreter, argument handling,
     the compiled graphs' wrappers).

   and it counts the host synchronisations (``aten::_local_scalar_dense``: ``.item()``, ``bool()`` of
   a tensor) and the graphs compiled during the profiled steps (0 when every graph is reused; run
   with ``TORCH_LOGS=recompiles`` to see why one was not).

Beside the time stands the update's arithmetic bound: its counted matmul flops
(:func:`~escort_rl.bench.cost.update_flops`) at the machine's float32 matmul rate measured in the same
run (:func:`~escort_rl.bench.cost.matmul_gflops`), and the ratio of the two.
"""

from __future__ import annotations

import time
from collections import defaultdict

import torch
from omegaconf import DictConfig

from escort_rl.bench.core import options

MATMUL_OPS = {"aten::bmm", "aten::baddbmm", "aten::mm", "aten::addmm", "aten::matmul", "aten::linear"}
SORT_OPS = {"aten::sort", "aten::kthvalue", "aten::topk", "aten::argsort", "aten::median"}
LINALG_OPS = {"aten::linalg_qr", "aten::_linalg_eigh", "aten::linalg_eigh", "aten::linalg_cholesky_ex",
              "aten::cholesky_inverse", "aten::linalg_solve_triangular", "aten::_linalg_check_errors"}
SYNC_OP = "aten::_local_scalar_dense"
GUARD_EVENT = "TorchDynamo Cache Lookup"
CATEGORIES = ("matmul", "fused kernels", "sort and select", "linear algebra", "other ops", "guards", "Python")


def op_category(name: str) -> str | None:
    """The category of a profiler event's ``name`` (``None``: a scope, whose time belongs to what it
    holds). Ops that contain other ops (``aten::matmul`` calling ``aten::bmm``) count by their self
    time, so nothing counts twice."""
    if name in MATMUL_OPS:
        return "matmul"
    if name in SORT_OPS:
        return "sort and select"
    if name in LINALG_OPS or name.startswith("aten::linalg_"):
        return "linear algebra"
    if "cpp_fused" in name:
        return "fused kernels"
    if name == GUARD_EVENT:
        return "guards"
    if name.startswith("aten::"):
        return "other ops"
    return None


def split_update_events(update_events) -> dict:
    """Split profiler events (``FunctionEvent`` trees, one per update scope) into :data:`CATEGORIES`
    and into the filter's parts (``filter::<part>`` scopes; ``between parts`` for the time outside
    them), in microseconds summed over the updates, and count the host synchronisations of each part."""
    categories: dict[str, float] = defaultdict(float)
    parts: dict[str, float] = defaultdict(float)
    syncs: dict[str, int] = defaultdict(int)
    wall = 0.0
    for root in update_events:
        wall += root.cpu_time_total
        stack = [(e, "between parts") for e in root.cpu_children]
        while stack:
            e, part = stack.pop()
            if e.name.startswith("filter::"):
                part = e.name.removeprefix("filter::")
                if not any(a.name.startswith("filter::") and a is not root for a in _ancestors(e, root)):
                    parts[part] += e.cpu_time_total
            stack.extend((c, part) for c in e.cpu_children)
            if e.name == SYNC_OP:
                syncs[part] += 1
            category = op_category(e.name)
            if category is not None:
                categories[category] += e.self_cpu_time_total
    categories["Python"] = max(wall - sum(categories.values()), 0.0)
    parts["between parts"] = max(wall - sum(parts.values()), 0.0)
    return {"wall_us": wall, "categories_us": {c: categories.get(c, 0.0) for c in CATEGORIES},
            "parts_us": dict(parts), "host_syncs": dict(syncs)}


def _ancestors(event, root):
    e = event.cpu_parent
    while e is not None and e is not root:
        yield e
        e = e.cpu_parent


def _rollout(env, policy, steps: int):
    with torch.no_grad():
        return env.rollout(steps, policy, break_when_any_done=False, auto_reset=False,
                           tensordict=env.reset())


def profile_rollout(cfg: DictConfig, num_envs: int, steps: int, warmup: int) -> dict:
    """Profile ``steps`` env steps of ``num_envs`` envs (after ``warmup`` steps) as this module says;
    returns the timed parts, the profiled split, the bound and the counts."""
    import torch._dynamo.utils as dynamo_utils
    import torch._inductor.config as inductor_config

    from escort_rl.bench.cost import arithmetic_bound_seconds, matmul_gflops, update_flops
    from escort_rl.trainers.builders import build_model, build_policy, make_env

    inductor_config.cpp.enable_kernel_profile = True  # the fused kernels as events of their own
    env = make_env(cfg, num_envs, seed=int(cfg.seed))
    belief = env.transform  # make_env's BeliefTransform (no action repeat here)
    filt = belief.filter
    _, policy = build_policy(cfg, build_model(cfg.env, cfg.device))
    policy = policy.to(cfg.device)
    _rollout(env, policy, warmup)  # compiles
    t0 = time.perf_counter()
    with filt.timed_parts() as parts:
        _rollout(env, policy, steps)
    step_seconds = (time.perf_counter() - t0) / steps
    frames_compiled = sum(dynamo_utils.counters["frames"].values())
    activities = [torch.profiler.ProfilerActivity.CPU]
    if torch.device(cfg.device).type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as prof:
        _rollout(env, policy, steps)
    compiled_during = sum(dynamo_utils.counters["frames"].values()) - frames_compiled
    update_scope = f"filter::{type(filt).__name__}.update"
    roots = [e for e in prof.events() if e.name == update_scope]
    split = split_update_events(roots)
    params = getattr(filt, "params", None)
    d, n = int(belief.model.state_dim), int(cfg.num_particles)
    machine = matmul_gflops(device=str(cfg.device))
    flops = bound = None
    if params is not None and hasattr(params, "num_steps"):
        flops = update_flops(n, d, params.num_steps, num_envs, corr=getattr(params, "lambda_corr", 0) > 0,
                             prior=params.prior in ("smoothed", "shrunk"))
        bound = arithmetic_bound_seconds(flops, machine)
    update_seconds = sum(parts.values()) / steps
    env.close()
    return {
        "filter": str(cfg.filter.name), "env": str(cfg.env.name), "device": str(cfg.device),
        "B": num_envs, "N": n, "d": d,
        "steps": steps, "torch_threads": torch.get_num_threads(), "matmul_gflops": machine,
        "step_seconds": step_seconds, "update_seconds": update_seconds,
        "parts_seconds": {k: v / steps for k, v in sorted(parts.items(), key=lambda kv: -kv[1])},
        "profiled_update_seconds": split["wall_us"] / 1e6 / max(len(roots), 1),
        "profiled_categories_seconds": {k: v / 1e6 / max(len(roots), 1) for k, v in split["categories_us"].items()},
        "profiled_parts_seconds": {k: v / 1e6 / max(len(roots), 1)
                                   for k, v in sorted(split["parts_us"].items(), key=lambda kv: -kv[1])},
        "host_syncs_per_update": sum(split["host_syncs"].values()) / max(len(roots), 1),
        "host_syncs_by_part": {k: v / max(len(roots), 1) for k, v in split["host_syncs"].items()},
        "graphs_compiled_while_profiling": compiled_during,
        "update_gflop": None if flops is None else flops / 1e9,
        "bound_seconds": bound,
    }


def profile_markdown(r: dict) -> str:
    ms = lambda s: f"{1e3 * s:.2f}"  # noqa: E731
    lines = [
        "# Where a belief update's time goes, inside a training rollout",
        "",
        f"`filter={r['filter']}` on `env={r['env']}`: B = {r['B']} envs, N = {r['N']} particles, d = {r['d']}, "
        f"the DeepSets policy sampling actions; {r['steps']} env steps timed after the compile, on "
        f"{r.get('device', 'cpu')}, {r['torch_threads']} torch threads. Machine float32 matmul: "
        f"{r['matmul_gflops']:.1f} GFLOP/s." + (" On a GPU the parts are timed with the device synchronised at "
        "their ends, and the profiled split below is the host's time (launches and Python), not the device's."
        if r.get("device", "cpu").startswith("cuda") else ""),
        "",
        f"- env step: {ms(r['step_seconds'])} ms ({r['B'] / r['step_seconds']:.0f} frames/s), of which the "
        f"belief update {ms(r['update_seconds'])} ms ({100 * r['update_seconds'] / r['step_seconds']:.0f}%).",
    ]
    if r["bound_seconds"] is not None:
        lines.append(f"- the update's arithmetic bound: {r['update_gflop']:.3f} GFLOP of matmul at the machine's rate "
                     f"= {ms(r['bound_seconds'])} ms; the update takes {r['update_seconds'] / r['bound_seconds']:.1f}× "
                     "its bound.")
    where = ", ".join(f"{k} {v:g}" for k, v in sorted(r["host_syncs_by_part"].items(), key=lambda kv: -kv[1]))
    lines += [
        f"- host synchronisations per update: {r['host_syncs_per_update']:g} ({where or 'none'}); graphs compiled "
        f"during the profiled steps: {r['graphs_compiled_while_profiling']}.",
        "",
        "## The update's parts (timed, not profiled)",
        "",
        "| part | ms per update | share |",
        "| --- | --- | --- |",
    ]
    for name, sec in r["parts_seconds"].items():
        lines.append(f"| {name} | {ms(sec)} | {100 * sec / r['update_seconds']:.0f}% |")
    lines += [
        "",
        "## What ran (under torch.profiler, which slows the update; shares of its profiled time)",
        "",
        f"Profiled update: {ms(r['profiled_update_seconds'])} ms.",
        "",
        "| what | ms per update | share |",
        "| --- | --- | --- |",
    ]
    total = r["profiled_update_seconds"] or 1.0
    for name, sec in r["profiled_categories_seconds"].items():
        lines.append(f"| {name} | {ms(sec)} | {100 * sec / total:.0f}% |")
    lines += ["", "By part, profiled (`between parts`: the update's own Python outside its parts):", "",
              "| part | ms per update | share |", "| --- | --- | --- |"]
    for name, sec in r["profiled_parts_seconds"].items():
        lines.append(f"| {name} | {ms(sec)} | {100 * sec / total:.0f}% |")
    return "\n".join(lines) + "\n"


QUICK = dict(num_envs=4, steps=3, warmup=2)


def register(subparsers) -> None:
    """Add ``bench profile`` to the ``bench`` subparsers."""
    prof = subparsers.add_parser("profile", help="where a belief update's time goes, inside a training rollout",
                                 description="Profiles the belief updates of a training rollout "
                                 "(filter=escort_train on Light-Dark 10D unless overridden; DeepSets policy) with "
                                 "torch.profiler: the "
                                 "filter's parts, matmuls against fused kernels, sorts, guards, host syncs, "
                                 "recompiles and Python overhead, beside the update's arithmetic bound.")
    options.add_overrides_argument(prof, "Hydra overrides of the training config, e.g. filter=svgd num_particles=200")
    prof.add_argument("--num-envs", type=int, default=None, metavar="B", help="envs stepped together (default: 64)")
    prof.add_argument("--steps", type=int, default=None, help="env steps timed, and again profiled (default: 20)")
    prof.add_argument("--warmup", type=int, default=None, help="env steps before timing (default: 3)")
    options.add_quick_option(prof, "4 envs, 3 steps after 2")
    options.add_threads_option(prof)
    options.add_output_option(prof, "outputs/bench/profile", "the report (profile.md and profile.json)")
    prof.set_defaults(handler=main)


def main(args) -> None:
    from escort_rl.config import compose
    from escort_rl.reporting.paths import write_results

    full = dict(num_envs=64, steps=20, warmup=3)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else (QUICK if args.quick else full)[k] for k in full}
    for k, v in kw.items():
        if v < 1:
            raise ValueError(f"--{k.replace('_', '-')}: must be at least 1, got {v}")
    options.set_threads(args)
    cfg = compose(args.overrides)
    result = profile_rollout(cfg, **kw)
    write_results(args.output, "profile", result, profile_markdown(result))
