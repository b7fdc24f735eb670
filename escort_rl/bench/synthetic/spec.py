"""Every setting of one ``bench synthetic`` run in a frozen :class:`SyntheticSpec` and of one
``bench scaling`` run in a :class:`ScalingSpec` (the same settings, over the 5-mode targets'
dimensions and structures instead of Table 2's targets); each with ``full()`` (the command's
defaults) and ``quick()`` (``--quick``). The field defaults are the full runs; this module is the
only place that states a default."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from escort_rl.bench.methods import SCALING_METHODS, SYNTHETIC_METHODS, check_at_least_one, check_choices
from escort_rl.bench.synthetic.cells import INITS, TRACKING_METHODS
from escort_rl.bench.synthetic.tracking import STEPS
from escort_rl.bench.targets import SCALABILITY_STRUCTURES

SYNTHETIC_TARGETS = ("gmm1d", "gmm2d", "gmm3d", "gmm5d", "gmm20d")
SCALING_DIMS = (1, 5, 20, 50, 100, 200)
PROTOCOLS = ("static", "tracking")
"""``static``: fit a fixed target from a start (``--init``); ``tracking``: follow a latent state
through the target-shaped likelihood (:mod:`escort_rl.bench.synthetic.tracking`)."""
FIT_STEPS = {"static": 500, "tracking": 50}
"""The default ``num_steps`` per protocol: of the fit, or per update."""
SYNTHETIC_OUTPUT = "outputs/bench/synthetic"
"""``bench synthetic``'s ``--output``."""
SCALING_OUTPUT = "outputs/bench/scaling"
"""``bench scaling``'s ``--output``."""

_QUICK = dict(seeds=2, particles=100, num_steps=30, steps=3)
"""What ``--quick`` changes on both grids (besides their axes)."""


@dataclass(frozen=True)
class GridSpec:
    """The settings :class:`SyntheticSpec` and :class:`ScalingSpec` share: the rows, the protocol
    and how the cells run. ``methods`` and ``num_steps`` left ``None`` become the protocol's
    defaults; the simple checks run on construction, each naming its command-line option."""

    methods: tuple | None = None
    """The rows (``None``: the bench's default methods, or the tracking protocol's)."""
    protocol: str = "static"
    """One of :data:`PROTOCOLS`."""
    seeds: int = 30
    """Seeds ``0 .. seeds-1``."""
    particles: int = 1000
    """N of every method."""
    num_steps: int | None = None
    """Iterations of ESCORT and SVGD: of the fit, or per update (``None``: :data:`FIT_STEPS`)."""
    steps: int = STEPS
    """Steps of the tracking protocol."""
    bandwidth_scale: float = 1.0
    """Multiplies ESCORT's and SVGD's median-heuristic bandwidth."""
    filter_kwargs: tuple = ()
    """``((key, value), ...)``: more ESCORT/SVGD arguments (a row's own setting wins)."""
    init: str = "cloud"
    """The static protocol's start, one of :data:`~escort_rl.bench.synthetic.cells.INITS`."""
    init_scale: float = 1.0
    """Multiplies the start's spread, for every method but the oracle."""
    threads: int = 1
    """Torch threads in each cell."""
    seeds_per_cell: int | None = None
    """Seeds per cell (``None``: all seeds of a row in one cell)."""
    output: Path | None = None
    """The results folder: plots, and the saved cells in ``<output>/cells``; ``None``: neither."""

    default_methods = SYNTHETIC_METHODS
    """The rows of the static protocol when ``methods`` is not given."""
    known_methods = SYNTHETIC_METHODS
    """The rows the static protocol can run."""

    @classmethod
    def full(cls, **changes):
        """The command's defaults, with ``changes`` on top."""
        return cls(**changes)

    @classmethod
    def quick(cls, **changes):
        """``--quick``, with ``changes`` (the flags given explicitly) on top."""
        return cls(**{**_QUICK, **cls.quick_axes(), **changes})

    @classmethod
    def quick_axes(cls) -> dict:
        return {}

    def __post_init__(self) -> None:
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"--protocol: expected one of {', '.join(PROTOCOLS)}, got {self.protocol!r}")
        tracking = self.protocol == "tracking"
        methods = self.methods if self.methods is not None else (
            TRACKING_METHODS if tracking else self.default_methods)
        object.__setattr__(self, "methods", tuple(methods))
        if self.num_steps is None:
            object.__setattr__(self, "num_steps", FIT_STEPS[self.protocol])
        items = self.filter_kwargs.items() if isinstance(self.filter_kwargs, dict) else self.filter_kwargs
        object.__setattr__(self, "filter_kwargs", tuple(tuple(kv) for kv in items))
        if self.output is not None:
            object.__setattr__(self, "output", Path(self.output))
        check_choices("--methods", self.methods, TRACKING_METHODS if tracking else self.known_methods)
        if self.init not in INITS:
            raise ValueError(f"--init: expected one of {', '.join(INITS)}, got {self.init!r}")
        check_at_least_one(seeds=self.seeds, particles=self.particles, num_steps=self.num_steps, steps=self.steps,
                           threads=self.threads, seeds_per_cell=self.seeds_per_cell)
        for name, value in (("bandwidth-scale", self.bandwidth_scale), ("init-scale", self.init_scale)):
            if not value > 0:
                raise ValueError(f"--{name}: must be positive, got {value}")

    def filter_arguments(self) -> dict:
        """The ESCORT/SVGD arguments of every cell: ``bandwidth_scale`` (unless 1), then
        ``filter_kwargs``."""
        out = {"bandwidth_scale": self.bandwidth_scale} if self.bandwidth_scale != 1.0 else {}
        return {**out, **dict(self.filter_kwargs)}


@dataclass(frozen=True)
class SyntheticSpec(GridSpec):
    """One run of Table 2's targets (:func:`~escort_rl.bench.synthetic.run.run_synthetic`).

    Examples:
        >>> SyntheticSpec().seeds, SyntheticSpec.quick().seeds, SyntheticSpec.quick().targets
        (30, 2, ('gmm1d', 'gmm2d', 'gmm3d'))
        >>> SyntheticSpec(protocol="tracking").num_steps, SyntheticSpec().num_steps
        (50, 500)
        >>> SyntheticSpec(particles=0)
        Traceback (most recent call last):
        ...
        ValueError: --particles: must be a positive int, got 0
    """

    targets: tuple = SYNTHETIC_TARGETS
    """The GMM targets (names of ``configs/bench/synthetic.yaml``, checked when the run starts)."""

    @classmethod
    def quick_axes(cls) -> dict:
        return dict(targets=("gmm1d", "gmm2d", "gmm3d"))

    def __post_init__(self) -> None:
        object.__setattr__(self, "targets", tuple(self.targets))
        super().__post_init__()


@dataclass(frozen=True)
class ScalingSpec(GridSpec):
    """One run of the 5-mode scalability targets against the dimension
    (:func:`~escort_rl.bench.synthetic.run.run_scaling`).

    Examples:
        >>> ScalingSpec().seeds, ScalingSpec.quick().dims, ScalingSpec.quick().structures
        (5, (1, 5), ('block',))
        >>> ScalingSpec(structures=["nope"])
        Traceback (most recent call last):
        ...
        ValueError: --structures: unknown structure 'nope'; choose from block, banded, long_range, sparse
    """

    seeds: int = 5
    dims: tuple = SCALING_DIMS
    """The dimensions."""
    structures: tuple = SCALABILITY_STRUCTURES
    """The correlation structures of the targets (a 1-D target has only the first)."""

    default_methods = SCALING_METHODS
    known_methods = SCALING_METHODS + tuple(m for m in SYNTHETIC_METHODS if m not in SCALING_METHODS)

    @classmethod
    def quick_axes(cls) -> dict:
        return dict(dims=(1, 5), structures=("block",))

    def __post_init__(self) -> None:
        object.__setattr__(self, "dims", tuple(int(d) for d in self.dims))
        object.__setattr__(self, "structures", tuple(self.structures))
        super().__post_init__()
        check_at_least_one(dims=list(self.dims))
        check_choices("--structures", self.structures, SCALABILITY_STRUCTURES, "structure")
