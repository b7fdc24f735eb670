"""Kidnapped Robot 20D (paper, Appendix "Domains: Kidnapped Robot Problem").

State ``s`` (``state_dim = 20``), in the paper's order:

    index  0, 1    position (x, y) in the map [0, map_size]²   (``position_dims = (0, 1)``)
    index  2       heading θ (radians; kept unwrapped, see below)
    index  3, 4    speed v and steering s
    index  5..9    sensor calibration c = (range bias, range scale error, boresight offset,
                   similarity gain error, similarity bias)
    index 10..19   feature descriptor f (unit norm in the noise-free dynamics)

Actions ``a ∈ {0, 1, 2, 3}`` (``n_actions = 4``): 0 turns by ``+turn_rate``, 1 by ``-turn_rate``
(paper: ±0.1), 2 keeps the heading, 3 stays in place (no displacement). The paper lists "actions
modify orientation (Δθ = ±0.1) or maintain position"; we read "maintain" both ways (keep the heading
and move, or stay put) and keep both.

Dynamics (additive correlated Gaussian noise ``η ~ N(0, Σ)``, ``Σ`` from the paper's correlations):

    x' = clip(x + m_a·v cos θ Δt, 0, map_size) + η_x      (m_a = 0 for "stay", else 1)
    y' = clip(y + m_a·v sin θ Δt, 0, map_size) + η_y
    θ' = θ + Δθ_a + η_θ                                  (paper, as written)
    v' = v + κ (v_nom − v) + η_v,   s' = (1 − κ) s + η_s (our choice: mean-reverting)
    c' = c + η_c                                         (sensor drift: a random walk)
    f' = f / ‖f‖ + η_f                                   (the unit-norm constraint, in the mean)

θ is not wrapped to [0, 2π): the model only uses cos θ and sin θ, and wrapping would make the
additive-Gaussian transition density jump by 2π. ``f`` lies on the unit sphere up to one step of
noise; the observation uses ``f / ‖f‖``.

Map: ``C`` clusters (default 4, a 2×2 grid 10 apart) that repeat one template of ``K`` landmarks
(default 4: two houses, a shop, a warehouse). Landmark ``(k, c)`` (slot ``k`` of cluster ``c``) sits
at ``centre_c + offset_k`` and has the descriptor ``d_kc = normalize(prototype[type_k] + σ_d ε)``
(paper: σ = 0.1), drawn once from ``map_seed``, so copies look alike but not identical.

Observation (``obs_dim = 3K``): for each template slot ``k``, ``[visible, distance, similarity]``;
an invisible slot is ``[0, 0, 0]``. Slots are per *template* landmark, not per landmark: the sensor
reports "a house of this kind at distance r", never which cluster it belongs to, which is the
perceptual aliasing the domain is about (one slot per landmark would hand the filter the landmark's
identity). Generative law, per slot:

- each copy ``c`` is detected independently with probability
  ``p_kc = p_det · σ((R − r_kc)/τ_r) · σ((cos Δ_kc − cos(fov/2)) / (sin(fov/2) τ_θ))``:
  a smooth version of "within range R (paper: 5) and inside the field of view (paper: 90°)", with
  ``r_kc`` the distance and ``Δ_kc`` the bearing relative to the boresight ``θ + c_2``;
- the slot reports the first detected copy in cluster order (at the default spacing at most one
  copy is ever in range, so the order does not matter); if none is detected it is invisible;
- the reported copy gives ``distance = (1 + c_1) r_kc + c_0 + σ_r ε`` and
  ``similarity = (1 + c_3) ⟨f/‖f‖, d_kc⟩ + c_4 + σ_s ε``.

``observation_log_prob`` is the exact log-density of this law (w.r.t. counting measure on the mask
times Lebesgue measure on the visible entries; the zeros of an invisible slot are ignored):
``Σ_k [visible_k] logsumexp_c(log p_kc + Σ_{c'<c} log(1 − p_kc') + log N(dist) + log N(sim))
+ [not visible_k] Σ_c log(1 − p_kc)``. Every term is finite (``p_det < 1``), so it never returns
NaN or -inf, and it is differentiable in the whole state (visibility included, through the sigmoids).
A slot counts as visible when its first entry is > 0.5.

Reward −1 per step (paper). ``is_terminal`` is always False: the paper ends an episode on a
belief-convergence criterion or a step limit, and a belief is not a function of the state; the
step limit (``max_steps``) lives in ``configs/env/kidnapped20d.yaml``.

The paper's correlations are not positive semi-definite (smallest eigenvalue −0.414 in the pose block
and −0.467 in the calibration/feature block); the model uses the nearest correlation matrix (Higham
2002), raised to a positive-definite one. :func:`describe_correlations` prints both.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Dict, List

import torch
import torch.nn.functional as F
from torch import Tensor

from escort_rl.config.errors import ConfigError
from escort_rl.config.params import HasParams, build_params, param
from escort_rl.models.gaussian import (
    AdditiveGaussianTransition,
    GaussianNoise,
    correlation_report,
    make_positive_definite,
    nearest_correlation_matrix,
)

N_CALIBRATION = 5
N_FEATURES = 10
STATE_NAMES: tuple[str, ...] = (
    ("x", "y", "theta", "v", "steer")
    + tuple(f"c{i + 1}" for i in range(N_CALIBRATION))
    + tuple(f"f{i + 1}" for i in range(N_FEATURES))
)

# state indices
X, Y, THETA, V, STEER = 0, 1, 2, 3, 4
CAL = slice(5, 5 + N_CALIBRATION)
FEAT = slice(10, 10 + N_FEATURES)
_EPS = 1e-6  # smooths ‖·‖ at 0 so that norms and their gradients stay finite


def paper_correlations(
    rho_position_heading: float = 0.6,
    rho_position_velocity: float = 0.8,
    rho_calibration: float = 0.4,
    rho_calibration_feature: float = 0.3,
) -> Tensor:
    """The process-noise correlation matrix as the paper states it (``[20, 20]`` float64).

    ρ(x, θ) = ρ(y, θ) = 0.6 ("position and orientation"), ρ(x, v) = ρ(y, v) = 0.8
    ("position-velocity"), ρ(c_i, c_j) = 0.4 for i ≠ j ("calibration internal"), ρ(c_i, f_k) = 0.3
    for all i, k ("calibration influences feature descriptors"); every other pair 0. Not PSD at the
    paper's values (smallest eigenvalue −0.414 in the pose block, −0.467 in the calibration/feature
    block).
    """
    c = torch.eye(20, dtype=torch.float64)

    def put(i: int, j: int, r: float) -> None:
        c[i, j] = c[j, i] = r

    for p in (X, Y):
        put(p, THETA, rho_position_heading)
        put(p, V, rho_position_velocity)
    cal = range(CAL.start, CAL.stop)
    for i in cal:
        for j in cal:
            if i < j:
                put(i, j, rho_calibration)
        for k in range(FEAT.start, FEAT.stop):
            put(i, k, rho_calibration_feature)
    return c


def _points(name: str, value: Sequence[Sequence[float]]) -> Tensor:
    """``KidnappedRobot20D.<name>`` as a ``[n, 2]`` float64 tensor; raises unless it is a non-empty
    list of finite (x, y) pairs."""
    try:
        t = torch.tensor([[float(v) for v in row] for row in value], dtype=torch.float64)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"KidnappedRobot20D.{name}: expected a list of (x, y) pairs ({err})") from None
    if t.ndim != 2 or t.shape[0] == 0 or t.shape[1] != 2 or not torch.isfinite(t).all():
        raise ConfigError(f"KidnappedRobot20D.{name}: expected a non-empty list of finite (x, y) pairs, "
                          f"got shape {tuple(t.shape)}")
    return t


def _descriptor(name: str, value: Sequence[float]) -> Tensor:
    """``KidnappedRobot20D.<name>`` normalised, as a ``[10]`` float64 tensor; raises unless it is
    ten finite numbers, not all zero."""
    try:
        t = torch.tensor([float(v) for v in value], dtype=torch.float64)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"KidnappedRobot20D.{name}: expected {N_FEATURES} numbers ({err})") from None
    if t.shape != (N_FEATURES,) or not torch.isfinite(t).all() or t.norm() < 1e-8:
        raise ConfigError(f"KidnappedRobot20D.{name}: expected {N_FEATURES} finite numbers, not all zero, "
                          f"got {value!r}")
    return t / t.norm()


def _prototypes(cluster_types: Sequence[str], type_prototypes: Mapping[str, Sequence[float]],
                n_slots: int) -> dict[str, Tensor]:
    """The normalised descriptor prototype of each type; raises unless ``cluster_types`` names one
    known type per cluster offset and ``type_prototypes`` is a non-empty mapping."""
    if len(cluster_types) != n_slots:
        raise ConfigError(f"KidnappedRobot20D.cluster_types: expected one type name per cluster offset "
                          f"({n_slots}), got {list(cluster_types)!r}")
    if not type_prototypes:
        raise ConfigError(f"KidnappedRobot20D.type_prototypes: expected a mapping type name -> "
                          f"{N_FEATURES} numbers, got {type_prototypes!r}")
    protos = {str(k): _descriptor(f"type_prototypes[{k}]", v) for k, v in type_prototypes.items()}
    for t in cluster_types:
        if t not in protos:
            raise ConfigError(f"KidnappedRobot20D.cluster_types: unknown type '{t}'; "
                              f"type_prototypes has {sorted(protos)}")
    return protos


@dataclass(frozen=True)
class KidnappedRobot20DParams:
    """:class:`KidnappedRobot20D`'s parameters (paper, Appendix "Domains: Kidnapped Robot Problem").
    Values the paper gives are marked (paper); the others are choices the paper leaves open, with
    the reason.

    Attributes:
        map_size: side of the square map (paper: 20, positions in ``[0, 20]²``).
        cluster_centres: ``C`` cluster centres ``(x, y)``. Four copies of one cluster on a 2×2 grid,
            10 apart: twice the sensor range, so at most one copy of a landmark is ever in range, and
            every observation fits four places (aliasing).
        cluster_offsets: ``K`` landmark offsets ``(dx, dy)`` of the repeated cluster template: four
            landmarks within 2.3 of the centre, in an irregular layout so that the heading can be
            read off the cluster once it is seen.
        cluster_types: the type of each template landmark (``K`` names, keys of ``type_prototypes``;
            paper: houses, shops and warehouses). Two houses, so that the template also aliases
            within itself.
        type_prototypes: type name -> 10-D descriptor prototype (normalised here), chosen so that
            their cosine similarity with the reference descriptor is about 0.8, 0.5 and 0.2: the
            types are told apart by similarity, while copies of one landmark differ only by the
            perturbation below.
        descriptor_perturbation_std: std of the per-landmark descriptor perturbation (paper: 0.1,
            "similar feature vectors with small perturbations").
        map_seed: seed of the descriptor perturbations; it fixes them, so every run sees the same map.
        reference_descriptor: the centre of the start distribution of the robot's own feature
            descriptor ``f`` (normalised here): the robot was kidnapped, its appearance model was not.
        sensor_range: (paper: 5).
        field_of_view_deg: (paper: 90), in (0, 360).
        range_softness, fov_softness: τ_r and τ_θ (radians), the widths of the soft range and
            field-of-view edges. Visibility is a smooth gate so that ``observation_log_prob`` is
            differentiable in the state: 0.2 units and 0.05 rad (3 degrees), narrow next to the range
            and the 90 degree cone, and wide enough that scores near the edges stay moderate.
        detection_prob: p_det, the detection probability well inside the cone, in (0, 1): a landmark
            there is missed 5% of the time. Sensors miss, and p < 1 keeps the log-likelihood of "not
            seen" finite everywhere (1 would make a missed detection impossible, log 0).
        distance_noise_std, similarity_noise_std: σ_r and σ_s of the two measurements. The paper
            gives none: 0.2 units of range (4% of the range) and 0.05 of similarity, a little under
            the copy-to-copy spread of similarities (~0.08), so one look barely tells copies apart
            and the belief stays multi-modal for a while.
        turn_rate: heading change of the turn actions (paper: ±0.1).
        dt: time step Δt. The paper gives none for this domain: Light-Dark's 0.1.
        nominal_speed: v_nom. 2 units/s at dt 0.1 is 0.2 units a step, and a turning circle of
            radius 2 at 0.1 rad a step: a cluster (radius ~2.3) is crossed in about 20 steps.
        velocity_reversion: κ in [0, 1], the pull of v to v_nom and of s to 0 per step. The paper
            gives dynamics for x, y and θ only; speed and steering relax to (nominal_speed, 0) by 10%
            a step, so that they stay bounded over long episodes; calibration is a random walk
            (sensor drift) and f is renormalised to unit norm.
        position_noise_std, heading_noise_std, velocity_noise_std, steering_noise_std,
            calibration_noise_std, feature_noise_std: per-step process-noise stds. The paper gives
            the correlations but not the scales: small next to the 0.2-unit motion and the 0.1-rad
            turns, and a slow drift of calibration and features.
        rho_position_heading, rho_position_velocity, rho_calibration, rho_calibration_feature:
            the paper's correlations (paper: 0.6, 0.8, 0.4, 0.3), each in (-1, 1). As stated they
            are not PSD (smallest eigenvalue -0.467), so the model uses the nearest correlation
            matrix (Higham 2002): see :func:`describe_correlations`.
        start_speed_std, start_steering_std, start_calibration_std, start_feature_std: spread of
            the start distribution around (v_nom, 0, 0, reference_descriptor). The start position is
            uniform over the map and the heading uniform in [0, 2π) (paper: kidnapped), for the true
            state and the prior alike; a calibration error of 0.05 is 0.25 units at the sensor range.
    """

    map_size: float = param(20.0, gt=0)
    cluster_centres: List[List[float]] = param([[5.0, 5.0], [15.0, 5.0], [5.0, 15.0], [15.0, 15.0]])
    cluster_offsets: List[List[float]] = param([[-2.0, -1.0], [0.5, -1.5], [1.5, 1.0], [-1.0, 1.5]])
    cluster_types: List[str] = param(["house", "house", "shop", "warehouse"])
    type_prototypes: Dict[str, List[float]] = param({
        "house": [0.8, 0.6, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        "shop": [0.5, 0.3, 0.8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        "warehouse": [0.2, 0.3, 0.4, 0.8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    })
    descriptor_perturbation_std: float = param(0.1, ge=0)
    map_seed: int = param(0)
    reference_descriptor: List[float] = param([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    sensor_range: float = param(5.0, gt=0)
    field_of_view_deg: float = param(90.0, gt=0, lt=360)
    range_softness: float = param(0.2, gt=0)
    fov_softness: float = param(0.05, gt=0)
    detection_prob: float = param(0.95, gt=0, lt=1)
    distance_noise_std: float = param(0.2, gt=0)
    similarity_noise_std: float = param(0.05, gt=0)
    turn_rate: float = param(0.1, ge=0)
    dt: float = param(0.1, gt=0)
    nominal_speed: float = param(2.0, ge=0)
    velocity_reversion: float = param(0.1, ge=0, le=1)
    position_noise_std: float = param(0.02, gt=0)
    heading_noise_std: float = param(0.02, gt=0)
    velocity_noise_std: float = param(0.05, gt=0)
    steering_noise_std: float = param(0.02, gt=0)
    calibration_noise_std: float = param(0.005, gt=0)
    feature_noise_std: float = param(0.01, gt=0)
    rho_position_heading: float = param(0.6, gt=-1, lt=1)
    rho_position_velocity: float = param(0.8, gt=-1, lt=1)
    rho_calibration: float = param(0.4, gt=-1, lt=1)
    rho_calibration_feature: float = param(0.3, gt=-1, lt=1)
    start_speed_std: float = param(0.1, ge=0)
    start_steering_std: float = param(0.05, ge=0)
    start_calibration_std: float = param(0.05, ge=0)
    start_feature_std: float = param(0.1, ge=0)


class KidnappedRobot20D(HasParams, AdditiveGaussianTransition):
    """The 20-D Kidnapped Robot localisation POMDP. All tensors are float32 on ``device``.

    Takes :class:`KidnappedRobot20DParams` (or its fields as keyword arguments; lists may be tuples
    or OmegaConf lists) and ``device``, where the model's constant tensors live.

    Attributes a filter or benchmark uses: ``position_dims = (0, 1)`` (the position error is
    ``‖E_b[s[..., 0:2]] − s_true[..., 0:2]‖``), ``n_pos = 2``, :meth:`position`,
    ``landmark_positions`` ``[K, C, 2]``, ``landmark_descriptors`` ``[K, C, 10]``, ``n_slots = K``,
    ``n_clusters = C``, ``correlation`` (float64, used) and ``noise_covariance``.
    """

    Params = KidnappedRobot20DParams

    state_dim = 20
    n_actions = 4
    n_pos = 2
    position_dims: tuple[int, ...] = (0, 1)
    velocity_dims: tuple[int, ...] = (3,)  # the speed v
    state_names = STATE_NAMES

    def __init__(self, params: KidnappedRobot20DParams | None = None, *,
                 device: torch.device | str | None = None, **kwargs) -> None:
        self.params = p = build_params(KidnappedRobot20DParams, params, kwargs,
                                       owner=type(self).__name__)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self._set_scalars(p)
        self._build_map(p)
        self._build_process_noise(p)
        # actions: heading change and whether the robot moves
        self._dtheta = torch.tensor([self.turn_rate, -self.turn_rate, 0.0, 0.0], device=self.device)
        self._moves = torch.tensor([1.0, 1.0, 1.0, 0.0], device=self.device)

    def _set_scalars(self, p: KidnappedRobot20DParams) -> None:
        """The scalar parameters as floats (an int in a config reads as the float it stands for),
        and the constants of the visibility gate."""
        for name in ("map_size", "sensor_range", "field_of_view_deg", "range_softness", "fov_softness",
                     "detection_prob", "distance_noise_std", "similarity_noise_std", "turn_rate", "dt",
                     "nominal_speed", "velocity_reversion", "start_speed_std", "start_steering_std",
                     "start_calibration_std", "start_feature_std"):
            setattr(self, name, float(getattr(p, name)))
        half = math.radians(self.field_of_view_deg) / 2
        self._cos_half_fov = math.cos(half)
        self._fov_scale = math.sin(half) * self.fov_softness  # cos Δ − cos(fov/2) ≈ sin(fov/2)·(fov/2 − |Δ|)
        self._log_p_det = math.log(self.detection_prob)

    def _build_map(self, p: KidnappedRobot20DParams) -> None:
        """Landmark ``(k, c)`` at ``centre_c + offset_k``, descriptor ``normalize(prototype + σ ε)``."""
        centres = _points("cluster_centres", p.cluster_centres)  # [C, 2]
        offsets = _points("cluster_offsets", p.cluster_offsets)  # [K, 2]
        types = [str(t) for t in p.cluster_types]
        protos = _prototypes(types, p.type_prototypes, offsets.shape[0])
        reference = _descriptor("reference_descriptor", p.reference_descriptor)

        self.n_slots, self.n_clusters = offsets.shape[0], centres.shape[0]
        self.obs_dim = 3 * self.n_slots
        self.cluster_types = tuple(types)
        g = torch.Generator().manual_seed(int(p.map_seed))
        positions = offsets[:, None, :] + centres[None, :, :]  # [K, C, 2]
        proto = torch.stack([protos[t] for t in types])  # [K, 10]
        noise = torch.randn(self.n_slots, self.n_clusters, N_FEATURES, generator=g, dtype=torch.float64)
        desc = proto[:, None, :] + float(p.descriptor_perturbation_std) * noise
        desc = desc / desc.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        self.landmark_positions = positions.to(torch.float32).to(self.device)
        self.landmark_descriptors = desc.to(torch.float32).to(self.device)
        self.reference_descriptor = reference.to(torch.float32).to(self.device)

    def _build_process_noise(self, p: KidnappedRobot20DParams) -> None:
        """The paper's correlations, the nearest correlation matrix used instead, and ``Σ``."""
        self.paper_correlation = paper_correlations(
            p.rho_position_heading, p.rho_position_velocity, p.rho_calibration, p.rho_calibration_feature)
        self.correlation = make_positive_definite(nearest_correlation_matrix(self.paper_correlation))
        stds = torch.tensor(
            [p.position_noise_std] * 2 + [p.heading_noise_std, p.velocity_noise_std, p.steering_noise_std]
            + [p.calibration_noise_std] * N_CALIBRATION + [p.feature_noise_std] * N_FEATURES,
            dtype=torch.float64,
        )
        cov = self.correlation * stds[:, None] * stds[None, :]
        self.noise_covariance = cov.to(torch.float32).to(self.device)
        self._process = GaussianNoise(torch.linalg.cholesky(cov).to(torch.float32).to(self.device))

    # ------------------------------------------------------------------ helpers
    def position(self, s: Tensor) -> Tensor:
        """The position part of a state: ``[*S, 20]`` -> ``[*S, 2]``."""
        return s[..., : self.n_pos]

    @staticmethod
    def unit_features(s: Tensor) -> Tensor:
        """``f / ‖f‖`` (smoothed at 0): ``[*S, 20]`` -> ``[*S, 10]``."""
        f = s[..., FEAT]
        return f * torch.rsqrt((f * f).sum(-1, keepdim=True) + _EPS**2)

    def observation_components(self, s: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per landmark ``(k, c)``: ``log p_kc``, ``log(1 − p_kc)``, the mean distance and the mean
        similarity it would report. ``s``: ``[*S, 20]`` -> four ``[*S, K, C]`` tensors."""
        lm = self.landmark_positions.to(s.dtype)
        diff = lm - s[..., None, None, : self.n_pos]  # [*S, K, C, 2]
        r = torch.sqrt((diff * diff).sum(-1) + _EPS**2)  # [*S, K, C]
        bore = s[..., THETA] + s[..., CAL.start + 2]  # θ + c_2
        cos_b, sin_b = torch.cos(bore)[..., None, None], torch.sin(bore)[..., None, None]
        cos_delta = (diff[..., 0] * cos_b + diff[..., 1] * sin_b) / r
        log_p = (
            self._log_p_det
            + F.logsigmoid((self.sensor_range - r) / self.range_softness)
            + F.logsigmoid((cos_delta - self._cos_half_fov) / self._fov_scale)
        )
        log_1mp = torch.log1p(-torch.exp(log_p))  # finite: p ≤ p_det < 1
        cal = s[..., CAL]
        mean_dist = (1.0 + cal[..., 1, None, None]) * r + cal[..., 0, None, None]
        desc = self.landmark_descriptors.to(s.dtype).reshape(-1, N_FEATURES)  # [K·C, 10]
        cos_sim = (self.unit_features(s) @ desc.T).unflatten(-1, (self.n_slots, self.n_clusters))
        mean_sim = (1.0 + cal[..., 3, None, None]) * cos_sim + cal[..., 4, None, None]
        return log_p, log_1mp, mean_dist, mean_sim

    def visibility_log_prob(self, s: Tensor) -> Tensor:
        """``log P(slot k visible | s)`` ``[*S, K]`` (``log(1 − Π_c (1 − p_kc))``, computed stably as
        the log-sum over "copy c is the first detected")."""
        log_p, log_1mp, _, _ = self.observation_components(s)
        return torch.logsumexp(log_p + torch.cumsum(log_1mp, -1) - log_1mp, dim=-1)

    # ------------------------------------------------------------------ protocol
    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """The kidnapped start: position uniform over the map, heading uniform in [0, 2π), speed
        ``N(v_nom, ·)``, steering and calibration near 0, ``f = normalize(f_ref + ·)``. ``[*shape, 20]``."""
        kw = dict(generator=generator, device=self.device)
        pos = self.map_size * torch.rand(*shape, 2, **kw)
        theta = 2 * math.pi * torch.rand(*shape, 1, **kw)
        v = self.nominal_speed + self.start_speed_std * torch.randn(*shape, 1, **kw)
        steer = self.start_steering_std * torch.randn(*shape, 1, **kw)
        cal = self.start_calibration_std * torch.randn(*shape, N_CALIBRATION, **kw)
        f = self.reference_descriptor + self.start_feature_std * torch.randn(*shape, N_FEATURES, **kw)
        f = f / torch.linalg.vector_norm(f, dim=-1, keepdim=True).clamp_min(1e-12)
        return torch.cat([pos, theta, v, steer, cal, f], dim=-1)

    def initial_belief(
        self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None
    ) -> Tensor:
        """``n`` draws of the start distribution (spread over the whole map): ``[*shape, n, 20]``."""
        return self.initial_state((*shape, n), generator)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """Noise-free dynamics. ``s``: ``[*S, 20]``, ``a``: ``[*S]`` (broadcast) -> ``[*S, 20]``."""
        a = a.long()
        theta, v, steer = s[..., THETA], s[..., V], s[..., STEER]
        step = self._moves.to(s.dtype)[a] * v * self.dt
        x = (s[..., X] + step * torch.cos(theta)).clamp(0.0, self.map_size)
        y = (s[..., Y] + step * torch.sin(theta)).clamp(0.0, self.map_size)
        theta = theta + self._dtheta.to(s.dtype)[a]
        k = self.velocity_reversion
        v = v + k * (self.nominal_speed - v)
        steer = (1.0 - k) * steer
        shape = torch.broadcast_shapes(x.shape, theta.shape)
        head = torch.stack([t.expand(shape) for t in (x, y, theta, v, steer)], dim=-1)
        rest = torch.cat([s[..., CAL], self.unit_features(s)], dim=-1)
        return torch.cat([head, rest.expand(*shape, rest.shape[-1])], dim=-1)

    def observe(self, s_next: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Sample ``[visible, distance, similarity]`` per slot. ``s_next``: ``[*S, 20]`` -> ``[*S, 3K]``."""
        log_p, _, mean_dist, mean_sim = self.observation_components(s_next)
        u = torch.rand(log_p.shape, generator=generator, device=log_p.device, dtype=log_p.dtype)
        detected = u < torch.exp(log_p)  # [*S, K, C]
        visible = detected.any(-1)  # [*S, K]
        first = torch.argmax(detected.to(torch.uint8), dim=-1, keepdim=True)  # first True (first max)
        dist = torch.gather(mean_dist, -1, first).squeeze(-1)
        sim = torch.gather(mean_sim, -1, first).squeeze(-1)
        noise = torch.randn((*visible.shape, 2), generator=generator, device=log_p.device, dtype=log_p.dtype)
        dist = dist + self.distance_noise_std * noise[..., 0]
        sim = sim + self.similarity_noise_std * noise[..., 1]
        m = visible.to(log_p.dtype)
        return torch.stack([m, m * dist, m * sim], dim=-1).flatten(-2)

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``log O(o | s')`` (the exact law in the module docstring). ``o``: ``[*S, 3K]``,
        ``s_next``: ``[*S, 20]`` (broadcast) -> ``[*S]``. Finite everywhere, never NaN."""
        log_p, log_1mp, mean_dist, mean_sim = self.observation_components(s_next)
        o3 = o.unflatten(-1, (self.n_slots, 3))
        visible = o3[..., 0] > 0.5  # [*S, K]
        zd = (o3[..., 1, None] - mean_dist) / self.distance_noise_std  # [*S, K, C]
        zs = (o3[..., 2, None] - mean_sim) / self.similarity_noise_std
        log_norm = -math.log(self.distance_noise_std * self.similarity_noise_std) - math.log(2 * math.pi)
        log_first = log_p + torch.cumsum(log_1mp, -1) - log_1mp  # copy c detected, none before it
        lp_visible = torch.logsumexp(log_first - 0.5 * (zd * zd + zs * zs), dim=-1) + log_norm
        lp_invisible = log_1mp.sum(-1)
        return torch.where(visible, lp_visible, lp_invisible).sum(-1)

    def observation_score(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``∇_{s'} log O(o | s')`` in closed form (the gradient autograd gives
        :meth:`observation_log_prob`). ``o``: ``[*S, 3K]``, ``s_next``: ``[*S, 20]`` (broadcast) ->
        ``[*S, 20]``; speed and steering get 0.

        Backward through :meth:`observation_components` by hand. Per landmark ``(k, c)`` the log-density
        depends on ``ℓ_kc = log p_kc``, ``m_kc = log(1 − p_kc)``, the mean distance ``μ_kc`` and the mean
        similarity ``η_kc``; with ``q_kc = softmax_c(ℓ_kc + Σ_{c' < c} m_kc' − (z_d² + z_s²)/2)`` (which copy
        was reported) for a visible slot:

            ∂/∂ℓ_kc = q_kc,   ∂/∂m_kc = Σ_{c' > c} q_kc',   ∂/∂μ_kc = q_kc z_d/σ_r,   ∂/∂η_kc = q_kc z_s/σ_s

        and for an invisible slot ``∂/∂m_kc = 1``, the rest 0; ``m = log(1 − e^ℓ)`` adds
        ``−∂/∂m · e^{ℓ − m}`` to ``∂/∂ℓ``. Then, with ``Δ = lm − p``, ``r = sqrt(‖Δ‖² + ε²)``, boresight
        ``b = θ + c_2``, ``h = (cos b, sin b)``, ``cos δ = Δ·h/r``, range logit ``α = (R − r)/τ_r`` and
        field-of-view logit ``β = (cos δ − cos(fov/2))/(sin(fov/2) τ_θ)``:

            ∂ℓ/∂r = −σ(−α)/τ_r,  ∂ℓ/∂cos δ = σ(−β)/(sin(fov/2) τ_θ),  ∂μ/∂r = 1 + c_1
            ∂r/∂p = −Δ/r,  ∂cos δ/∂p = (cos δ·Δ/r − h)/r,  ∂cos δ/∂b = Δ·h⊥/r,  h⊥ = (−sin b, cos b)
            ∂μ/∂c_0 = 1, ∂μ/∂c_1 = r, ∂η/∂c_3 = ⟨u, d_kc⟩, ∂η/∂c_4 = 1,  u = f/n,  n = sqrt(‖f‖² + ε²)
            ∂/∂f = (g − u⟨u, g⟩)/n   for   g = ∂/∂u = (1 + c_3) Σ_kc ∂/∂η_kc · d_kc
        """
        dt = s_next.dtype
        pos, cal = s_next[..., : self.n_pos], s_next[..., CAL]
        # forward: the pieces of observation_components, kept for the backward pass
        delta = self.landmark_positions.to(dt) - pos[..., None, None, :]  # [*S, K, C, 2]
        r = torch.sqrt((delta * delta).sum(-1) + _EPS**2)  # [*S, K, C]
        bore = s_next[..., THETA] + cal[..., 2]
        cos_b, sin_b = torch.cos(bore)[..., None, None], torch.sin(bore)[..., None, None]
        cos_delta = (delta[..., 0] * cos_b + delta[..., 1] * sin_b) / r
        alpha = (self.sensor_range - r) / self.range_softness
        beta = (cos_delta - self._cos_half_fov) / self._fov_scale
        log_p = self._log_p_det + F.logsigmoid(alpha) + F.logsigmoid(beta)
        p = torch.exp(log_p)
        log_1mp = torch.log1p(-p)
        f = s_next[..., FEAT]
        inv_n = torch.rsqrt((f * f).sum(-1, keepdim=True) + _EPS**2)
        unit = f * inv_n  # [*S, 10]
        desc = self.landmark_descriptors.to(dt).reshape(-1, N_FEATURES)  # [K·C, 10]
        cos_sim = (unit @ desc.T).unflatten(-1, (self.n_slots, self.n_clusters))
        gain_d, gain_s = 1.0 + cal[..., 1, None, None], 1.0 + cal[..., 3, None, None]
        mean_dist = gain_d * r + cal[..., 0, None, None]
        mean_sim = gain_s * cos_sim + cal[..., 4, None, None]
        o3 = o.unflatten(-1, (self.n_slots, 3))
        visible = (o3[..., 0] > 0.5).unsqueeze(-1).to(dt)  # [*S, K, 1], 1.0 for a visible slot
        zd = (o3[..., 1, None] - mean_dist) / self.distance_noise_std
        zs = (o3[..., 2, None] - mean_sim) / self.similarity_noise_std
        log_first = log_p + torch.cumsum(log_1mp, -1) - log_1mp
        logits = log_first - 0.5 * (zd * zd + zs * zs)
        q = torch.exp(logits - logits.amax(-1, keepdim=True))  # softmax by hand: on a CPU, faster than
        q = q * (visible / q.sum(-1, keepdim=True))  # ATen's on rows of a few entries; 0 if invisible
        # backward: adjoints of log p, log(1 − p), mean distance and mean similarity
        later = q.sum(-1, keepdim=True) - torch.cumsum(q, -1)  # Σ_{c' > c} q_kc'
        g_1mp = later + (1.0 - visible)
        g_lp = q - g_1mp * p / (1.0 - p)
        g_dist = q * zd / self.distance_noise_std
        g_sim = q * zs / self.similarity_noise_std
        # position and boresight, through r and cos δ
        g_r = -g_lp * torch.sigmoid(-alpha) / self.range_softness + g_dist * gain_d
        g_cos = g_lp * torch.sigmoid(-beta) / self._fov_scale
        heading = torch.stack([cos_b, sin_b], dim=-1)  # [*S, 1, 1, 2]
        dir_ = delta / r.unsqueeze(-1)
        d_pos = -g_r.unsqueeze(-1) * dir_ + (g_cos / r).unsqueeze(-1) * (cos_delta.unsqueeze(-1) * dir_ - heading)
        d_pos = d_pos.sum((-3, -2))  # [*S, 2]
        d_bore = (g_cos * (delta[..., 1] * cos_b - delta[..., 0] * sin_b) / r).sum((-2, -1))
        # calibration
        d_cal = torch.stack([
            g_dist.sum((-2, -1)), (g_dist * r).sum((-2, -1)), d_bore,
            (g_sim * cos_sim).sum((-2, -1)), g_sim.sum((-2, -1)),
        ], dim=-1)  # [*S, 5]
        # features, through u = f/n
        g_unit = gain_s[..., 0] * (g_sim.flatten(-2) @ desc)  # [*S, 10]
        d_feat = (g_unit - unit * (unit * g_unit).sum(-1, keepdim=True)) * inv_n
        shape = d_cal.shape[:-1]
        zero = torch.zeros((), dtype=dt, device=q.device).expand(shape)
        head = torch.stack([d_pos[..., 0], d_pos[..., 1], d_bore, zero, zero], dim=-1)
        return torch.cat([head, d_cal, d_feat.expand(*shape, N_FEATURES)], dim=-1)

    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor:
        """−1 per step (paper)."""
        shape = torch.broadcast_shapes(s.shape[:-1], a.shape, s_next.shape[:-1])
        return torch.full(shape, -1.0, dtype=s_next.dtype, device=s_next.device)

    def is_terminal(self, s: Tensor) -> Tensor:
        """Always False: episodes end at ``max_steps`` (config)."""
        return torch.zeros(s.shape[:-1], dtype=torch.bool, device=s.device)


def describe_correlations(model: KidnappedRobot20D | None = None) -> str:
    """A Markdown report of the paper's process-noise correlations and the nearest correlation
    matrix (Higham 2002) that :class:`KidnappedRobot20D` uses instead, one row per group of pairs
    the paper gives one value for (with the range of the used values over the group)."""
    model = KidnappedRobot20D() if model is None else model
    paper, used = model.paper_correlation, model.correlation
    cal, feat = list(range(CAL.start, CAL.stop)), list(range(FEAT.start, FEAT.stop))
    groups = {
        "rho(x, theta), rho(y, theta)": [(X, THETA), (Y, THETA)],
        "rho(x, v), rho(y, v)": [(X, V), (Y, V)],
        "rho(c_i, c_j), i != j": [(i, j) for i in cal for j in cal if i < j],
        "rho(c_i, f_k)": [(i, k) for i in cal for k in feat],
        "rho(x, y) (not given)": [(X, Y)],
        "rho(theta, v) (not given)": [(THETA, V)],
        "rho(f_k, f_l), k != l (not given)": [(k, other) for k in feat for other in feat if k < other],
    }
    rows = []
    for label, pairs in groups.items():
        p = torch.stack([paper[i, j] for i, j in pairs])
        u = torch.stack([used[i, j] for i, j in pairs])
        used_txt = f"{u.min().item():.3f}" if torch.allclose(u.min(), u.max(), atol=5e-4) else \
            f"{u.min().item():.3f} .. {u.max().item():.3f}"
        rows.append((label, f"{p.max().item():.2f}", used_txt))
    return correlation_report("Kidnapped Robot 20D process-noise correlations", paper, used, rows, column="pairs")
