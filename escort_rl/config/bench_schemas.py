"""Schemas of the benchmark settings read without Hydra (``configs/bench/*.yaml``), applied with
:func:`escort_rl.config.checking.load_typed`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from omegaconf import MISSING

from escort_rl.config.files import check_filter_name
from escort_rl.config.params import MAX_LR
from escort_rl.config.params import param as _f


def _sub(cls) -> Any:
    return field(default_factory=cls)


@dataclass
class TrainBudgetConfig:
    iterations: int = _f(MISSING, ge=1)
    num_envs: int = _f(MISSING, ge=1)


@dataclass
class PlannerRowConfig:
    filter: str = _f(MISSING, check=check_filter_name)


@dataclass
class LearnedRowConfig:
    trainer: str = MISSING


@dataclass
class ClosedLoopBenchConfig:
    """``configs/bench/closed_loop.yaml`` (protocol (b) of the domain benchmark)."""

    episodes: int = _f(MISSING, ge=1)
    eval_seed: int = MISSING
    particles: int = _f(MISSING, ge=1)
    greedy: bool = MISSING
    # the trainer of the filter rows (a DeepSets policy on a filter's belief); None: config.yaml's
    trainer: Optional[str] = _f(None, choices=["ppo", "reinforce"])
    train: Dict[str, TrainBudgetConfig] = MISSING
    planners: Dict[str, PlannerRowConfig] = MISSING
    # scripted rows have the planner rows' shape: {filter: <a configs/filter/ name>}
    scripted: Dict[str, PlannerRowConfig] = MISSING
    learned: Dict[str, LearnedRowConfig] = MISSING
    # recurrent rows (no belief) have the learned rows' shape: {trainer: <a configs/trainer/ name>}
    recurrent: Dict[str, LearnedRowConfig] = MISSING


@dataclass
class SyntheticTargetConfig:
    """One GMM target: components are ``{mean, cov}`` or ``{mean, var, corr}`` with several forms
    each (see the yaml's header), so they stay untyped."""

    dim: int = _f(MISSING, ge=1)
    weights: List[float] = _f(MISSING, gt=0, le=1)
    components: List[Any] = MISSING


@dataclass
class GaussianInitialConfig:
    mean: float = MISSING
    std: float = _f(MISSING, gt=0)


@dataclass
class ScalabilityConfig:
    dims: List[int] = _f(MISSING, ge=1)
    structures: List[str] = _f(MISSING, choices=["block", "banded", "long_range", "sparse"])
    weights: List[float] = _f(MISSING, gt=0, le=1)
    positions: List[float] = MISSING
    std: List[float] = _f(MISSING, gt=0)
    block: Dict[str, Any] = MISSING
    banded: Dict[str, Any] = MISSING
    long_range: Dict[str, Any] = MISSING
    sparse: Dict[str, Any] = MISSING
    initial: GaussianInitialConfig = _sub(GaussianInitialConfig)


@dataclass
class SyntheticBenchConfig:
    """``configs/bench/synthetic.yaml`` (the paper's synthetic targets)."""

    targets: Dict[str, SyntheticTargetConfig] = MISSING
    initial: Dict[str, GaussianInitialConfig] = MISSING
    scalability: ScalabilityConfig = _sub(ScalabilityConfig)


@dataclass
class AtariTrainerConfig:
    """``configs/bench/atari.yaml``'s ``trainer``: A2C with DVRL's Atari settings."""

    num_envs: int = _f(MISSING, ge=1)
    rollout_steps: int = _f(MISSING, ge=1)
    updates_per_iteration: int = _f(MISSING, ge=1)
    lr: float = _f(MISSING, gt=0, lt=MAX_LR)
    belief_lr: Optional[float] = _f(None, gt=0, lt=MAX_LR)  # DVRL's and ESCORT-latent's rate; None: lr
    normalize_advantage: bool = True  # each window's advantages standardised (A2C and DVRL use them raw)
    rmsprop_alpha: float = _f(MISSING, ge=0, lt=1)
    rmsprop_eps: float = _f(MISSING, gt=0)
    gamma: float = _f(MISSING, gt=0, le=1)
    entropy_coef: float = _f(MISSING, ge=0)
    value_loss_coef: float = _f(MISSING, ge=0)
    encoding_loss_coef: float = _f(MISSING, ge=0)
    max_grad_norm: float = _f(MISSING, gt=0)
    reward_clip: bool = MISSING
    parallel_envs: bool = MISSING
    vectorized_envs: bool = False  # Atari only; optional so that configs/bench/minatar.yaml needs no key
    checkpoint_every: int = _f(MISSING, ge=1)
    keep_checkpoints: int = _f(MISSING, ge=1)


@dataclass
class AtariVRNNConfig:
    """The VRNN of DVRL and ESCORT-latent (``escort_rl.modules.DVRL``'s size arguments)."""

    num_particles: int = _f(MISSING, ge=1)
    latent_dim: int = _f(MISSING, ge=1)
    hidden: int = _f(MISSING, ge=1)
    encoding_dim: int = _f(MISSING, ge=1)
    summary: str = _f(MISSING, choices=["gru", "deepsets"])
    emission_min_std: float = _f(0.0, ge=0)  # a floor on the emission's learned std (0: none)


@dataclass
class AtariESCORTConfig:
    """ESCORT-latent: where it reads the likelihood and which ELBO it learns by (``ESCORTLatent``'s
    ``likelihood`` and ``elbo``), and its particle evolution (``ESCORTFilter``'s arguments)."""

    likelihood: str = _f(MISSING, choices=["pixels", "features"])
    elbo: str = _f(MISSING, choices=["proposal", "prior"])
    num_steps: int = _f(MISSING, ge=1)
    step_size: float = _f(MISSING, gt=0)
    lambda_corr: float = _f(MISSING, ge=0)
    lambda_temp: float = _f(MISSING, ge=0)
    n_proj: int = _f(MISSING, ge=1)
    proj_dim: int = _f(MISSING, ge=1)
    jitter: float = _f(MISSING, ge=0)
    temporal_ascent_steps: int = _f(MISSING, ge=0)
    projection_ascent_steps: int = _f(MISSING, ge=0)
    compile: bool = MISSING


@dataclass
class AtariGRUConfig:
    hidden: int = _f(MISSING, ge=1)


@dataclass
class AtariPaperConfig:
    """The paper's Table 4: ``table4[game][method] = [mean, s.e.]`` at ``frames``."""

    frames: int = _f(MISSING, ge=1)
    table4: Dict[str, Dict[str, List[float]]] = MISSING


@dataclass
class AtariBenchConfig:
    """``configs/bench/atari.yaml`` (Flickering Atari, the paper's Table 4) and
    ``configs/bench/minatar.yaml`` (Flickering MinAtar, which has no paper figures: ``paper: null``)."""

    trainer: AtariTrainerConfig = _sub(AtariTrainerConfig)
    vrnn: AtariVRNNConfig = _sub(AtariVRNNConfig)
    escort: AtariESCORTConfig = _sub(AtariESCORTConfig)
    gru: AtariGRUConfig = _sub(AtariGRUConfig)
    paper: Optional[AtariPaperConfig] = None
