"""Grids of independent cells, run on one of three backends, each result saved as it finishes.

A benchmark is a list of **cells**: frozen dataclasses (:class:`Cell`) that hold everything their
result depends on (method, domain or target, seeds, sizes, torch threads, device) and whose
:meth:`Cell.run` returns a JSON-serialisable dict. A cell draws its randomness only from its own
fields (seeded generators), so the same cell gives the same numbers wherever it runs.

:func:`run_cells` runs a grid on a backend:

- ``inprocess``: one cell after another in this process;
- ``process``: a spawn pool of ``workers`` local processes (``--workers K``);
- ``ray``: each cell a ``ray.remote`` task with its CPUs (its torch threads) and, for a CUDA cell, one
  GPU declared (``--ray-address ADDRESS``, or ``RAY_ADDRESS``, joins a running cluster; without
  either a local Ray starts and stops with the run).

Every cell sets torch's thread count to its ``threads`` before it runs, on every backend, so the
thread count (which can change the floating-point order of a reduction) is part of the cell.
With a :class:`CellStore` each result is written as ``<root>/<cell.key()>-<hash>.json`` (the hash
is of :meth:`Cell.spec`) the moment it arrives, and a rerun loads the finished cells instead of
running them again. A tqdm bar counts the cells (on a terminal).

Examples:
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class Square(Cell):
    ...     x: int
    ...     def key(self): return f"square/{self.x}"
    ...     def run(self): return {"y": self.x ** 2}
    >>> [r["y"] for r in run_cells([Square(x=2), Square(x=3)], make_backend("inprocess"))]
    [4, 9]
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

BACKENDS = ("inprocess", "process", "ray")
RAY_MISSING = "ray is not installed; install with pip install escort-rl[ray]"


@dataclass(frozen=True, kw_only=True)
class Cell:
    """One independent unit of a benchmark grid.

    Subclasses are frozen dataclasses (picklable, hashable) and define :meth:`key` (a readable
    relative path, unique within the grid) and :meth:`run`. ``threads``: the torch threads the cell
    runs with (and the CPUs a Ray task declares); ``device``: where its tensors live (a ``cuda``
    device makes a Ray task declare one GPU).
    """

    threads: int = 1
    device: str = "cpu"
    stored = True
    """Whether a :class:`CellStore` keeps the result (a cell whose inputs live outside its fields,
    such as a checkpoint that may be retrained, sets it to ``False``)."""

    def key(self) -> str:
        raise NotImplementedError

    def run(self) -> dict:
        raise NotImplementedError

    def spec(self) -> dict:
        """Everything the result depends on, as plain JSON: the cell's type and fields."""
        return json.loads(json.dumps({"cell": type(self).__name__, **asdict(self)}))

    def resources(self) -> dict:
        """The Ray resources of the cell's task: ``num_cpus`` (its threads) and ``num_gpus``."""
        return {"num_cpus": self.threads, "num_gpus": 1 if str(self.device).startswith("cuda") else 0}


class ConfigCell(Cell):
    """A cell that runs a composed config (:meth:`config`): its result depends on that config, so its spec
    holds the config resolved, and a changed config file makes a new cell even with the same fields."""

    def config(self):
        raise NotImplementedError

    def spec(self) -> dict:
        from omegaconf import OmegaConf

        return {**super().spec(), "config": OmegaConf.to_container(self.config(), resolve=True)}


def execute_cell(cell: Cell) -> dict:
    """Run ``cell`` with its torch thread count (restored afterwards); the result gets the cell's
    wall-clock seconds under ``timing.cell_seconds``. Module-level, so every backend can ship it."""
    previous = torch.get_num_threads()
    torch.set_num_threads(cell.threads)
    try:
        t0 = time.perf_counter()
        result = cell.run()
        result.setdefault("timing", {})["cell_seconds"] = time.perf_counter() - t0
        return result
    finally:
        torch.set_num_threads(previous)


class CellStore:
    """Cell results on disk under ``root``: ``<root>/<cell.key()>-<hash of spec>.json``, holding
    ``{"spec": ..., "result": ...}``, written atomically (a killed write leaves no file)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def path(self, cell: Cell) -> Path:
        digest = hashlib.sha256(json.dumps(cell.spec(), sort_keys=True).encode()).hexdigest()[:10]
        return self.root / f"{cell.key()}-{digest}.json"

    def load(self, cell: Cell) -> dict | None:
        """The saved result of ``cell``, or ``None`` (none, unreadable, or saved for another spec)."""
        if not cell.stored:
            return None
        try:
            saved = json.loads(self.path(cell).read_text())
        except (OSError, ValueError):
            return None
        return saved.get("result") if saved.get("spec") == cell.spec() else None

    def save(self, cell: Cell, result: dict) -> None:
        if not cell.stored:
            return
        path = self.path(cell)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps({"spec": cell.spec(), "result": result}))
        tmp.replace(path)


class InProcessBackend:
    """Runs the cells one after another in this process."""

    name = "inprocess"

    def map(self, cells: list[Cell]):
        """Yield ``(index, result)`` as each cell finishes."""
        for i, cell in enumerate(cells):
            yield i, execute_cell(cell)

    def close(self) -> None:
        pass


class ProcessBackend:
    """A spawn pool of ``workers`` local processes; cells go to whichever worker is free."""

    name = "process"

    def __init__(self, workers: int) -> None:
        self.workers, self.pool = workers, None

    def map(self, cells: list[Cell]):
        import multiprocessing as mp
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

        if self.pool is None:
            self.pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"))
        pending = {self.pool.submit(execute_cell, c): i for i, c in enumerate(cells)}
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                yield pending.pop(future), future.result()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)
            self.pool = None


class RayBackend:
    """Each cell a ``ray.remote`` task declaring :meth:`Cell.resources`. ``address``: a running
    cluster (``auto``, ``HOST:PORT`` or ``ray://...``); ``None`` uses ``RAY_ADDRESS`` when set, else
    starts a local Ray (stopped again by :meth:`close`)."""

    name = "ray"

    def __init__(self, address: str | None = None) -> None:
        self.address, self.started = address, False

    def _init(self):
        try:
            import ray
        except ImportError:
            raise ValueError(f"--backend ray: {RAY_MISSING}") from None
        if not ray.is_initialized():
            from escort_rl.trainers.ray_collection import ray_init_kwargs

            ray.init(**ray_init_kwargs(self.address))
            self.started = True
        return ray

    def map(self, cells: list[Cell]):
        ray = self._init()
        task = ray.remote(execute_cell)
        pending = {task.options(**c.resources()).remote(c): i for i, c in enumerate(cells)}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            yield pending.pop(done[0]), ray.get(done[0])

    def close(self) -> None:
        if self.started:
            import ray

            ray.shutdown()
            self.started = False


def make_backend(name: str = "inprocess", workers: int = 1, ray_address: str | None = None):
    """The backend called ``name`` (``inprocess``, ``process`` or ``ray``); errors name the flag."""
    if name not in BACKENDS:
        raise ValueError(f"--backend: unknown backend '{name}'; choose from {', '.join(BACKENDS)}")
    if workers < 1:
        raise ValueError(f"--workers: must be >= 1, got {workers}")
    if workers > 1 and name != "process":
        raise ValueError(f"--workers: {workers} worker processes need --backend process (got {name})")
    if ray_address and name != "ray":
        raise ValueError(f"--ray-address: only with --backend ray (got {name})")
    if name == "ray":
        return RayBackend(ray_address)
    return ProcessBackend(workers) if name == "process" else InProcessBackend()


def run_cells(cells: list[Cell], backend, store: CellStore | None = None, on_result=None,
              desc: str = "cells") -> list[dict]:
    """Run ``cells`` on ``backend`` and return their results in the cells' order.

    With ``store``, finished cells are loaded instead of run, and each new result is saved as soon
    as it arrives. ``on_result(cell, result)`` is called for every cell (loaded or run) as its result
    is known, in completion order. A tqdm bar over the cells shows progress on a terminal.
    """
    from tqdm import tqdm

    results: list[dict | None] = [None] * len(cells)
    todo = []
    for i, cell in enumerate(cells):
        saved = store.load(cell) if store is not None else None
        if saved is None:
            todo.append(i)
        else:
            results[i] = saved
            if on_result is not None:
                on_result(cell, saved)
    with tqdm(total=len(cells), initial=len(cells) - len(todo), desc=desc, unit="cell", disable=None,
              leave=False) as bar:
        for j, result in backend.map([cells[i] for i in todo]):
            i = todo[j]
            if store is not None:
                store.save(cells[i], result)
            results[i] = result
            bar.update(1)
            if on_result is not None:
                with tqdm.external_write_mode():
                    on_result(cells[i], result)
    return results


def run_groups(groups: dict, backend, store: CellStore | None = None, on_group=None, desc: str = "cells") -> dict:
    """Run the cells of every group (``groups``: key -> its cells, e.g. a table row's seed blocks)
    and return key -> the results in the group's order. ``on_group(key, results)`` is called as soon
    as a group's last cell is in (loaded or run)."""
    owner = {id(c): key for key, cells in groups.items() for c in cells}
    done: dict = {key: {} for key in groups}
    out = {}

    def on_result(cell, result):
        key = owner[id(cell)]
        done[key][id(cell)] = result
        if len(done[key]) == len(groups[key]):
            out[key] = [done[key][id(c)] for c in groups[key]]
            if on_group is not None:
                on_group(key, out[key])

    run_cells([c for cells in groups.values() for c in cells], backend, store, on_result, desc)
    return out


def seed_blocks(seeds: list[int], per_cell: int | None) -> list[tuple[int, ...]]:
    """``seeds`` in consecutive blocks of ``per_cell`` (``None``: one block of all).

    Examples:
        >>> seed_blocks([0, 1, 2, 3, 4], 2)
        [(0, 1), (2, 3), (4,)]
    """
    size = len(seeds) if per_cell is None else per_cell
    return [tuple(seeds[i:i + size]) for i in range(0, len(seeds), max(size, 1))]


def backend_from_args(args):
    """The backend of ``--backend`` / ``--workers`` / ``--ray-address`` (``--workers K > 1`` alone
    means the process backend)."""
    name = args.backend or ("process" if args.workers > 1 else "inprocess")
    return make_backend(name, args.workers, args.ray_address)
