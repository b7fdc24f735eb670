"""Protocol (a)'s grid of cells: the reference posteriors (:meth:`Grid.run_references`, which
returns the :class:`References` the method cells read) and the (domain, method, N) rows
(:meth:`Grid.run`, which takes them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from escort_rl.bench.core.runner import Cell, run_groups, seed_blocks
from escort_rl.bench.domains.cells import FilterCell, LearnedCell
from escort_rl.bench.domains.rows import assemble_row
from escort_rl.bench.domains.spec import DomainsSpec
from escort_rl.bench.reference_cell import ReferenceCell
from escort_rl.metrics.reference import Reference, summarize_series
from escort_rl.reporting.stats import mean_se


@dataclass(frozen=True)
class References:
    """The reference posteriors a run's method cells are compared with: ``folder``, where their
    files are, and ``files``: (domain, seed block) -> ``((particles, file, hash), ...)``. The empty
    one (the default) means no reference."""

    folder: str = ""
    files: dict = field(default_factory=dict)

    def of(self, domain: str, block: tuple) -> tuple:
        return self.files.get((domain, block), ())


class Grid:
    """Runs a spec's (domain, method, N) rows as cells on ``backend`` and assembles the rows.

    ``horizon``: domain -> steps per trajectory; ``store``: the saved cells (or ``None``);
    ``learned``: (domain, method) -> checkpoint of each learned belief; ``progress(kind, payload)``
    gets each row as it is complete."""

    def __init__(self, spec: DomainsSpec, horizon: dict, backend, store=None, learned: dict | None = None,
                 progress=None) -> None:
        self.spec, self.horizon, self.backend, self.store = spec, horizon, backend, store
        self.learned, self.progress = learned or {}, progress
        self.seeds = list(range(spec.seeds))
        self.blocks = seed_blocks(self.seeds, spec.seeds_per_cell)

    def cells(self, domain: str, method: str, n: int, references: References) -> list[Cell]:
        """The cells of one row, one per seed block."""
        common = dict(domain=domain, method=method, steps=self.horizon[domain], base_seed=self.spec.base_seed,
                      threads=self.spec.threads)
        if (domain, method) in self.learned:
            return [LearnedCell(seeds=b, checkpoint=str(self.learned[(domain, method)]), **common)
                    for b in self.blocks]
        return [FilterCell(particles=n, seeds=b, filter_set=self.spec.filter_set, references=references.of(domain, b),
                           reference_folder=references.folder, **common) for b in self.blocks]

    def run(self, jobs: list[tuple[str, str, int]], references: References, desc: str) -> list[dict]:
        """``jobs``: (domain, method, N). Rows in job order; each is reported to ``progress`` as
        soon as its last cell is in."""
        rows = {}

        def on_group(job, parts):
            rows[job] = assemble_row(*job, parts, self.seeds)
            if self.progress is not None:
                self.progress("row", rows[job])

        run_groups({job: self.cells(*job, references) for job in jobs}, self.backend, self.store, on_group, desc)
        return [rows[job] for job in jobs]

    def run_references(self, folder: Path, trajectory_hashes: dict) -> tuple[References, dict]:
        """Compute (or load) the reference posteriors at ``N_ref`` and ``2 × N_ref`` of every domain
        and seed block into ``folder``. Returns the :class:`References` for the method cells and,
        per domain, the sizes, seconds, and the distance between the two references (the floor
        under the figures). ``trajectory_hashes``: domain -> the shared trajectories' hashes, which
        the references must have seen."""
        spec = self.spec
        sizes = (spec.reference_particles, 2 * spec.reference_particles)
        cells = {(d, b, n): ReferenceCell(domain=d, particles=n, steps=self.horizon[d], seeds=b,
                                          base_seed=spec.base_seed, sample=spec.reference_sample, folder=str(folder),
                                          threads=spec.threads)
                 for d in spec.domains for b in self.blocks for n in sizes}
        if self.store is not None:  # a saved result whose file is gone or damaged is computed again
            for cell in cells.values():
                saved = self.store.load(cell)
                if saved is not None and not cell.valid(saved):
                    self.store.path(cell).unlink()
        results = {k: v[0] for k, v in run_groups({k: [c] for k, c in cells.items()}, self.backend, self.store,
                                                  desc="reference cells").items()}
        references = References(str(folder), {
            (d, b): tuple((n, results[(d, b, n)]["file"], results[(d, b, n)]["hash"]) for n in sizes)
            for d in spec.domains for b in self.blocks})
        out = {}
        for d in spec.domains:
            hashes = [h for b in self.blocks for h in results[(d, b, sizes[0])]["input_hashes"]]
            if hashes != trajectory_hashes[d]:
                raise RuntimeError(f"the reference posterior of '{d}' saw a different trajectory")
            out[d] = {"particles": list(sizes), "sample": spec.reference_sample,
                      "seconds": {str(n): sum(results[(d, b, n)]["timing"]["seconds"] for b in self.blocks)
                                  for n in sizes},
                      "floor": self._floor(d, folder, [[results[(d, b, n)] for n in sizes] for b in self.blocks])}
        return references, out

    def _floor(self, domain: str, folder: Path, pairs: list[list[dict]]) -> dict:
        """The distance of the 2 N_ref reference to the N_ref one (per seed block: the two cells'
        results), time-averaged and final, mean ± s.e. over seeds."""
        floor = []
        for pair in pairs:
            ref, ref2 = (Reference.load(folder / r["file"], r["hash"]) for r in pair)
            steps = [ref.compare_reference(ref2, t) for t in range(self.horizon[domain] + 1)]
            floor.append({k: torch.stack([s[k] for s in steps], 1) for k in steps[0]})
        series = {k: torch.cat([f[k] for f in floor]) for k in floor[0]}
        per_seed = summarize_series(series, self.horizon[domain])
        return {k: {w: mean_se(v[w]) for w in ("final", "mean")} for k, v in per_seed.items()}
