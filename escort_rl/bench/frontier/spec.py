"""Every setting of one ``bench frontier`` run in a frozen :class:`FrontierSpec`, of one ``bench
regime-map`` in a :class:`RegimeSpec` (its axes, and a :class:`FrontierSpec` for each point's
settings), and of one ``bench frontier-decisions`` in a :class:`DecisionsSpec`; each with
``full()`` (the command's defaults) and ``quick()`` (``--quick``). The field defaults are the full
runs; this module is the only place that states a default."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from escort_rl.bench.frontier.cells import FILTER_METHODS, ITERATIVE
from escort_rl.bench.methods import check_at_least_one, check_choices

DEFAULT_OUTPUT = "outputs/bench/frontier"
"""``bench frontier``'s ``--output``."""
REGIME_OUTPUT = "outputs/bench/regime_map"
"""``bench regime-map``'s ``--output``."""
DECISIONS_OUTPUT = "outputs/bench/frontier_decisions"
"""``bench frontier-decisions``'s ``--output``."""
METRICS = ("w1", "mean", "cov", "mmd2")
"""The distances to the reference a front can be drawn on (``w1``: sliced W1)."""
DEFAULT_PARTICLES = {"sir": (100, 300, 1000, 3000, 10_000, 30_000, 100_000),
                     "enkf": (100, 300, 1000, 3000, 10_000, 30_000, 100_000),
                     "svgd": (30, 100, 300, 1000), "escort": (30, 100, 300, 1000)}
"""The N swept per filter."""
DEFAULT_ITERATIONS = (5, 15, 50)
"""The K swept for SVGD and ESCORT."""

_QUICK = dict(particles={"sir": (100, 1000, 10_000), "enkf": (100, 1000, 10_000), "svgd": (50, 200),
                         "escort": (50, 200)},
              iterations=(5, 15), seeds=2, steps=5, reference_particles=2000)
"""What ``bench frontier --quick`` changes: a few points per filter, 2 seeds × 5 steps."""
_REGIME_QUICK = dict(dims=(2, 4), obs_stds=(1.0,))
"""What ``bench regime-map --quick`` changes on the map (each point: ``bench frontier --quick``)."""
_DECISIONS_QUICK = dict(episodes=4, steps=5)
"""What ``bench frontier-decisions --quick`` changes: 4 episodes of 5 steps."""


@dataclass(frozen=True)
class FrontierSpec:
    """One frontier (:func:`~escort_rl.bench.frontier.run.run_frontier`): every filter of ``methods``
    over its N (and K) on one model.

    ``particles`` holds an N tuple for every filter (a filter left out of the given dict gets the
    default's); sequences are stored as tuples and ``output`` as a ``Path``. The simple checks run on
    construction, each naming its command-line option; the model is built when the run starts.

    Examples:
        >>> FrontierSpec().seeds, FrontierSpec.quick().seeds, FrontierSpec.quick().particles["svgd"]
        (5, 2, (50, 200))
        >>> FrontierSpec.quick(particles={"sir": (10,)}).particles["enkf"]
        (100, 1000, 10000)
        >>> FrontierSpec(metric="w2")
        Traceback (most recent call last):
        ...
        ValueError: --metric: unknown metric 'w2'; choose from w1, mean, cov, mmd2
    """

    model: str = "env:linear_gaussian"
    """``env:NAME`` (a package env) or ``class:pkg.module:Class`` (a model of one's own)."""
    model_args: tuple = ()
    """``KEY=VALUE`` items: the env's overrides, or the class's keyword arguments."""
    methods: tuple = FILTER_METHODS
    """The filters swept."""
    particles: dict = field(default_factory=lambda: dict(DEFAULT_PARTICLES))
    """Filter -> the N swept."""
    iterations: tuple = DEFAULT_ITERATIONS
    """The K of SVGD and ESCORT (``--num-steps``)."""
    seeds: int = 5
    """Shared trajectories."""
    steps: int = 20
    """Updates per trajectory."""
    compile: bool = False
    """SVGD and ESCORT compiled (the first update, which compiles, is not timed)."""
    metric: str = "w1"
    """The front's distance, one of :data:`METRICS`."""
    reference_particles: int = 100_000
    """N of the SIR reference for a model without an exact posterior."""
    reference_filter: str = "sir"
    """The filter of that reference: ``sir``, ``resample_move`` (tempered, with MCMC moves:
    :class:`~escort_rl.belief.ResampleMoveFilter`) or ``rao_blackwell``
    (:mod:`~escort_rl.metrics.rao_blackwell`), one of :data:`~escort_rl.metrics.reference.REFERENCE_METHODS`."""
    threads: int = 1
    """Torch threads in each cell."""
    base_seed: int = 0
    """Added to every seed of the trajectories and priors."""
    variants: tuple = ()
    """``((name, method, ("KEY=VALUE", ...)), ...)``: more rows, each a filter with its own settings
    swept over its method's N (and K)."""
    output: Path | None = None
    """Where the cells (and the SIR reference) are kept; ``None``: nowhere."""

    @classmethod
    def full(cls, **changes) -> FrontierSpec:
        """The command's defaults, with ``changes`` on top."""
        return cls(**changes)

    @classmethod
    def quick(cls, **changes) -> FrontierSpec:
        """``--quick``, with ``changes`` (the flags given explicitly) on top; ``particles`` is merged
        per filter."""
        particles = {**_QUICK["particles"], **changes.pop("particles", {})}
        return cls(**{**_QUICK, **changes, "particles": particles})

    def __post_init__(self) -> None:
        for name in ("model_args", "methods", "iterations"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        particles = {**DEFAULT_PARTICLES, **self.particles}
        object.__setattr__(self, "particles", {m: tuple(int(n) for n in ns) for m, ns in particles.items()})
        object.__setattr__(self, "variants", tuple((name, method, tuple(settings))
                                                   for name, method, settings in self.variants))
        if self.output is not None:
            object.__setattr__(self, "output", Path(self.output))
        check_choices("--methods", self.methods, FILTER_METHODS)
        check_choices("--metric", [self.metric], METRICS, "metric")
        from escort_rl.metrics.reference import REFERENCE_METHODS

        check_choices("--reference-filter", [self.reference_filter], REFERENCE_METHODS, "reference filter")
        check_choices("particles", list(self.particles), FILTER_METHODS, "filter")
        check_choices("--variant", [method for _, method, _ in self.variants], FILTER_METHODS, "filter")
        for m, ns in self.particles.items():
            if any(n < 1 for n in ns):
                raise ValueError(f"--{m}-particles: must be >= 1, got {list(ns)}")
        check_at_least_one(num_steps=list(self.iterations), seeds=self.seeds, steps=self.steps,
                           reference_particles=self.reference_particles, threads=self.threads)
        names = [name for name, _, _ in self.variants]
        if len(set(names)) != len(names):
            raise ValueError("--variant: labels must differ")


@dataclass(frozen=True)
class RegimeSpec:
    """One regime map (:func:`~escort_rl.bench.frontier.regime.run_regime_map`): a frontier at every
    ``(D, r)`` of ``dims`` × ``obs_stds``, each with ``frontier``'s settings (its model, model
    arguments and output are the point's, :meth:`point`).

    Examples:
        >>> RegimeSpec().dims, RegimeSpec.quick().dims, RegimeSpec.quick().frontier.seeds
        ((10, 20, 50, 100, 200), (2, 4), 2)
        >>> RegimeSpec(obs_stds=[0.0])
        Traceback (most recent call last):
        ...
        ValueError: --obs-std: must be positive, got 0.0
    """

    dims: tuple = (10, 20, 50, 100, 200)
    """The dimension axis."""
    obs_stds: tuple = (0.1, 1.0)
    """The sharpness axis (``--obs-std``)."""
    env: str = "linear_gaussian"
    """The family's env config."""
    model: str | None = None
    """``pkg.module:Class``, a model class or factory of one's own instead of ``env``."""
    dim_key: str = "model.state_dim"
    """The key of the dimension axis: an env key, or a keyword argument of ``model``."""
    sharpness_key: str = "model.obs_std"
    """The key of the sharpness axis."""
    frontier: FrontierSpec = field(default_factory=FrontierSpec)
    """Every point's frontier settings."""
    output: Path | None = None
    """The map's folder, a folder per point in it (the run needs one)."""

    @classmethod
    def full(cls, frontier: FrontierSpec | None = None, **changes) -> RegimeSpec:
        """The command's defaults, with ``changes`` on top (``frontier``: default
        :meth:`FrontierSpec.full`)."""
        return cls(frontier=frontier or FrontierSpec.full(), **changes)

    @classmethod
    def quick(cls, frontier: FrontierSpec | None = None, **changes) -> RegimeSpec:
        """``--quick``, with ``changes`` on top (``frontier``: default :meth:`FrontierSpec.quick`)."""
        return cls(frontier=frontier or FrontierSpec.quick(), **{**_REGIME_QUICK, **changes})

    def __post_init__(self) -> None:
        object.__setattr__(self, "dims", tuple(int(d) for d in self.dims))
        object.__setattr__(self, "obs_stds", tuple(float(r) for r in self.obs_stds))
        if self.output is not None:
            object.__setattr__(self, "output", Path(self.output))
        check_at_least_one(dims=list(self.dims))
        for r in self.obs_stds:
            if not r > 0:
                raise ValueError(f"--obs-std: must be positive, got {r}")

    def family(self) -> str:
        """The points' model: ``class:<model>`` or ``env:<env>``."""
        return f"class:{self.model}" if self.model else f"env:{self.env}"

    def point_folder(self, dim: int, obs_std: float) -> Path:
        """``<output>/D<dim>_obs<obs_std>``."""
        return Path(self.output) / f"D{dim}_obs{obs_std:g}"

    def point(self, dim: int, obs_std: float) -> FrontierSpec:
        """The frontier at ``(dim, obs_std)``."""
        return dataclasses.replace(self.frontier, model=self.family(),
                                   model_args=(f"{self.dim_key}={int(dim)}", f"{self.sharpness_key}={float(obs_std)}"),
                                   output=self.point_folder(dim, obs_std))


def parse_row(text: str) -> tuple[str, int, int]:
    """``METHOD:N`` or ``METHOD:N:K`` (SVGD, ESCORT), or ``exact`` -> ``(method, N, K)``."""
    parts = text.split(":")
    if parts == ["exact"]:
        return "exact", 0, 0
    try:
        method, n, k = parts[0], int(parts[1]), (int(parts[2]) if len(parts) > 2 else 0)
    except (IndexError, ValueError):
        raise ValueError(f"--rows: expected METHOD:N[:K] or exact, got {text!r}") from None
    if method not in FILTER_METHODS:
        raise ValueError(f"--rows: unknown filter '{method}' in {text!r}; choose from {', '.join(FILTER_METHODS)}")
    if n < 1 or (method in ITERATIVE) != (len(parts) == 3) or (method in ITERATIVE and k < 1):
        raise ValueError(f"--rows: {text!r}: give N >= 1, and K >= 1 exactly for svgd and escort")
    return method, n, k


@dataclass(frozen=True)
class DecisionsSpec:
    """One run of the greedy regulator on frontier rows
    (:func:`~escort_rl.bench.frontier.decisions.run_decisions`). ``rows``: ``(method, N, K)`` or
    the command line's ``METHOD:N[:K]`` / ``exact`` (:func:`parse_row`), the first the baseline.

    Examples:
        >>> s = DecisionsSpec(model="class:m:M", rows=["sir:10", "exact"])
        >>> s.rows, s.episodes, DecisionsSpec.quick(model="class:m:M", rows=["sir:10"]).episodes
        ((('sir', 10, 0), ('exact', 0, 0)), 50, 4)
        >>> DecisionsSpec(model="class:m:M", rows=["sir:10"], steps=1)
        Traceback (most recent call last):
        ...
        ValueError: --episodes and --steps: need at least 2 each, got 50 and 1
    """

    model: str
    """``class:pkg.module:Class``, a model with actions and a reward ``-|s|``."""
    rows: tuple
    """The rows, ``((method, N, K), ...)``."""
    model_args: tuple = ()
    """Keyword arguments of the model, ``KEY=VALUE``."""
    episodes: int = 50
    """Closed-loop episodes per row."""
    steps: int = 20
    """Steps per episode."""
    threads: int = 1
    """Torch threads in each cell."""
    output: Path | None = None
    """Where the cells are kept; ``None``: nowhere."""

    @classmethod
    def full(cls, **changes) -> DecisionsSpec:
        """The command's defaults, with ``changes`` on top."""
        return cls(**changes)

    @classmethod
    def quick(cls, **changes) -> DecisionsSpec:
        """``--quick``, with ``changes`` (the flags given explicitly) on top."""
        return cls(**{**_DECISIONS_QUICK, **changes})

    def __post_init__(self) -> None:
        object.__setattr__(self, "model_args", tuple(self.model_args))
        object.__setattr__(self, "rows", tuple(parse_row(r) if isinstance(r, str) else tuple(r) for r in self.rows))
        if self.output is not None:
            object.__setattr__(self, "output", Path(self.output))
        if not self.rows:
            raise ValueError("--rows: give at least one row")
        if self.episodes < 2 or self.steps < 2:
            raise ValueError(f"--episodes and --steps: need at least 2 each, got {self.episodes} and {self.steps}")
        check_at_least_one(threads=self.threads)
