"""The parameters of Multi-Target Tracking 20D (:class:`~escort_rl.models.MultiTargetTracking20D`)
and the checks that relate several of them or need their shapes.

The single-field ranges live in the field metadata and are checked by the one checker
(:func:`escort_rl.config.params.build_params`); the functions here check what a bound cannot say
(the shape of a point list, a strictly increasing edge list, zone tables with the same zones, a
zone grid that matches its edges) and return the checked values as float64 tensors.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Dict, List

import torch
from torch import Tensor

from escort_rl.config.errors import ConfigError
from escort_rl.config.params import param

N_TARGETS = 4


@dataclass(frozen=True)
class MultiTargetTracking20DParams:
    """:class:`~escort_rl.models.MultiTargetTracking20D`'s parameters (paper, Appendix "Domains:
    Multiple Target Tracking"). Values the paper gives are marked (paper); the others are choices
    the paper leaves open, with the reason.

    Attributes:
        map_size: side of the square map ``[0, map_size]²`` (paper: 10); entities outside it are
            pushed back by ``wall_gain``.
        dt: time step Δt. The paper gives none; 0.1 matches Light-Dark 10D so the two domains share
            a time scale.
        damping: velocity damping λ in [0, 1] (paper: 0.1).
        accel: acceleration per action. The paper gives no size; 0.2 per step gives a top speed of 1
            per axis when the agent alternates +x and +y, i.e. about 0.14 map units per step toward
            the goal.
        actions: 2-D acceleration directions, one per action, none zero (paper: +x, -x, +y, -y). The
            agent's 4-D state has no heading, so the camera faces the direction of the chosen
            acceleration: the normalised direction also aims the 60-degree field of view.
        flow_center, flow_rate, flow_radius, flow_attraction: the circular current
            ``F(p) = ω·(-r_y, r_x) + 2κ·(1 - u)/(1 + u)·r``, ``r = p - c``, ``u = ‖r‖²/R²``, that targets
            are dragged toward. The paper names a flow field but not its form. A current about the
            map centre carries every target through all four zone quadrants in turn (clear ->
            limited -> blind -> confusion) and its pull onto the ring ``R`` keeps them in the map.
            The pull is linear far out (``-2κ·r``): a cubic pull made the time step unstable for
            particles beyond ``‖r‖ ≈ 14``, and an unseen target's belief got there and blew up.
            ``flow_rate`` ω in rad per unit time (0.3: about 210 steps per revolution at dt 0.1);
            ``flow_radius`` R (3.5: halfway between the centre and the map edge); ``flow_attraction``
            κ (0.2: strong enough that the drag lag and the noise do not spiral targets out of the
            map).
        flocking_alignment: gain pulling each target's velocity toward the mean target velocity.
            The paper names flocking without a law; alignment couples the targets' motion. Cohesion
            is left out: with the current it collapses the ring.
        repulsion_radius: collision avoidance when two targets are closer than this (paper: 1.0).
        repulsion_gain: its strength. The paper gives none; 0.1 per step at full overlap separates
            targets within a few steps.
        wall_gain: restoring force per unit distance outside the map. Positions are never clipped
            (the transition stays Gaussian); a soft wall of 0.1 per unit of overshoot per step
            brings an entity that leaves the map back.
        position_noise_std, velocity_noise_std: process-noise stds (same for agent and targets).
            The paper gives the correlations but not the scale: 0.05 per step as in Light-Dark 10D,
            small next to the motion per step yet enough to spread the belief of an unseen target.
        agent_obs_noise_std: std of the agent's own position measurement. The paper observes the
            agent's position without a noise level: 0.1, the clear-zone noise, and not zone
            dependent, so the agent always localises itself and the belief problem is the targets.
        zone_x_edges, zone_y_edges: strictly increasing cell edges of the zone grid. Zone geometry
            is not given: the map is split into four 5×5 quadrants, so the current visits each zone
            once per revolution.
        zone_grid: zone names per cell, rows = y bins from the bottom, columns = x bins from the
            left (``len(zone_y_edges) + 1`` rows of ``len(zone_x_edges) + 1`` names).
        zone_visibility: ν per zone, in [0, 1] (paper: clear 1.0, limited 0.3, confusion 0.7,
            blind 0.0); some zone of the grid must be visible.
        zone_noise_std: σ per zone, > 0. The paper says only "high noise" in the limited zone: 0.1
            clear, 0.5 limited, 0.2 confusion; the blind value is never used (nothing is detected
            there) but must be positive. Same zones as ``zone_visibility``.
        zone_swap_prob: q per zone, in [0, 1) (paper: a 30% chance of an identity swap in the
            confusion zone, none elsewhere). Same zones as ``zone_visibility``.
        zone_softness: width of the sigmoid zone boundaries: sharp on the 10-unit map (the paper's
            "sharp discontinuities"), yet a particle at a boundary gets a finite, informative score.
        fov_degrees: field of view, in (0, 360) (paper: 60; the paper gives it no range limit).
        fov_softness: width of its edge in ``cos θ`` units (0.02: about 2.3 degrees).
        swap_length_scale: ℓ of the proximity weights of the swap partner: a swapped slot reports
            target j with weight ``exp(-‖p_i - p_j‖²/(2ℓ²))``, the paper's "any of the targets whose
            last known positions were nearby". ℓ = 2 favours a target 1 away over one 5 away 20:1.
        goal: the agent's goal. The paper marks it on its figure without coordinates; (9, 9) is the
            corner opposite the start.
        success_radius: (paper: 0.5).
        distance_weight: α (paper: 0.1). step_penalty: β (paper: 0.05).
        collision_radius: δ (paper: 0.5). collision_penalty: per target closer than δ (paper: 1).
        agent_start_center, agent_start_halfwidth, target_start_centers, target_start_halfwidth:
            start positions uniform in these boxes; start velocities zero. The paper gives no start
            distribution: the agent starts in the corner box [0.5, 1.5]², far from the goal; target
            i starts in a 1×1 box around the centre of quadrant i on the current's ring (one target
            per zone).
    """

    map_size: float = param(10.0, gt=0)
    dt: float = param(0.1, gt=0)
    damping: float = param(0.1, ge=0, le=1)
    accel: float = param(0.2, gt=0)
    actions: List[List[float]] = param([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    flow_center: List[float] = param([5.0, 5.0])
    flow_rate: float = param(0.3)
    flow_radius: float = param(3.5, gt=0)
    flow_attraction: float = param(0.2, ge=0)
    flocking_alignment: float = param(0.05, ge=0)
    repulsion_radius: float = param(1.0, gt=0)
    repulsion_gain: float = param(0.1, ge=0)
    wall_gain: float = param(0.1, ge=0)
    position_noise_std: float = param(0.05, gt=0)
    velocity_noise_std: float = param(0.05, gt=0)
    agent_obs_noise_std: float = param(0.1, gt=0)
    zone_x_edges: List[float] = param([5.0])
    zone_y_edges: List[float] = param([5.0])
    zone_grid: List[List[str]] = param([["clear", "limited"], ["confusion", "blind"]])
    zone_visibility: Dict[str, float] = param({"clear": 1.0, "limited": 0.3, "confusion": 0.7, "blind": 0.0},
                                              ge=0, le=1)
    zone_noise_std: Dict[str, float] = param({"clear": 0.1, "limited": 0.5, "confusion": 0.2, "blind": 0.5}, gt=0)
    zone_swap_prob: Dict[str, float] = param({"clear": 0.0, "limited": 0.0, "confusion": 0.3, "blind": 0.0},
                                             ge=0, lt=1)
    zone_softness: float = param(0.1, gt=0)
    fov_degrees: float = param(60.0, gt=0, lt=360)
    fov_softness: float = param(0.02, gt=0)
    swap_length_scale: float = param(2.0, gt=0)
    goal: List[float] = param([9.0, 9.0])
    success_radius: float = param(0.5, gt=0)
    distance_weight: float = param(0.1, ge=0)
    step_penalty: float = param(0.05, ge=0)
    collision_radius: float = param(0.5, ge=0)
    collision_penalty: float = param(1.0, ge=0)
    agent_start_center: List[float] = param([1.0, 1.0])
    agent_start_halfwidth: float = param(0.5, ge=0)
    target_start_centers: List[List[float]] = param([[2.5, 2.5], [7.5, 2.5], [7.5, 7.5], [2.5, 7.5]])
    target_start_halfwidth: float = param(0.5, ge=0)


OWNER = "MultiTargetTracking20D"


def _fail(name: str, msg: str):
    raise ConfigError(f"{OWNER}.{name}: {msg}")


def _tensor(value) -> Tensor | None:
    """``value`` as a float64 tensor, or ``None`` when it is not a (nested) list of numbers of one shape."""
    try:
        return torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        return None


def check_pair(name: str, value: Sequence[float]) -> Tensor:
    """``<name>`` as a ``[2]`` tensor; raises unless it is two finite numbers."""
    t = _tensor(value)
    if t is None or t.shape != (2,) or not torch.isfinite(t).all():
        _fail(name, f"must be two finite numbers, got {value!r}")
    return t


def check_edges(name: str, value: Sequence[float]) -> Tensor:
    """``<name>`` as a ``[E]`` tensor; raises unless it is a strictly increasing list of finite numbers."""
    t = _tensor(list(value))
    if (t is None or t.dim() != 1 or not torch.isfinite(t).all()
            or (t.numel() > 1 and not bool((t.diff() > 0).all()))):
        _fail(name, f"must be a strictly increasing list of finite numbers, got {value!r}")
    return t


def check_actions(actions: Sequence[Sequence[float]]) -> Tensor:
    """``actions`` as a ``[n_actions, 2]`` tensor; raises unless it is a non-empty list of non-zero
    ``[ax, ay]`` pairs."""
    act = _tensor(actions)
    if (act is None or act.dim() != 2 or act.shape[0] < 1 or act.shape[1] != 2
            or not bool(torch.isfinite(act).all())):
        _fail("actions", f"must be a non-empty list of [ax, ay] pairs, got {actions!r}")
    if not bool((torch.linalg.vector_norm(act, dim=-1) > 0).all()):
        _fail("actions", "every action needs a non-zero direction (it also sets the camera heading)")
    return act


def check_target_start_centers(value: Sequence[Sequence[float]]) -> Tensor:
    """``target_start_centers`` as a ``[4, 2]`` tensor; raises unless it is four finite pairs."""
    t = _tensor(value)
    if t is None or t.shape != (N_TARGETS, 2) or not torch.isfinite(t).all():
        _fail("target_start_centers", f"must be {N_TARGETS} pairs [x, y], got {value!r}")
    return t


def check_zone_tables(p: MultiTargetTracking20DParams) -> None:
    """Raise unless the three zone tables are non-empty and name the same zones."""
    for name in ("zone_visibility", "zone_noise_std", "zone_swap_prob"):
        table = getattr(p, name)
        if not isinstance(table, Mapping) or not table:
            _fail(name, f"must be a non-empty mapping zone name -> number, got {table!r}")
    names = set(p.zone_visibility)
    for name in ("zone_noise_std", "zone_swap_prob"):
        table = getattr(p, name)
        if set(table) != names:
            _fail(name, f"must have the same zones as zone_visibility {sorted(names)}, got {sorted(table)}")


def check_zone_grid(p: MultiTargetTracking20DParams, x_edges: Tensor, y_edges: Tensor) -> list[list[str]]:
    """The rows of ``zone_grid``; raises unless it has one row per y bin of one known zone name per
    x bin, and some cell is visible."""
    names, grid = set(p.zone_visibility), p.zone_grid
    rows = [list(r) for r in grid if isinstance(r, Sequence) and not isinstance(r, str)]
    if (len(rows) != len(grid) or len(rows) != y_edges.numel() + 1
            or any(len(r) != x_edges.numel() + 1 for r in rows)):
        _fail("zone_grid", f"must be {y_edges.numel() + 1} rows (y bins) of {x_edges.numel() + 1} zone names "
              f"(x bins), got {grid!r}")
    for r in rows:
        for z in r:
            if z not in names:
                _fail("zone_grid", f"unknown zone '{z}'; zones are {sorted(names)}")
    if not any(p.zone_visibility[z] > 0 for r in rows for z in r):
        _fail("zone_visibility", "every zone in zone_grid is blind; no target could ever be observed")
    return rows
