"""Synthetic multi-modal targets of the benchmark (paper, appendix "Synthetic multi-modal
distributions"): Gaussian mixtures in 1D/2D/3D/5D/20D and the 5-mode scalability mixtures
at 1..200D, with the initial particle clouds.

All numbers live in ``configs/bench/synthetic.yaml`` (which values are the paper's and which are
ours is explained there); this module only turns them into :class:`GaussianMixture` objects and
checks that every covariance is symmetric positive definite.
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from escort_rl.metrics.moments import mixture_mean_and_covariance, safe_correlation

__all__ = [
    "GaussianMixture",
    "TARGET_NAMES",
    "SCALABILITY_DIMS",
    "SCALABILITY_STRUCTURES",
    "synthetic_config",
    "load_target",
    "initial_distribution",
    "scalability_target",
    "scalability_initial",
]

TARGET_NAMES = ("gmm1d", "gmm2d", "gmm3d", "gmm5d", "gmm20d")
SCALABILITY_DIMS = (1, 5, 20, 50, 100, 200)
SCALABILITY_STRUCTURES = ("block", "banded", "long_range", "sparse")

_LOG_2PI = math.log(2.0 * math.pi)


class GaussianMixture:
    r"""p(x) = Σ_k w_k N(x; μ_k, Σ_k).

    ``weights`` [K] (non-negative, summing to 1 within 1e-6; renormalised when off by more than
    1e-12, else kept exactly as given), ``means``
    [K, d], ``covariances`` [K, d, d], each symmetric positive definite (else ValueError naming the
    component). Parameters are stored in ``dtype`` (float64 by default); :meth:`log_prob` and
    :meth:`score` compute in the dtype and on the device of their input.
    """

    def __init__(self, weights, means, covariances, dtype: torch.dtype = torch.float64,
                 name: str | None = None):
        self.name = name
        w = torch.as_tensor(weights, dtype=dtype).detach().clone()
        mu = torch.as_tensor(means, dtype=dtype).detach().clone()
        cov = torch.as_tensor(covariances, dtype=dtype).detach().clone()
        if w.dim() != 1 or w.shape[0] < 1:
            raise ValueError(f"weights: expected [K], got shape {list(w.shape)}")
        k = w.shape[0]
        if mu.dim() != 2 or mu.shape[0] != k or mu.shape[1] < 1:
            raise ValueError(f"means: expected [K, d] with K = {k}, got shape {list(mu.shape)}")
        d = mu.shape[1]
        if cov.shape != (k, d, d):
            raise ValueError(f"covariances: expected [K, d, d] = {[k, d, d]}, got shape {list(cov.shape)}")
        for arg, t in (("weights", w), ("means", mu), ("covariances", cov)):
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{arg}: contains NaN or Inf")
        if bool((w < 0).any()):
            raise ValueError(f"weights: must be non-negative, got {w.tolist()}")
        total = float(w.sum())
        if abs(total - 1.0) > 1e-6:
            raise ValueError(f"weights: must sum to 1, got {total}")
        chol = torch.empty_like(cov)
        for i in range(k):
            c = cov[i]
            scale = float(c.abs().max())
            if not torch.allclose(c, c.T, rtol=0.0, atol=1e-10 * max(scale, 1.0)):
                raise ValueError(f"covariances[{i}]: component {i} is not symmetric "
                                 f"(max |Σ - Σᵀ| = {float((c - c.T).abs().max()):.3g})")
            c = 0.5 * (c + c.T)
            cov[i] = c
            lower, info = torch.linalg.cholesky_ex(c)
            min_eig = float(torch.linalg.eigvalsh(c).min())
            if int(info) != 0 or min_eig <= 0:
                raise ValueError(f"covariances[{i}]: component {i} is not positive definite "
                                 f"(smallest eigenvalue {min_eig:.3g})")
            chol[i] = lower
        self.weights = w if abs(total - 1.0) <= 1e-12 else w / w.sum()
        self.means = mu
        self.covariances = cov
        self.scale_tril = chol
        eye = torch.eye(d, dtype=dtype).expand(k, d, d)
        self._inv_tril = torch.linalg.solve_triangular(chol, eye, upper=False)  # L_k⁻¹
        self._half_log_det = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)  # [K]
        self._cache: dict[tuple, tuple[Tensor, ...]] = {}

    # -- shape ---------------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return int(self.means.shape[1])

    @property
    def num_components(self) -> int:
        return int(self.weights.shape[0])

    def __repr__(self) -> str:
        name = f"{self.name!r}, " if self.name else ""
        return f"GaussianMixture({name}K={self.num_components}, d={self.dim})"

    # -- density -------------------------------------------------------------------------------
    def _params(self, like: Tensor) -> tuple[Tensor, ...]:
        key = (like.dtype, like.device)
        if key not in self._cache:
            to = dict(dtype=like.dtype, device=like.device)
            self._cache[key] = (torch.log(self.weights).to(**to), self.means.to(**to),
                                self._inv_tril.to(**to), self._half_log_det.to(**to))
        return self._cache[key]

    def _check_x(self, x) -> Tensor:
        if not isinstance(x, Tensor):
            x = torch.as_tensor(x, dtype=self.means.dtype)
        if not x.is_floating_point():
            x = x.to(self.means.dtype)
        if x.dim() < 1 or x.shape[-1] != self.dim:
            raise ValueError(f"x: expected [..., d] with d = {self.dim}, got shape {list(x.shape)}")
        return x

    def component_log_prob(self, x) -> Tensor:
        r"""log w_k + log N(x; μ_k, Σ_k) for every component: ``x`` [..., d] -> [..., K].

        log N = −½‖L_k⁻¹(x − μ_k)‖² − Σ_i log (L_k)_ii − (d/2) log 2π, with Σ_k = L_k L_kᵀ.
        """
        x = self._check_x(x)
        log_w, mu, inv_tril, half_log_det = self._params(x)
        diff = x[..., None, :] - mu  # [..., K, d]
        z = torch.einsum("kij,...kj->...ki", inv_tril, diff)
        maha = (z * z).sum(-1)
        return log_w - 0.5 * maha - half_log_det - 0.5 * self.dim * _LOG_2PI

    def log_prob(self, x) -> Tensor:
        r"""log p(x) = logsumexp_k [log w_k + log N(x; μ_k, Σ_k)]; ``x`` [..., d] -> [...].
        Differentiable in ``x``."""
        return torch.logsumexp(self.component_log_prob(x), dim=-1)

    def score(self, x) -> Tensor:
        r"""∇_x log p(x) = −Σ_k r_k(x) Σ_k⁻¹ (x − μ_k), r_k the posterior responsibilities;
        ``x`` [..., d] -> [..., d] (analytic, no autograd)."""
        x = self._check_x(x)
        _, mu, inv_tril, _ = self._params(x)
        resp = torch.softmax(self.component_log_prob(x), dim=-1)  # [..., K]
        diff = x[..., None, :] - mu
        z = torch.einsum("kij,...kj->...ki", inv_tril, diff)          # L⁻¹ (x − μ)
        prec_diff = torch.einsum("kji,...kj->...ki", inv_tril, z)     # L⁻ᵀ L⁻¹ (x − μ)
        return -(resp[..., None] * prec_diff).sum(-2)

    # -- sampling ------------------------------------------------------------------------------
    def sample(self, n: int, generator: torch.Generator | None = None, return_labels: bool = False):
        """``n`` i.i.d. draws ``[n, d]`` (in the mixture's dtype, on CPU): a component index from
        the weights, then μ_k + L_k z with z ~ N(0, I), all from ``generator``. With
        ``return_labels`` also returns the component indices ``[n]`` (int64)."""
        n = int(n)
        if n < 0:
            raise ValueError(f"n: expected a non-negative sample count, got {n}")
        if n == 0:
            x = torch.empty(0, self.dim, dtype=self.means.dtype)
            labels = torch.empty(0, dtype=torch.long)
        else:
            labels = torch.multinomial(self.weights, n, replacement=True, generator=generator)
            z = torch.randn(n, self.dim, dtype=self.means.dtype, generator=generator)
            x = self.means[labels] + torch.einsum("nij,nj->ni", self.scale_tril[labels], z)
        return (x, labels) if return_labels else x

    # -- moments -------------------------------------------------------------------------------
    def mean(self) -> Tensor:
        """Mixture mean Σ_k w_k μ_k, [d]."""
        return mixture_mean_and_covariance(self.weights, self.means, self.covariances)[0]

    def covariance(self) -> Tensor:
        """Mixture covariance Σ_k w_k (Σ_k + μ_k μ_kᵀ) − μ μᵀ, [d, d]."""
        return mixture_mean_and_covariance(self.weights, self.means, self.covariances)[1]

    def correlation(self) -> Tensor:
        """Correlation matrix of the whole mixture (the metric's C_true), [d, d]."""
        return safe_correlation(self.covariance())

    def component_correlations(self) -> Tensor:
        """Per-component correlation matrices, [K, d, d]."""
        return safe_correlation(self.covariances)


# --------------------------------------------------------------------------------- config

def _config_path() -> Path:
    from escort_rl.config import config_dir

    return config_dir() / "bench" / "synthetic.yaml"


@lru_cache(maxsize=1)
def _load_yaml(path: str) -> dict:
    from omegaconf import OmegaConf

    from escort_rl.config.bench_schemas import SyntheticBenchConfig
    from escort_rl.config.checking import load_typed

    return OmegaConf.to_container(load_typed(path, SyntheticBenchConfig), resolve=True)


def synthetic_config() -> dict:
    """``configs/bench/synthetic.yaml``, checked against
    :class:`escort_rl.config.bench_schemas.SyntheticBenchConfig` (a fresh deep copy)."""
    import copy

    return copy.deepcopy(_load_yaml(str(_config_path())))


def _f(value) -> Tensor:
    """A float64 scalar tensor (so that torch.where keeps float64 precision)."""
    return torch.tensor(float(value), dtype=torch.float64)


def _vector(where: str, value: Any, d: int) -> Tensor:
    if isinstance(value, (int, float)):
        return torch.full((d,), float(value), dtype=torch.float64)
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.shape != (d,):
        raise ValueError(f"{where}: expected {d} numbers, got shape {list(t.shape)}")
    return t


def _mean_pattern(where: str, spec: dict, d: int) -> Tensor:
    j = torch.arange(d, dtype=torch.float64)
    kind = spec.get("pattern")
    if kind == "split":
        return torch.where(j < spec["at"], _f(spec["low"]), _f(spec["high"]))
    if kind == "alternate":
        return float(spec["value"]) * (1.0 - 2.0 * (j % 2))
    if kind == "linear":
        return torch.linspace(float(spec["start"]), float(spec["stop"]), d, dtype=torch.float64)
    if kind == "subspace":
        on = (j >= spec["first"] - 1) & (j <= spec["last"] - 1)
        return torch.where(on, _f(spec["value"]), _f(0.0))
    if kind == "sine":
        return float(spec["amplitude"]) * torch.sin(2 * math.pi * j / float(spec["period"])
                                                    + float(spec.get("phase", 0.0)))
    if kind == "quadratic":
        t = torch.linspace(-1.0, 1.0, d, dtype=torch.float64)
        return float(spec["scale"]) * t * t + float(spec.get("offset", 0.0))
    if kind == "constant":
        return torch.full((d,), float(spec["value"]), dtype=torch.float64)
    raise ValueError(f"{where}.pattern: unknown mean pattern {kind!r}")


def _corr_pattern(where: str, spec: dict, d: int) -> Tensor:
    i = torch.arange(d)
    lag = (i[:, None] - i[None, :]).abs().to(torch.float64)
    sign = 1.0 - 2.0 * ((i[:, None] + i[None, :]) % 2).to(torch.float64)  # (-1)^(i+j)
    eye = torch.eye(d, dtype=torch.float64)
    kind = spec.get("pattern")
    if kind == "block_alternating":
        b = int(spec["block_size"])
        same = (i[:, None] // b) == (i[None, :] // b)
        return torch.where(same, float(spec["rho"]) * sign, _f(0.0)) * (1 - eye) + eye
    if kind == "checkerboard":
        return float(spec["rho"]) * sign * (1 - eye) + eye
    if kind == "exponential_decay":
        return float(spec["base"]) ** lag
    if kind == "subspace_equicorrelation":
        on = (i >= spec["first"] - 1) & (i <= spec["last"] - 1)
        both = on[:, None] & on[None, :]
        return torch.where(both, _f(spec["rho"]), _f(0.0)) * (1 - eye) + eye
    if kind == "hierarchical":
        g = int(spec["group_size"])
        same = (i[:, None] // g) == (i[None, :] // g)
        r = torch.where(same, _f(spec["intra"]), _f(spec["inter"]))
        return r * (1 - eye) + eye
    if kind == "mirror_pairs":
        r = eye.clone()
        rho = float(spec["rho"])
        for a in range(d // 2):
            b = d - 1 - a
            r[a, b] = r[b, a] = rho if a % 2 == 0 else -rho
        return r
    raise ValueError(f"{where}.pattern: unknown correlation pattern {kind!r}")


def _corr(where: str, spec: Any, d: int) -> Tensor:
    if spec is None:
        return torch.eye(d, dtype=torch.float64)
    if isinstance(spec, dict) and "pairs" in spec:
        r = torch.eye(d, dtype=torch.float64)
        for a, b, rho in spec["pairs"]:
            if not (1 <= a <= d and 1 <= b <= d and a != b):
                raise ValueError(f"{where}.pairs: bad 1-based pair ({a}, {b}) for d = {d}")
            r[a - 1, b - 1] = r[b - 1, a - 1] = float(rho)
        return r
    if isinstance(spec, dict):
        return _corr_pattern(where, spec, d)
    r = torch.as_tensor(spec, dtype=torch.float64)
    if r.shape != (d, d):
        raise ValueError(f"{where}: expected a {d}×{d} matrix, got shape {list(r.shape)}")
    return r


def _component(where: str, spec: dict, d: int) -> tuple[Tensor, Tensor]:
    mean = spec["mean"]
    mu = _mean_pattern(f"{where}.mean", mean, d) if isinstance(mean, dict) else _vector(f"{where}.mean", mean, d)
    if "cov" in spec:
        cov = torch.as_tensor(spec["cov"], dtype=torch.float64)
        if cov.shape != (d, d):
            raise ValueError(f"{where}.cov: expected a {d}×{d} matrix, got shape {list(cov.shape)}")
    else:
        std = _vector(f"{where}.var", spec["var"], d).sqrt()
        cov = std[:, None] * _corr(f"{where}.corr", spec.get("corr"), d) * std[None, :]
    return mu, cov


def _build(name: str, spec: dict) -> GaussianMixture:
    d = int(spec["dim"])
    comps = [_component(f"targets.{name}.components[{k}]", c, d) for k, c in enumerate(spec["components"])]
    if len(spec["weights"]) != len(comps):
        raise ValueError(f"targets.{name}.weights: {len(spec['weights'])} weights for {len(comps)} components")
    means = torch.stack([m for m, _ in comps])
    covs = torch.stack([c for _, c in comps])
    try:
        return GaussianMixture(spec["weights"], means, covs, name=name)
    except ValueError as err:
        raise ValueError(f"targets.{name}: {err}") from None


def load_target(name: str) -> GaussianMixture:
    """The synthetic target ``name`` (one of ``gmm1d, gmm2d, gmm3d, gmm5d, gmm20d``), float64."""
    targets = synthetic_config()["targets"]
    if name not in targets:
        raise ValueError(f"name: unknown synthetic target {name!r}; expected one of {sorted(targets)}")
    return _build(name, targets[name])


def _isotropic(name: str, d: int, spec: dict) -> GaussianMixture:
    mean = _vector(f"{name}.mean", spec["mean"], d)
    std = float(spec["std"])
    return GaussianMixture([1.0], mean[None], (std * std * torch.eye(d, dtype=torch.float64))[None],
                           name=f"{name}/initial")


def initial_distribution(name: str) -> GaussianMixture:
    """The initial particle cloud of target ``name``: N(mean·1, std² I) from the config's
    ``initial`` section (a one-component :class:`GaussianMixture`; the paper gives none)."""
    cfg = synthetic_config()
    if name not in cfg["initial"]:
        raise ValueError(f"name: no initial distribution for {name!r}; expected one of {sorted(cfg['initial'])}")
    return _isotropic(name, int(cfg["targets"][name]["dim"]), cfg["initial"][name])


# --------------------------------------------------------------------------------- scalability

def _scal_corr(structure: str, k: int, d: int, cfg: dict, gen: torch.Generator) -> Tensor:
    eye = torch.eye(d, dtype=torch.float64)
    if d == 1:
        return eye
    i = torch.arange(d)
    if structure == "block":
        b = int(cfg["block"]["block_size"])
        rho = float(cfg["block"]["rho"][k])
        same = (i[:, None] // b) == (i[None, :] // b)
        return torch.where(same, _f(rho), _f(0.0)) * (1 - eye) + eye
    if structure == "banded":
        bw = int(cfg["banded"]["bandwidth"])
        r = float(cfg["banded"]["r"][k])
        lag = (i[:, None] - i[None, :]).abs().to(torch.float64)
        return (r ** lag) * (1.0 - lag / (bw + 1)).clamp_min(0.0)
    if structure == "long_range":
        rho = float(cfg["long_range"]["rho"][k])
        pairing = cfg["long_range"]["pairing"][k]
        out = eye.clone()
        half = d // 2
        for a in range(half):
            if pairing == "mirror":
                b = d - 1 - a
            elif pairing == "half_shift":
                b = a + half
            else:
                raise ValueError(f"scalability.long_range.pairing[{k}]: unknown pairing {pairing!r}")
            out[a, b] = out[b, a] = rho if a % 2 == 0 else -rho
        return out
    if structure == "sparse":
        sp = cfg["sparse"]
        lo, hi = float(sp["rho_min"]), float(sp["rho_max"])
        out = eye.clone()
        for _ in range(int(sp["matchings"])):
            perm = torch.randperm(d, generator=gen)
            for a, b in zip(perm[0::2].tolist(), perm[1::2].tolist()):
                u = torch.rand(2, generator=gen, dtype=torch.float64)
                rho = (lo + (hi - lo) * float(u[0])) * (1.0 if float(u[1]) < 0.5 else -1.0)
                out[a, b] = out[b, a] = rho
        return out
    raise ValueError(f"correlation: expected one of {list(SCALABILITY_STRUCTURES)}, got {structure!r}")


def scalability_target(dim: int, correlation: str, generator_seed: int = 0) -> GaussianMixture:
    """The 5-mode scalability mixture in ``dim`` dimensions with correlation structure
    ``correlation`` in ``block, banded, long_range, sparse`` (config key ``scalability``; the
    construction is documented there). ``generator_seed`` seeds the per-coordinate assignment of
    modes to positions and the sparse pattern; the same arguments always give the same target."""
    dim = int(dim)
    if dim < 1:
        raise ValueError(f"dim: expected a positive dimension, got {dim}")
    if correlation not in SCALABILITY_STRUCTURES:
        raise ValueError(f"correlation: expected one of {list(SCALABILITY_STRUCTURES)}, got {correlation!r}")
    cfg = synthetic_config()["scalability"]
    gen = torch.Generator().manual_seed(int(generator_seed))
    positions = torch.as_tensor(cfg["positions"], dtype=torch.float64)
    k = len(cfg["weights"])
    if positions.shape[0] != k or len(cfg["std"]) != k:
        raise ValueError("scalability: weights, positions and std must have one entry per mode")
    means = torch.stack([positions[torch.randperm(k, generator=gen)] for _ in range(dim)], dim=1)  # [K, d]
    covs = []
    for m in range(k):
        r = _scal_corr(correlation, m, dim, cfg, gen)
        s = float(cfg["std"][m])
        covs.append(s * s * r)
    name = f"scalability/{correlation}/{dim}d/seed{int(generator_seed)}"
    try:
        return GaussianMixture(cfg["weights"], means, torch.stack(covs), name=name)
    except ValueError as err:
        raise ValueError(f"{name}: {err}") from None


def scalability_initial(dim: int) -> GaussianMixture:
    """Initial particle cloud of the scalability targets: N(mean·1, std² I) from
    ``scalability.initial``."""
    dim = int(dim)
    if dim < 1:
        raise ValueError(f"dim: expected a positive dimension, got {dim}")
    return _isotropic("scalability", dim, synthetic_config()["scalability"]["initial"])
