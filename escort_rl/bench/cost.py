"""The cost of one belief update: time against d, N and batch B for ESCORT, SVGD and SIR
in the same run, a breakdown of ESCORT's time, a fitted scaling exponent in d, and achieved
GFLOP/s next to the machine's measured float32 matmul GFLOP/s."""

from __future__ import annotations

import math
import statistics
import time

import torch

from escort_rl.belief import ESCORTFilter, SIRFilter, SVGDFilter
from escort_rl.bench.core import options
from escort_rl.models import LightDark10D, LinearGaussian
from escort_rl.models.protocol import random_action


def matmul_gflops(size: int = 1024, repeats: int = 10, device: str = "cpu") -> float:
    """Measured float32 GFLOP/s of a ``size × size`` matmul (``2 size³`` flops), median of ``repeats``."""
    a = torch.randn(size, size, device=device)
    b = torch.randn(size, size, device=device)
    for _ in range(3):
        a @ b
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        a @ b
        _sync(device)
        times.append(time.perf_counter() - t0)
    return 2 * size**3 / statistics.median(times) / 1e9


def _sync(device) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def update_flops(n: int, d: int, k: int, batch: int, corr: bool, prior: bool = True) -> float:
    """Counted flops of the dense work of one SVGD/ESCORT update, the arithmetic the update cannot do
    without. Per iteration and belief:

    - the kernel: ``6 N² d`` (the pairwise distances ``2 N² d``, ``K·[score, x]`` ``4 N² d``);
    - the smoothed prior's score (``prior``): ``4 N² d + 2 N d²`` (the responsibilities' logits
      ``xP·μᵀ`` and ``r·μP``, each ``2 N² d``; ``x·P``, ``2 N d²``);
    - ``F_corr`` (``corr``): ``2 N d²`` (``(φ − φ̄)·Σ_k w_k A_k A_kᵀ``);

    times ``K`` iterations and ``B`` beliefs. Elementwise work (the exponentials) is not counted.

    Example:
        >>> update_flops(100, 10, 15, 64, corr=True) / 1e9  # escort_train at B = 64: about 1 GFLOP
        0.9984
    """
    per_iter = 6.0 * n * n * d + (4.0 * n * n * d + 2.0 * n * d * d if prior else 0.0) + (
        2.0 * n * d * d if corr else 0.0)
    return batch * k * per_iter


def arithmetic_bound_seconds(flops: float, matmul_gflops: float) -> float:
    """The update's arithmetic lower bound: its counted flops (:func:`update_flops`) at the machine's
    measured matmul rate (:func:`matmul_gflops`), in seconds."""
    return flops / (matmul_gflops * 1e9)


def cost_model(d: int, device: str = "cpu"):
    """Light-Dark 10D at d = 10; otherwise a linear-Gaussian model with ``obs_dim = d/2``."""
    if d == 10:
        return LightDark10D(device=device)
    return LinearGaussian(state_dim=d, obs_dim=max(1, d // 2), device=device)


def time_update(filt, model, batch: int, n: int, repeats: int = 5, warmup: int = 1, device: str = "cpu",
                seed: int = 0) -> dict:
    """Median seconds of one ``filt.update`` on ``batch`` beliefs of ``n`` particles, the seconds of
    each part of one more update (:meth:`~escort_rl.belief.base.BeliefFilter.timed_parts`), and the
    seconds of the first warm-up update (which includes compiling, for ``compile=True``)."""
    g = torch.Generator(device=device).manual_seed(seed)
    belief = filt.init(model, (batch,), n, g)
    s = model.initial_state((batch,), g)
    a = random_action(model, (batch,), g, device)
    o = model.observe(model.transition(s, a, g), a, g)
    runs, first = [], None
    for i in range(warmup + repeats):
        _sync(device)
        t0 = time.perf_counter()
        filt.update(model, belief, a, o, g)
        _sync(device)
        if i >= warmup:
            runs.append(time.perf_counter() - t0)
        elif first is None:
            first = time.perf_counter() - t0
    with filt.timed_parts() as breakdown:  # one more update, its parts timed (which syncs a GPU)
        filt.update(model, belief, a, o, g)
    return {"seconds": statistics.median(runs), "breakdown": breakdown, "first_seconds": first}


def fit_exponent(ds: list[int], seconds: list[float]) -> float:
    """Least-squares slope of log(seconds) against log(d)."""
    x = [math.log(v) for v in ds]
    y = [math.log(v) for v in seconds]
    mx, my = sum(x) / len(x), sum(y) / len(y)
    den = sum((a - mx) ** 2 for a in x)
    return sum((a - mx) * (b - my) for a, b in zip(x, y)) / den if den > 0 else float("nan")


def run_cost_benchmark(dims=(10, 20, 50, 100, 200), particles=(100, 1000), batches=(1, 32), repeats: int = 3,
                       num_steps: int = 50, device: str = "cpu", progress=None, max_pairs: float = float("inf"),
                       compile: bool = False) -> dict:
    """Time ESCORT, SVGD and SIR for every (d, N, B) with ``B·N² ≤ max_pairs``; returns rows, the
    skipped combinations, exponents and machine GFLOP/s. With ``compile``, ESCORT and SVGD are also
    timed with ``compile=True`` (rows ``escort_compiled``, ``svgd_compiled``)."""
    filters = {
        "escort": ESCORTFilter(num_steps=num_steps),
        "svgd": SVGDFilter(num_steps=num_steps),
        "sir": SIRFilter(),
    }
    if compile:
        filters["escort_compiled"] = ESCORTFilter(num_steps=num_steps, compile=True)
        filters["svgd_compiled"] = SVGDFilter(num_steps=num_steps, compile=True)
    machine = matmul_gflops(device=device)
    rows, skipped = [], []
    for d in dims:
        model = cost_model(d, device)
        for n in particles:
            for b in batches:
                if b * n * n > max_pairs:
                    skipped.append({"d": d, "N": n, "B": b})
                    continue
                for name, filt in filters.items():
                    r = time_update(filt, model, b, n, repeats=repeats, device=device)
                    flops = (update_flops(n, d, num_steps, b, corr=name.startswith("escort")) if name != "sir"
                             else float("nan"))
                    row = {"filter": name, "d": d, "N": n, "B": b, "model": type(model).__name__,
                           "seconds": r["seconds"], "first_seconds": r["first_seconds"], "gflop": flops / 1e9,
                           "gflops_per_s": flops / r["seconds"] / 1e9 if name != "sir" else float("nan"),
                           "bound_seconds": arithmetic_bound_seconds(flops, machine),
                           "breakdown": r["breakdown"]}
                    rows.append(row)
                    if progress is not None:
                        progress(row)
    exponents = {}
    for name in filters:
        for n in particles:
            sel = [r for r in rows if r["filter"] == name and r["N"] == n and r["B"] == 1]
            if len(sel) >= 2:
                exponents[f"{name}_N{n}"] = fit_exponent([r["d"] for r in sel], [r["seconds"] for r in sel])
    return {"device": device, "torch_threads": torch.get_num_threads(), "num_steps": num_steps,
            "matmul_gflops": machine, "rows": rows, "skipped": skipped, "max_pairs": max_pairs,
            "exponents": exponents}


def cost_markdown(result: dict) -> str:
    """The update-cost tables and, where measured, the training-throughput rows and compile warm-up
    (:mod:`escort_rl.bench.training_cost`)."""
    parts = [update_cost_markdown(result)] if result.get("rows") else ["# Cost of belief updates", ""]
    if result.get("training") or result.get("warmup"):
        from escort_rl.bench.training_cost import training_cost_markdown

        parts.append(training_cost_markdown(result.get("training", []), result.get("warmup")))
    return "\n".join(parts)


def update_cost_markdown(result: dict) -> str:
    lines = [
        "# Cost of one belief update",
        "",
        f"Device {result['device']}, {result['torch_threads']} torch threads, K = {result['num_steps']} "
        f"iterations for ESCORT and SVGD. Machine float32 matmul: {result['matmul_gflops']:.1f} GFLOP/s; "
        "an update's arithmetic bound is its counted matmul flops at that rate (`update_flops`). "
        "Median of repeated runs after a warm-up. Models: Light-Dark 10D at d = 10, a linear-Gaussian "
        "model with obs_dim = d/2 otherwise.",
        "",
        "| d | N | B | ESCORT ms | SVGD ms | SIR ms | ESCORT/SVGD | ESCORT/SIR | ESCORT GFLOP/s | "
        "ESCORT bound ms | ESCORT × bound | ESCORT's parts (ms) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    rows = result["rows"]
    compiled = any(r["filter"] == "escort_compiled" for r in rows)
    keys = sorted({(r["d"], r["N"], r["B"]) for r in rows})
    for d, n, b in keys:
        by = {r["filter"]: r for r in rows if (r["d"], r["N"], r["B"]) == (d, n, b)}
        e, s, p = by["escort"], by["svgd"], by["sir"]
        lines.append(
            f"| {d} | {n} | {b} | {1e3 * e['seconds']:.1f} | {1e3 * s['seconds']:.1f} | {1e3 * p['seconds']:.2f} | "
            f"{e['seconds'] / s['seconds']:.2f} | {e['seconds'] / p['seconds']:.0f} | {e['gflops_per_s']:.2f} | "
            f"{1e3 * e['bound_seconds']:.2f} | {e['seconds'] / e['bound_seconds']:.0f} | "
            f"{describe_parts(e['breakdown'])} |"
        )
    if compiled:
        lines += ["", "With `compile=True` (each iteration through torch.compile; the first update of a shape "
                  "compiles, and its time is the last column):", "",
                  "| d | N | B | ESCORT ms | SVGD ms | ESCORT/SVGD | speed-up over eager (ESCORT, SVGD) | "
                  "ESCORT GFLOP/s | ESCORT × bound | first update incl. compile (ESCORT, SVGD, s) | "
                  "ESCORT's parts (ms) |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for d, n, b in keys:
            by = {r["filter"]: r for r in rows if (r["d"], r["N"], r["B"]) == (d, n, b)}
            e, s_, ec, sc = by["escort"], by["svgd"], by["escort_compiled"], by["svgd_compiled"]
            lines.append(
                f"| {d} | {n} | {b} | {1e3 * ec['seconds']:.1f} | {1e3 * sc['seconds']:.1f} | "
                f"{ec['seconds'] / sc['seconds']:.2f} | {e['seconds'] / ec['seconds']:.1f}×, "
                f"{s_['seconds'] / sc['seconds']:.1f}× | {ec['gflops_per_s']:.2f} | "
                f"{ec['seconds'] / ec['bound_seconds']:.0f} | {ec['first_seconds']:.1f}, {sc['first_seconds']:.1f} | "
                f"{describe_parts(ec['breakdown'])} |")
    if result.get("skipped"):
        lines += ["", f"Not run (B·N² > {result['max_pairs']:.0e}): "
                  + ", ".join(f"d={r['d']} N={r['N']} B={r['B']}" for r in result["skipped"])]
    lines += ["", "Fitted exponent of time in d (B = 1): "
              + ", ".join(f"{k} {v:.2f}" for k, v in result["exponents"].items()), ""]
    return "\n".join(lines)


def describe_parts(parts: dict[str, float]) -> str:
    """An update's parts (:mod:`escort_rl.belief.timing`), largest first, in ms: ``"iterations 41.2,
    projections 5.9, ..."``."""
    return ", ".join(f"{name} {1e3 * sec:.1f}" for name, sec in sorted(parts.items(), key=lambda kv: -kv[1]))


def register(subparsers) -> None:
    """Add ``bench cost`` to the ``bench`` subparsers."""
    cost = subparsers.add_parser("cost", help="time one belief update: ESCORT vs SVGD vs SIR over d, N, B",
                                 description="Times one update for d, N and B, ESCORT, SVGD and SIR in the same "
                                 "run; reports the ESCORT breakdown, the fitted exponent in d and GFLOP/s. "
                                 "filter.compile=true also times ESCORT and SVGD compiled.")
    options.add_overrides_argument(cost, "filter.compile=true: also time ESCORT and SVGD with compile=True (each shape "
                           "compiles once first)")
    cost.add_argument("--dims", type=int, nargs="+", default=[10, 20, 50, 100, 200], metavar="D",
                      help="state dimensions d")
    cost.add_argument("--particles", type=int, nargs="+", default=[100, 1000], metavar="N", help="particle counts N")
    cost.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 32], metavar="B",
                      help="batch sizes B (beliefs updated together)")
    cost.add_argument("--repeats", type=int, default=3, help="timed repeats of each update (the median is kept)")
    cost.add_argument("--num-steps", type=int, default=50, metavar="K", help="K for ESCORT and SVGD")
    cost.add_argument("--device", default="cpu", help="torch device of the particles")
    options.add_quick_option(cost, "a small grid: d 10 20, N 100, B 1 2")
    cost.add_argument("--max-pairs", type=float, default=1e7,
                      help="skip (d, N, B) with B·N² above this (1e7 skips N=1000 at B=32 on a CPU)")
    cost.add_argument("--training", type=int, nargs="+", default=[], metavar="B",
                      help="also measure PPO training frames/s on SIR, SVGD and ESCORT beliefs at these batch sizes")
    cost.add_argument("--training-overrides", nargs="+", default=[], metavar="OVERRIDE",
                      help="config overrides of every training row, e.g. actor.head=pooled (default: none)")
    cost.add_argument("--training-steps", type=int, default=100,
                      help="episode length of the training rows (3 iterations of B x this many frames)")
    cost.add_argument("--warmup", action="store_true",
                      help="also time the first compiled ESCORT update in fresh processes, cold and from the cache")
    cost.add_argument("--no-updates", action="store_true", help="skip the per-update grid (training/warm-up rows only)")
    options.add_threads_option(cost)
    options.add_output_option(cost, "outputs/bench/cost", "cost.md and cost.json")
    cost.set_defaults(handler=main)


def main(args) -> None:
    from pathlib import Path

    from escort_rl.config.schema import check_device
    from escort_rl.reporting.paths import write_results

    problem = check_device(args.device)
    if problem is not None:
        raise ValueError(f"--device: {problem.replace('device=cpu', '--device cpu')}")
    if not (math.isfinite(args.max_pairs) and args.max_pairs > 0):
        raise ValueError(f"--max-pairs: must be a finite number > 0, got {args.max_pairs}")
    compile = options.compile_override(args.overrides)
    options.set_threads(args)
    grid = dict(dims=args.dims, particles=args.particles, batches=args.batch_sizes)
    if args.quick:
        grid = dict(dims=[10, 20], particles=[100], batches=[1, 2])

    def show(row):
        print(f"{row['filter']:>15} d={row['d']:<4} N={row['N']:<5} B={row['B']:<3} "
              f"{1e3 * row['seconds']:9.2f} ms", flush=True)

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    result = {} if args.no_updates else run_cost_benchmark(
        **grid, repeats=args.repeats, num_steps=args.num_steps, device=args.device, progress=show,
        max_pairs=args.max_pairs, compile=compile)
    if args.training or args.warmup:
        from escort_rl.bench.training_cost import training_cost_rows

        result.update(training_cost_rows(args.training, out / "training_runs", args.training_steps,
                                         args.warmup, progress=print, overrides=tuple(args.training_overrides)))
    write_results(out, "cost", result, cost_markdown(result))
