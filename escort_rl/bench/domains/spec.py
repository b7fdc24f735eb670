"""Every setting of one ``bench domains`` run, in one frozen :class:`DomainsSpec`, and the two sets
of defaults: :meth:`DomainsSpec.full` (the command's defaults) and :meth:`DomainsSpec.quick`
(``--quick``). The field defaults are protocol (a)'s full run; this module is the only place that
states a default."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from escort_rl.bench import methods as registry
from escort_rl.metrics.reference import SAMPLE

PROTOCOLS = ("a", "b")
"""``a``: shared trajectories; ``b``: closed loop (each method trains its own policy)."""
DEFAULT_OUTPUT = "outputs/bench/domains"
"""The command's ``--output`` (a spec without ``output`` writes nothing but its result)."""
PARTICLE_GRID = (50, 100, 200, 500, 1000, 2000, 5000, 10_000, 20_000, 50_000, 100_000)
"""The ``N'`` the equal wall-clock table chooses from (capped by ``max_particles``)."""

_QUICK = {
    "a": dict(methods=registry.QUICK_METHODS, seeds=2, particles=30, steps=20, max_particles=60, calibration_steps=1,
              reference_particles=2000, reference_sample=200),
    "b": dict(methods=registry.QUICK_METHODS, seeds=2, particles=20, steps=10, train_iterations=1, train_envs=2),
}
"""What ``--quick`` changes from the field defaults, per protocol."""


@dataclass(frozen=True)
class DomainsSpec:
    """One run of the domain benchmark: protocol (a) (:func:`~escort_rl.bench.domains.run.run_domains`)
    or protocol (b) (:func:`~escort_rl.bench.domains.run.run_closed_loop`).

    Sequences are stored as tuples and ``output`` as a ``Path``; the simple checks (counts at least
    1, the reference sizes, the flags of the other protocol) run on construction, each naming its
    command-line option. The names of domains and methods are checked when the run starts (they
    read the configs).

    Examples:
        >>> DomainsSpec().particles, DomainsSpec.quick().particles, DomainsSpec.quick("b").particles
        (100, 30, 20)
        >>> DomainsSpec.quick(particles=50).methods
        ('escort', 'svgd', 'sir')
        >>> DomainsSpec(seeds=0)
        Traceback (most recent call last):
        ...
        ValueError: --seeds: must be a positive int, got 0
    """

    protocol: str = "a"
    domains: tuple = registry.DOMAINS
    """Env configs, the tables' columns."""
    methods: tuple = registry.PROTOCOL_A_METHODS
    """Filter configs and learned beliefs (protocol b: also the named rows of its yaml; the random
    row is always added)."""
    seeds: int | None = 30
    """Seeds ``0 .. seeds-1`` (protocol b: evaluation episodes; ``None``: the yaml's)."""
    particles: int | None = 100
    """N of every method (protocol b: ``None``, the yaml's)."""
    steps: int | None = None
    """Steps per trajectory or episode (``None``: each env's ``max_steps``)."""
    threads: int = 1
    """Torch threads in each cell and in the equal-time measurement."""
    seeds_per_cell: int | None = None
    """Seeds per protocol (a) cell (``None``: all seeds of a row in one cell)."""
    filter_set: tuple = ()
    """``((key, value), ...)`` set on every method's filter config that has the key."""
    output: Path | None = None
    """The results folder: plots, ``cells/`` and ``runs/``. ``None`` (protocol a only): no plots, no
    saved cells, the reference files in a temporary folder, and no learned beliefs."""
    equal_time: bool = True
    """Protocol (a): add the equal wall-clock table."""
    max_particles: int = 100_000
    """Protocol (a): the largest ``N'`` of the equal wall-clock table."""
    particle_grid: tuple = PARTICLE_GRID
    """Protocol (a): the ``N'`` the equal wall-clock table chooses from."""
    time_reference: str = "escort"
    """Protocol (a): the method whose time per step at N is the budget (the first method if absent)."""
    calibration_steps: int = 3
    """Protocol (a): timed updates per ``N'`` in the equal-time measurement."""
    base_seed: int = 0
    """Protocol (a): added to every seed of the trajectories and priors."""
    reference_particles: int = 100_000
    """Protocol (a): N of the reference posterior (run at N and 2N); 0: none."""
    reference_sample: int = SAMPLE
    """Protocol (a): reference particles kept per step for the sample-based distances."""
    train_iterations: int | None = None
    """Protocol (b): ``trainer.iterations`` for every domain (``None``: the yaml's budget)."""
    train_envs: int | None = None
    """Protocol (b): ``trainer.num_envs`` for every domain (``None``: the yaml's budget)."""
    train_progress: bool = False
    """Protocol (b): show the trainer's progress."""

    @classmethod
    def full(cls, protocol: str = "a", **changes) -> DomainsSpec:
        """The command's defaults for ``protocol`` (b: the yaml's methods, episodes and N), with
        ``changes`` on top."""
        base = {}
        if protocol == "b":
            base = dict(seeds=None, particles=None)
            if "methods" not in changes:
                base["methods"] = tuple(registry.protocol_b_methods())
        return cls(protocol=protocol, **{**base, **changes})

    @classmethod
    def quick(cls, protocol: str = "a", **changes) -> DomainsSpec:
        """``--quick`` for ``protocol``, with ``changes`` (the flags given explicitly) on top."""
        if protocol not in _QUICK:
            raise ValueError(f"--protocol: expected one of {', '.join(PROTOCOLS)}, got {protocol!r}")
        return cls(protocol=protocol, **{**_QUICK[protocol], **changes})

    def __post_init__(self) -> None:
        for name in ("domains", "methods", "particle_grid"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        object.__setattr__(self, "filter_set", tuple(tuple(kv) for kv in self.filter_set))
        if self.output is not None:
            object.__setattr__(self, "output", Path(self.output))
        self._check()

    def _check(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"--protocol: expected one of {', '.join(PROTOCOLS)}, got {self.protocol!r}")
        registry.check_at_least_one(seeds=self.seeds, particles=self.particles, steps=self.steps,
                                    threads=self.threads, seeds_per_cell=self.seeds_per_cell,
                                    train_iterations=self.train_iterations, train_envs=self.train_envs)
        if self.protocol == "b":
            if self.seeds_per_cell is not None:
                raise ValueError("--seeds-per-cell: protocol b's cells are (domain, method) runs; leave it out")
            return
        if self.train_iterations is not None or self.train_envs is not None:
            raise ValueError("--train-iterations/--train-envs: only for --protocol b")
        n_ref, sample = self.reference_particles, self.reference_sample
        if isinstance(n_ref, bool) or not isinstance(n_ref, int) or n_ref < 0:
            raise ValueError(f"--reference-particles: must be a whole number >= 0 (0: no reference), got {n_ref!r}")
        if n_ref and (isinstance(sample, bool) or not isinstance(sample, int) or not 2 <= sample <= n_ref):
            raise ValueError(f"--reference-sample: must be a whole number from 2 to --reference-particles "
                             f"({n_ref}), got {sample!r}")

    def train_overrides(self) -> dict:
        """Protocol (b): the trainer keys set for every domain on top of the yaml's budget."""
        return {k: v for k, v in (("iterations", self.train_iterations), ("num_envs", self.train_envs))
                if v is not None}
