"""How noisy a learner's policy gradient is: ``escort-rl bench gradient-noise RUN``.

At the policy of a run's checkpoint (held fixed: no step is taken), the run's own collector gathers
``R`` independent batches, each of the frames one training iteration collects. On each batch, each
estimator gives one policy gradient ``g_r`` (the actor's parameters, flattened):

- ``monte carlo``: REINFORCE's advantage, the return-to-go less the baseline,
  ``Â_t = G_t − V(b_t)`` (TorchRL's ``TD1``, bootstrapped where the time limit cuts an episode);
- ``GAE λ``: the generalised advantage ``Â_t = Σ_k (γλ)^k δ_{t+k}``, ``δ_t = r_t + γ V(b_{t+1}) − V(b_t)``,
  as PPO computes it (TorchRL's ``GAE``).

Both read the run's own critic ``V``; the advantages are standardised over the batch, and
``g_r = ∇_θ [−(1/M) Σ_t log π_θ(a_t | b_t) Â_t]``, the score-function gradient that REINFORCE's loss and
PPO's clipped loss share at the policy that collected the batch. The entropy and value terms are left
out: this is the gradient of the decision, the part whose noise the estimators differ in.

:func:`gradient_statistics` then gives, over the ``R`` gradients, the noise
``σ² = 1/(R−1) Σ_r ‖g_r − ḡ‖²`` (the trace of one batch's gradient covariance), the signal
``‖E g‖² ≈ ‖ḡ‖² − σ²/R`` (unbiased), their ratio (the signal-to-noise ratio of one batch's gradient:
below 1, one batch's gradient is mostly noise), and the mean cosine of each ``g_r`` with the mean of the
others. Every estimator is measured on the same batches.
"""

from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from escort_rl.bench.core import options

MONTE_CARLO = "monte carlo"


def gradient_statistics(grads: Tensor) -> dict:
    """The noise and signal of ``R`` independent estimates ``grads`` ``[R, P]`` of one gradient ``E g``.

    - ``noise``: ``σ² = 1/(R−1) Σ_r ‖g_r − ḡ‖²``, unbiased for ``E‖g − E g‖²`` (one estimate's variance);
    - ``signal``: ``‖ḡ‖² − σ²/R``, unbiased for ``‖E g‖²`` (it may come out negative when ``R`` is small
      and the signal is far below the noise);
    - ``snr``: ``signal / noise``;
    - ``cosine``: the mean over ``r`` of ``cos(g_r, mean of the other R − 1)``;
    - ``norm``: the mean ``‖g_r‖``.

    Example: ``g_r = μ + σ z_r`` with ``z_r ~ N(0, I_P)`` has ``noise ≈ P σ²`` and ``snr ≈ ‖μ‖² / (P σ²)``.

        >>> g = torch.tensor([[1.0, 0.0], [3.0, 0.0]])
        >>> s = gradient_statistics(g)
        >>> s["noise"], s["signal"]
        (2.0, 3.0)
    """
    r = grads.shape[0]
    if grads.dim() != 2 or r < 2:
        raise ValueError(f"gradient_statistics: grads must be [R, P] with R >= 2, got {tuple(grads.shape)}")
    g = grads.double()
    mean = g.mean(0)
    noise = float((g - mean).pow(2).sum(-1).sum() / (r - 1))
    signal = float(mean.pow(2).sum()) - noise / r
    others = (g.sum(0, keepdim=True) - g) / (r - 1)
    cosine = torch.nn.functional.cosine_similarity(g, others, dim=-1)
    return {"noise": noise, "signal": signal, "snr": signal / noise if noise > 0 else math.inf,
            "cosine": float(cosine.mean()), "norm": float(g.norm(dim=-1).mean())}


def decision_gradient(policy, params: list, batch, advantage: Tensor, chunk: int) -> Tensor:
    """``∇_θ [−(1/M) Σ_t log π_θ(a_t | b_t) Â_t]`` over the ``M`` frames of ``batch`` (flattened), with
    ``advantage`` ``[M]`` (no gradient), accumulated over chunks of ``chunk`` frames; returns it flat ``[P]``
    over ``params`` (the actor's)."""
    flat = batch.reshape(-1)
    m = flat.shape[0]
    grads = [torch.zeros_like(p) for p in params]
    for start in range(0, m, chunk):
        mb = flat[start:start + chunk]
        log_prob = policy.get_dist(mb).log_prob(mb["action"])
        log_prob = log_prob.reshape(mb.shape[0], -1).sum(-1)  # one term per frame, whatever the action's shape
        loss = -(log_prob * advantage[start:start + chunk]).sum() / m
        for acc, g in zip(grads, torch.autograd.grad(loss, params, allow_unused=True)):
            if g is not None:
                acc += g
    return torch.cat([g.flatten() for g in grads])


def estimator_advantages(loss, batch, gamma: float, lambdas: tuple[float, ...]) -> dict[str, Tensor]:
    """``{estimator: standardised advantage [M]}`` on ``batch`` from ``loss``'s critic: ``monte carlo``
    (``TD1``) and ``GAE λ`` for each ``λ``. ``loss`` is a TorchRL loss module with a critic; its value
    estimator is set back to ``TD1`` or the last ``GAE`` it was given, so call this on a measurement's own
    algorithm only."""
    from torchrl.objectives import ValueEstimators

    from escort_rl.trainers.reinforce import standardised

    key = loss.tensor_keys.advantage
    out = {}
    with torch.no_grad():
        for name, kind, kw in [(MONTE_CARLO, ValueEstimators.TD1, {}),
                               *[(f"GAE λ={lam:g}", ValueEstimators.GAE, {"lmbda": lam}) for lam in lambdas]]:
            loss.make_value_estimator(kind, gamma=gamma, **kw)
            td = batch.clone(False)
            loss.value_estimator(td)
            out[name] = standardised(td[key]).flatten()  # as REINFORCE scales them, flattened [M]
    return out


def measure_run(run, batches: int, lambdas: tuple[float, ...], chunk: int = 4000) -> dict:
    """Collect ``batches`` batches at the policy of ``run``'s newest intact checkpoint and compare the
    estimators' gradients on them (see the module docstring). The run's trainer must keep a TorchRL loss
    with a critic (``loss``), its DeepSets policy (``policy``) and actor (``actor``): REINFORCE and PPO do."""
    from escort_rl.trainers.builders import build_model
    from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint
    from escort_rl.trainers.resume import run_config
    from escort_rl.trainers.training import build_algorithm

    checkpoint = resolve_checkpoint(run)
    saved = load_checkpoint(checkpoint)
    cfg = run_config(saved)
    iteration = int(saved["trainer_state"]["iteration"])
    torch.manual_seed(int(cfg.seed))
    algo = build_algorithm(cfg, build_model(cfg.env, cfg.device))
    missing = [name for name in ("loss", "policy", "actor") if not hasattr(algo, name)]
    if missing:
        raise ValueError(f"RUN: the trainer of '{run}' ({cfg.trainer.algorithm}) keeps no {', '.join(missing)}; "
                         "gradient-noise measures trainers with a TorchRL loss and a critic (ppo, reinforce)")
    load_checkpoint(checkpoint, **algo.components)
    params = [p for p in algo.actor.parameters() if p.requires_grad]
    grads: dict[str, list[Tensor]] = {}
    frames, t0 = 0, time.perf_counter()
    try:
        collector = algo.collectors.for_iteration(max(iteration - 1, 0))
        for r in range(batches):
            collector.set_seed(10_000 + 1_000 * r)
            batch = algo.collectors.next()
            batch = batch.reshape(-1, batch.shape[-1])
            batch["next", "reward"] = batch["next", "reward"] * algo.params.reward_scale
            frames = batch.numel()
            for name, adv in estimator_advantages(algo.loss, batch, algo.params.gamma, lambdas).items():
                grads.setdefault(name, []).append(decision_gradient(algo.policy, params, batch, adv, chunk))
    finally:
        algo.close()
    return {"run": str(run), "trainer": str(cfg.trainer.algorithm), "filter": algo.belief_at(max(iteration - 1, 0)),
            "iteration": iteration, "frames_trained": int(saved["trainer_state"]["frames"]),
            "batches": batches, "frames_per_batch": frames, "parameters": int(sum(p.numel() for p in params)),
            "seconds": time.perf_counter() - t0,
            "estimators": estimator_statistics({name: torch.stack(g) for name, g in grads.items()})}


def estimator_statistics(grads: dict[str, Tensor]) -> dict[str, dict]:
    """:func:`gradient_statistics` of each estimator's gradients ``[R, P]``, and ``agreement``: the cosine
    of its mean gradient with the Monte-Carlo estimator's, the unbiased one (GAE's may be biased by
    the critic: a consistent direction is not the right one unless it agrees)."""
    reference = grads[MONTE_CARLO].double().mean(0)
    return {name: {**gradient_statistics(g), "agreement": float(torch.nn.functional.cosine_similarity(
        g.double().mean(0), reference, dim=0))} for name, g in grads.items()}


def gradient_noise_markdown(results: list[dict]) -> str:
    """The report: one table per run, one row per estimator."""
    lines = ["# Policy-gradient noise", "",
             "One batch's policy gradient at a fixed policy (a run's checkpoint), over independent batches of one "
             "training iteration's frames. Noise σ² = E‖g − E g‖², signal ‖E g‖², SNR = signal / noise (below 1: "
             "one batch's gradient is mostly noise); cosine: of each batch's gradient with the mean of the others. "
             "Monte carlo is REINFORCE's advantage (return-to-go less the baseline), GAE is PPO's; both read the run's "
             "critic, on the same batches. Agreement: the cosine of the estimator's mean gradient with Monte Carlo's, "
             "the unbiased one (a critic's error can make GAE consistent in a wrong direction).", ""]
    for res in results:
        lines += [f"## {res['run']}", "",
                  f"{res['trainer']} on {res['filter']} beliefs, at iteration {res['iteration']} "
                  f"({res['frames_trained']:,} frames trained); {res['batches']} batches of "
                  f"{res['frames_per_batch']:,} frames; {res['parameters']:,} actor parameters; "
                  f"{res['seconds']:.0f} s.", "",
                  "| estimator | noise σ² | signal ‖E g‖² | SNR | cosine | agreement | mean ‖g‖ |",
                  "|---|---|---|---|---|---|---|"]
        for name, s in res["estimators"].items():
            lines.append(f"| {name} | {s['noise']:.3g} | {s['signal']:.3g} | {s['snr']:.3f} | {s['cosine']:.3f} | "
                         f"{s['agreement']:.3f} | {s['norm']:.3g} |")
        lines.append("")
    return "\n".join(lines)


def register(subparsers) -> None:
    """Add ``bench gradient-noise`` to the ``bench`` subparsers."""
    from escort_rl.trainers.params import PPOParams

    p = subparsers.add_parser("gradient-noise", help="the noise of a learner's policy gradient at a run's checkpoint",
                              description="At the policy of each run's newest checkpoint, collects independent batches "
                              "(one training iteration's frames each) and compares REINFORCE's Monte-Carlo advantage "
                              "with GAE's (PPO's) on the same batches: the noise, signal and signal-to-noise ratio of "
                              "one batch's policy gradient.")
    p.add_argument("runs", nargs="+", metavar="RUN", help="run directories or checkpoints (REINFORCE or PPO)")
    p.add_argument("--batches", type=int, default=8, help="independent batches at each checkpoint (at least 2)")
    p.add_argument("--lambdas", type=float, nargs="+", default=[PPOParams.gae_lambda],
                   help="GAE's λ for each GAE row (PPO's default first)")
    options.add_threads_option(p)
    options.add_output_option(p, "outputs/bench/gradient_noise", "gradient_noise.md and gradient_noise.json")
    p.set_defaults(handler=main)


def main(args) -> None:
    from escort_rl.reporting.paths import write_results

    if args.batches < 2:
        raise ValueError(f"--batches: at least 2 give a variance, got {args.batches}")
    bad = [lam for lam in args.lambdas if not 0.0 <= lam <= 1.0]
    if bad:
        raise ValueError(f"--lambdas: each λ lies in [0, 1], got {bad[0]}")
    options.set_threads(args)
    results = [measure_run(run, args.batches, tuple(args.lambdas)) for run in args.runs]
    write_results(args.output, "gradient_noise", {"runs": results}, gradient_noise_markdown(results))
