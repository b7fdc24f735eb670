"""The benchmark cell that computes a reference posterior (:func:`~escort_rl.metrics.reference.reference_posterior`)
of one domain's shared trajectories, writes its tensors to a file named by the cell's key under
``folder`` and returns the file's name and a hash of its tensors; a method cell recomputes that hash
when it loads the file (:meth:`~escort_rl.metrics.reference.Reference.load`), so a damaged or
replaced file is detected, not read."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from escort_rl.bench.core.runner import Cell
from escort_rl.metrics.reference import SAMPLE, Reference, content_hash, reference_posterior


@dataclass(frozen=True)
class ReferenceCell(Cell):
    """The reference posterior of one domain's shared trajectories of ``seeds`` at ``particles``.

    Its tensors go to ``<folder>/<key>.pt``; the result names the file (relative to ``folder``) and
    the hash of its tensors. ``folder`` is where the file lives, not what it holds, so it is left
    out of :meth:`spec`: two runs in different folders have the same cells.
    """

    domain: str
    particles: int
    steps: int
    seeds: tuple
    base_seed: int = 0
    sample: int = SAMPLE
    folder: str = ""
    replicate: int = 0
    """``r > 0``: an independent reference on the same trajectories (:func:`reference_posterior`'s ``replicate``)."""
    method: str = "sir"
    """The reference's filter (:func:`reference_posterior`'s ``method``)."""

    def key(self) -> str:
        return (f"reference/{self.domain}/N{self.particles}-M{self.sample}-T{self.steps}-"
                f"seeds{self.seeds[0]}-{self.seeds[-1]}" + (f"-r{self.replicate}" if self.replicate else "")
                + (f"-{self.method}" if self.method != "sir" else ""))

    def spec(self) -> dict:
        spec = super().spec()
        spec.pop("folder")
        if not self.replicate:  # the first reference keeps the spec (and saved file) it had before replicates
            spec.pop("replicate")
        if self.method == "sir":  # so does a SIR reference, from before the choice of filter
            spec.pop("method")
        return spec

    def model(self):
        """The model whose posterior this is: the domain's (a subclass may build another)."""
        from escort_rl.bench.methods import build_domain

        return build_domain(self.domain)[0]

    def posterior(self, model, traj: dict, seeds: list[int]) -> dict:
        """The reference's tensors (:func:`reference_posterior`; a subclass may compute another)."""
        return reference_posterior(model, traj, seeds, self.particles, self.base_seed, self.sample, name=self.domain,
                                   replicate=self.replicate, method=self.method)

    def run(self) -> dict:
        from escort_rl.bench.trajectories import generate_trajectories

        model = self.model()
        seeds = list(self.seeds)
        traj = generate_trajectories(model, self.steps, seeds, self.base_seed)
        t0 = time.perf_counter()
        data = self.posterior(model, traj, seeds)
        seconds = time.perf_counter() - t0
        data["input_hashes"] = list(traj["hashes"])
        name = f"{self.key()}.pt"
        path = Path(self.folder) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".pt.tmp")
        torch.save(data, tmp)
        tmp.replace(path)
        return {"file": name, "hash": content_hash(data), "input_hashes": data["input_hashes"],
                "timing": {"seconds": seconds}}

    def valid(self, result: dict) -> bool:
        """Whether the file of a saved ``result`` is there and holds what the result says."""
        try:
            Reference.load(Path(self.folder) / result["file"], result["hash"])
        except (OSError, ValueError, KeyError, RuntimeError):
            return False
        return True

