"""The soft zone grid of Multi-Target Tracking 20D: a grid of cells whose edges are sigmoids.

Along one axis the edges ``e_0 < … < e_last`` cut the line into soft bins: bin 0 is
``σ(-(x - e_0)/τ)``, the last ``σ((x - e_last)/τ)``, and bin ``b`` in between
``σ((x - e_{b-1})/τ) - σ((x - e_b)/τ)``; a cell of the grid is a pair of bins (``c = by·n_x + bx``),
and its probability the product. Each cell carries the observation constants of its zone.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def log_cosh(z: Tensor) -> Tensor:
    """``log cosh z``, stable for any ``z`` (gradient ``tanh z``)."""
    return F.softplus(2 * z) - z - math.log(2.0)


def log_sinh(k: float) -> float:
    """``log sinh k`` for a constant ``k > 0``, without overflow."""
    return k + math.log(-math.expm1(-2 * k)) - math.log(2.0)


def bin_log_sinh(edges: Tensor, softness: float) -> list[float]:
    """``log sinh(w/2τ)`` for the width ``w`` of each inner bin (the constants of :func:`bin_log_probs`)."""
    return [log_sinh(float(w) / (2 * softness)) for w in edges.diff()]


def bin_log_probs(x: Tensor, edges: Tensor, softness: float, logsinh: list[float]) -> Tensor:
    """Soft 1-D bins: ``x`` ``[*S]`` -> ``[*S, n_edges + 1]`` log-probabilities summing to 1.

    Bin 0 is ``σ(-(x - e_0)/τ)``, the last ``σ((x - e_last)/τ)``, and bin ``b`` in between
    ``σ((x - e_{b-1})/τ) - σ((x - e_b)/τ) = sinh(w/2τ) / (2 cosh(a/2) cosh(c/2))``, evaluated
    in log space (no cancellation, finite gradients)."""
    if edges.numel() == 0:
        return torch.zeros(*x.shape, 1, dtype=x.dtype, device=x.device)
    a = (x.unsqueeze(-1) - edges) / softness  # [*S, E]
    parts = [F.logsigmoid(-a[..., 0])]
    for b in range(1, edges.numel()):
        parts.append(logsinh[b - 1] - math.log(2.0) - log_cosh(a[..., b - 1] / 2) - log_cosh(a[..., b] / 2))
    parts.append(F.logsigmoid(a[..., -1]))
    return torch.stack(parts, dim=-1)


def bin_log_prob_grads(x: Tensor, edges: Tensor, softness: float) -> Tensor:
    """``d/dx`` of :func:`bin_log_probs`: ``x`` ``[*S]`` -> ``[*S, n_edges + 1]``. With
    ``a_e = (x − e)/τ``: ``−σ(a_0)/τ`` for bin 0, ``σ(−a_last)/τ`` for the last bin, and
    ``−(tanh(a_{b−1}/2) + tanh(a_b/2))/(2τ)`` in between (``d log cosh z/dz = tanh z``; autograd
    through :func:`log_cosh` differs by under ``1e-8/τ``, as softplus turns linear past 20)."""
    if edges.numel() == 0:
        return torch.zeros(*x.shape, 1, dtype=x.dtype, device=x.device)
    a = (x.unsqueeze(-1) - edges) / softness  # [*S, E]
    tau = softness
    parts = [-torch.sigmoid(a[..., 0]) / tau]
    for b in range(1, edges.numel()):
        parts.append(-(torch.tanh(a[..., b - 1] / 2) + torch.tanh(a[..., b] / 2)) / (2 * tau))
    parts.append(torch.sigmoid(-a[..., -1]) / tau)
    return torch.stack(parts, dim=-1)


def cell_constants(zone_names: tuple[str, ...], visibility: dict, noise_std: dict, swap_prob: dict,
                   device: torch.device) -> dict[str, Tensor]:
    """The per-cell observation constants of the zones ``zone_names`` (one per cell), by attribute
    name, float32 (index tensors int64) on ``device``:

    - ``cell_visibility``, ``cell_noise_std``, ``cell_swap_prob``: ν, σ and q per cell;
    - ``_vis_cells`` / ``_miss_cells``: the cells where a detection / a miss can happen (ν > 0 / ν < 1),
      with ``_log_nu_vis`` = log ν and ``_log_1m_nu_miss`` = log(1 − ν) there;
    - ``_log_sig``, ``_inv_var``: log σ and 1/σ²; ``_log_keep``, ``_log_swap``: log(1 − q) for the
      identity component and log q for the swap components (-inf when q = 0);
    - for the score, the visible cells split into "plain" ones (q = 0, a report of the slot's own
      target) and "swapping" ones (q > 0), in the order plain then swapping: ``_score_cells``,
      ``_score_log_nu`` and the plain / swapping parts of the constants above. They are the same
      constants, indexed (not recombined), so the log-density and the score round alike.
    """

    def to(x: Tensor) -> Tensor:
        return x.to(dtype=torch.float32, device=device)

    nu = torch.tensor([float(visibility[z]) for z in zone_names], dtype=torch.float64)
    sig = torch.tensor([float(noise_std[z]) for z in zone_names], dtype=torch.float64)
    q = torch.tensor([float(swap_prob[z]) for z in zone_names], dtype=torch.float64)
    c = {"cell_visibility": to(nu), "cell_noise_std": to(sig), "cell_swap_prob": to(q)}
    c["_vis_cells"] = torch.nonzero(nu > 0).flatten().to(device)
    c["_miss_cells"] = torch.nonzero(nu < 1).flatten().to(device)
    c["_log_nu_vis"] = to(torch.log(nu[nu > 0]))
    c["_log_1m_nu_miss"] = to(torch.log1p(-nu[nu < 1]))
    c["_log_sig"] = to(torch.log(sig))
    c["_inv_var"] = to(1.0 / sig**2)
    c["_log_keep"] = to(torch.log1p(-q))
    c["_log_swap"] = to(torch.log(q))
    plain, swapping = (nu > 0) & (q == 0), (nu > 0) & (q > 0)
    score_cells = torch.cat([torch.nonzero(plain).flatten(), torch.nonzero(swapping).flatten()])
    c["_score_cells"], c["_score_log_nu"] = score_cells.to(device), to(torch.log(nu[score_cells]))
    plain, swapping = plain.to(device), swapping.to(device)
    c["_plain_inv_var"], c["_plain_log_sig"] = c["_inv_var"][plain], c["_log_sig"][plain]
    c["_swap_inv_var"], c["_swap_log_sig"] = c["_inv_var"][swapping], c["_log_sig"][swapping]
    c["_swap_log_keep"], c["_swap_log_swap"] = c["_log_keep"][swapping], c["_log_swap"][swapping]
    return c
