"""The cells of protocol (a): one filter method (:class:`FilterCell`) or one learned belief
(:class:`LearnedCell`) on one domain's shared trajectories of a block of seeds, filtered as one
batch ``[S, N, d]``; and the training of the learned beliefs they read
(:func:`train_learned_beliefs`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from escort_rl.bench import methods as registry
from escort_rl.bench.core.runner import Cell
from escort_rl.bench.domains.closed_loop_cells import run_config, train_run
from escort_rl.bench.methods import build_domain
from escort_rl.bench.trajectories import filter_trajectories, generate_trajectories, learned_trajectories
from escort_rl.metrics.reference import Reference, summarize_series


def cell_result(out: dict) -> dict:
    """A filtering output (:func:`~escort_rl.bench.trajectories.filter_trajectories`) as a cell result:
    plain lists, and the wall-clock figures under ``timing`` (the only entries that differ between runs)."""
    part = {k: v for k, v in out.items() if k not in ("seconds", "first_seconds", "errors", "accuracy")}
    part["errors"] = out["errors"].tolist()
    accuracy = out.get("accuracy") or []
    if accuracy:  # the first reference's whole series; the doubled reference's per-seed summaries
        part["accuracy"] = {"series": {k: v.tolist() for k, v in accuracy[0].items()},
                            "checks": [summarize_series(a, out["steps"]) for a in accuracy[1:]]}
    part["timing"] = {"seconds": out["seconds"], "first_seconds": out["first_seconds"]}
    return part


@dataclass(frozen=True)
class FilterCell(Cell):
    """One filter method on one domain's shared trajectories of ``seeds`` (one batch).

    Examples:
        >>> cell = FilterCell(domain="lightdark10d", method="sir", particles=10, steps=2, seeds=(0, 1))
        >>> cell.key()
        'domains/lightdark10d/sir/N10-T2-seeds0-1'
        >>> len(cell.run()["errors"][0])  # [S, T + 1] position errors, index 0 the prior's
        3
    """

    domain: str
    method: str
    particles: int
    steps: int
    seeds: tuple
    base_seed: int = 0
    filter_set: tuple = ()
    references: tuple = ()
    """``((particles, file, hash), ...)``: the reference posteriors of these seeds
    (:class:`~escort_rl.bench.reference_cell.ReferenceCell` results) to compare the belief with."""
    reference_folder: str = ""
    """Where the reference files are; left out of :meth:`spec` (it is where, not what)."""

    def key(self) -> str:
        return (f"domains/{self.domain}/{self.method}/N{self.particles}-T{self.steps}-"
                f"seeds{self.seeds[0]}-{self.seeds[-1]}")

    def spec(self) -> dict:
        spec = super().spec()
        spec.pop("reference_folder")
        return spec

    def run(self) -> dict:
        model, _ = build_domain(self.domain)
        seeds = list(self.seeds)
        traj = generate_trajectories(model, self.steps, seeds, self.base_seed)
        refs = tuple(Reference.load(Path(self.reference_folder) / file, digest) for _, file, digest in self.references)
        for ref in refs:
            if ref.data["input_hashes"] != list(traj["hashes"]):
                raise RuntimeError(f"{self.key()}: its reference posterior was computed on other trajectories")
        part = cell_result(filter_trajectories(self.domain, self.method, traj, seeds, self.particles, self.base_seed,
                                         self.filter_set, refs))
        if "accuracy" in part:
            part["accuracy"]["references"] = [int(n) for n, _, _ in self.references]
        return part


@dataclass(frozen=True)
class LearnedCell(Cell):
    """A learned belief (DVRL, from ``checkpoint``) on one domain's shared trajectories of ``seeds``.
    Not stored: the checkpoint may be trained further between runs."""

    domain: str
    method: str
    steps: int
    seeds: tuple
    checkpoint: str
    base_seed: int = 0
    stored = False

    def key(self) -> str:
        return f"domains/{self.domain}/{self.method}/T{self.steps}-seeds{self.seeds[0]}-{self.seeds[-1]}"

    def run(self) -> dict:
        model, _ = build_domain(self.domain)
        seeds = list(self.seeds)
        traj = generate_trajectories(model, self.steps, seeds, self.base_seed)
        return cell_result(learned_trajectories(self.domain, self.method, traj, seeds, self.checkpoint, self.base_seed))


def train_learned_beliefs(domains, methods, runs_dir: Path, progress: bool = False) -> dict:
    """Train (or resume, or reuse) each learned-belief method of ``methods`` on each domain in
    ``runs_dir/<domain>/<method>``, with protocol (b)'s run config and budget (the same folder layout,
    so ``--output`` of a protocol (b) run can share its runs). Returns ``{(domain, method): checkpoint}``."""
    settings = registry.load_settings()
    learned = registry.learned_methods(settings)
    out = {}
    for d in domains:
        for m in methods:
            if m in learned:
                cfg = run_config(d, "sir", int(settings["particles"]), Path(runs_dir) / d / m,
                                 settings["train"][d], trainer=learned[m]["trainer"])
                out[(d, m)] = train_run(cfg, progress=progress)["checkpoint"]
    return out

