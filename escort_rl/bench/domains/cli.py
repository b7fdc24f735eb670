"""``escort-rl bench domains``: the options of both protocols, the spec they give
(:func:`spec_from_args`), and what a run writes (``<output>/domains.md|json``, plots and ``cells/``;
protocol b: ``closed_loop.md|json``, plots and ``runs/``)."""

from __future__ import annotations

import time
from pathlib import Path

from escort_rl.bench import methods as registry
from escort_rl.bench.core.options import (
    add_output_option,
    add_overrides_argument,
    add_quick_option,
    add_runner_options,
    add_seeds_option,
    filter_overrides,
)
from escort_rl.bench.domains.spec import DEFAULT_OUTPUT, PROTOCOLS, DomainsSpec

FLAGS = ("domains", "methods", "seeds", "particles", "steps", "threads", "max_particles", "reference_particles",
         "reference_sample", "train_iterations", "train_envs")
"""The options that set the spec's field of the same name when given (else ``--quick``'s or the default)."""


def _quick_help() -> str:
    a, b = DomainsSpec.quick("a"), DomainsSpec.quick("b")
    return (f"all three domains, {' '.join(a.methods)}, {a.seeds} seeds, {a.steps} steps, N={a.particles}, "
            f"{a.threads} torch thread, equal-time grid up to N'={a.max_particles} with {a.calibration_steps} timed "
            f"step, a reference of {a.reference_particles} particles ({a.reference_sample} kept per step); protocol "
            f"b: {b.steps} steps, N={b.particles}, {b.train_iterations} training iteration of {b.train_envs} envs")


def register(subparsers) -> None:
    """Add ``bench domains`` (protocols (a) and (b)) to the ``bench`` subparsers."""
    full = DomainsSpec()
    dom = subparsers.add_parser(
        "domains", help="filters on Light-Dark, Kidnapped Robot, MTT: shared trajectories",
        description="Protocol (a) (paper Table 1 layout): every method filters the same seeded "
        "trajectories (uniform random actions) from the same seeded priors; final and time-averaged position "
        "error (mean ± s.e. over seeds), ms per step, and a table at equal wall-clock per step. Methods are "
        "filter config names. The grid's cells (domain × method × seeds) run on --backend; each is saved in "
        "<output>/cells as it finishes and a rerun skips it.")
    add_overrides_argument(dom, "filter overrides, each set on every method whose config has the key, e.g. "
                           "filter.num_steps=10 filter.compile=true")
    dom.add_argument("--domains", nargs="+", default=None, help=f"env configs (default: {' '.join(full.domains)})")
    dom.add_argument("--methods", nargs="+", default=None, help=registry.methods_help())
    add_seeds_option(dom, None, "seeds 0..N-1 (protocol b: evaluation episodes)", str(full.seeds))
    dom.add_argument("--particles", type=int, default=None, metavar="N",
                     help=f"N for every method (default: {full.particles})")
    dom.add_argument("--steps", type=int, default=None, help="steps per trajectory (default: env.max_steps)")
    add_runner_options(dom, threads_help="torch threads in each cell and in the equal-time measurement; small "
                       f"updates are often fastest with 1 (default: {full.threads})")
    dom.add_argument("--max-particles", type=int, default=None,
                     help="largest N' for the equal wall-clock table; the timing stops at the first N' over the "
                     f"budget (default: {full.max_particles})")
    dom.add_argument("--no-equal-time", action="store_true", help="skip the equal wall-clock table")
    dom.add_argument("--reference-particles", type=int, default=None, metavar="N",
                     help="particles of the reference posterior (an SIR filter, run at N and 2N to check it has "
                     f"converged) that every belief is compared with at every step; 0: none (default: "
                     f"{full.reference_particles})")
    dom.add_argument("--reference-sample", type=int, default=None, metavar="M",
                     help="reference particles kept per step for sliced W1 and MMD² (default: "
                     f"{full.reference_sample})")
    add_quick_option(dom, _quick_help())
    dom.add_argument("--protocol", choices=PROTOCOLS, default=full.protocol,
                     help="a: shared trajectories; b: closed loop, each method trains its own DeepSets "
                     "policy (budget per domain in configs/bench/closed_loop.yaml) and drives it on --seeds "
                     "evaluation episodes; a rerun with the same --output resumes from the checkpoints")
    dom.add_argument("--train-iterations", type=int, default=None,
                     help="protocol b: trainer.iterations for every domain (default: the yaml's)")
    dom.add_argument("--train-envs", type=int, default=None,
                     help="protocol b: trainer.num_envs for every domain (default: the yaml's)")
    add_output_option(dom, DEFAULT_OUTPUT, "domains.json, domains.md, PNGs and cells/ (protocol b: "
                      "closed_loop.json, closed_loop.md, PNGs and runs/)")
    dom.set_defaults(handler=main)


def spec_from_args(args) -> DomainsSpec:
    """The run ``args`` ask for: each option of :data:`FLAGS` given explicitly, else ``--quick``'s
    setting, else the default (:meth:`DomainsSpec.quick`, :meth:`DomainsSpec.full`)."""
    explicit = {name: getattr(args, name) for name in FLAGS if getattr(args, name) is not None}
    make = DomainsSpec.quick if args.quick else DomainsSpec.full
    return make(args.protocol, **explicit, equal_time=not args.no_equal_time, seeds_per_cell=args.seeds_per_cell,
                filter_set=filter_overrides(args.overrides), output=Path(args.output))


def show_progress(kind: str, payload) -> None:
    """Protocol (a)'s progress lines: a row, the reference posteriors, an equal-time measurement."""
    from escort_rl.bench.domains.report import parts_cell
    from escort_rl.reporting.stats import format_mean_se

    if kind == "row" and payload["failed"]:
        f = payload["failed"]
        print(f"{payload['domain']:>13} {payload['method']:>14} N={payload['particles']:<5} FAILED at step "
              f"{f['step']}: {f['message']}", flush=True)
    elif kind == "row":
        s = payload["summary"]
        w1 = f"  W1 to ref (pos/vel) {parts_cell(payload, 'w1')}" if payload.get("accuracy") else ""
        print(f"{payload['domain']:>13} {payload['method']:>14} N={payload['particles']:<5} final error "
              f"{format_mean_se(s['final_error'])}  mean error {format_mean_se(s['mean_error'])}  "
              f"{1e3 * payload['seconds_per_step']:.1f} ms/step{w1}", flush=True)
    elif kind == "reference":
        for d, info in payload.items():
            floor = ", ".join(f"{k} {v['mean'][0]:.4g}" for k, v in info["floor"].items() if k.endswith("/w1"))
            n, n2 = (str(p) for p in info["particles"])
            print(f"{d:>13} reference N_ref={n}/{n2}: {info['seconds'][n]:.0f} + {info['seconds'][n2]:.0f} s; "
                  f"floor (sliced W1) {floor}", flush=True)
    else:
        times = ", ".join(f"N'={k}: {1e3 * v:.1f} ms" for k, v in payload["times"].items())
        print(f"{payload['domain']:>13} {payload['method']:>14} equal-time: budget "
              f"{1e3 * payload['budget']:.1f} ms; {times} -> N'={payload['chosen']}", flush=True)


def show_closed_loop_row(row: dict) -> None:
    """Protocol (b)'s progress line of a finished row."""
    from escort_rl.bench.domains.report import train_cell

    if row["failed"]:
        print(f"{row['domain']:>13} {row['method']:>14} FAILED: {row['failed']['message']}", flush=True)
        return
    s = row["summary"]
    trained = f"  trained {train_cell(row)}" if row["train"] else ""
    if "seconds_per_decision" in row:
        trained += f"  {1e3 * row['seconds_per_decision']:.1f} ms per decision"
    print(f"{row['domain']:>13} {row['method']:>14} final error {s['final_position_error']:.3f} ± "
          f"{s['final_position_error_se']:.3f}  return {s['episode_return']:.1f} ± {s['episode_return_se']:.1f}  "
          f"distance {s['final_distance']:.3f}  success {s['success_rate']:.2f}  "
          f"{1e3 * row['seconds_per_step']:.1f} ms/step{trained}", flush=True)


def main(args) -> None:
    """``bench domains``: protocol (a), or protocol (b) with ``--protocol b``."""
    from escort_rl.bench.core.runner import backend_from_args
    from escort_rl.bench.domains.report import closed_loop_markdown, domains_markdown, plot_closed_loop, plot_domains
    from escort_rl.bench.domains.run import run_closed_loop, run_domains
    from escort_rl.reporting.paths import write_results

    spec = spec_from_args(args)
    backend = backend_from_args(args)
    spec.output.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if spec.protocol == "b":
        result = run_closed_loop(spec, backend, progress=show_closed_loop_row)
        plot_closed_loop(result, spec.output)
        write_results(spec.output, "closed_loop", result, closed_loop_markdown(result), time.perf_counter() - t0)
    else:
        result = run_domains(spec, backend, progress=show_progress)
        plot_domains(result, spec.output)
        write_results(spec.output, "domains", result, domains_markdown(result), time.perf_counter() - t0)
