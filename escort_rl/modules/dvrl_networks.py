"""The networks of DVRL (Igl et al. 2018): encoders, Gaussian heads, the recurrence, belief summaries.

Every piece is a small ``nn.Module`` with a fixed call signature, so that
:class:`escort_rl.modules.dvrl.DVRL` can take any of them as a replacement (the tests inject a
linear-Gaussian model this way).
Shapes: ``B`` envs, ``K`` particles, ``H`` the per-particle hidden size, ``Z`` the latent size,
``E`` an encoding size.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.distributions import Independent, Normal

ATARI_SIZE = 84  # the side of the original's Atari frames
MINATAR_SIZE = 10  # the side of MinAtar's grids


def mlp(sizes: list[int], last_activation: bool = True) -> nn.Sequential:
    """``Linear -> ReLU`` layers through ``sizes`` (ReLU as in the original code)."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2 or last_activation:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


# ---------------------------------------------------------------------------------------- encoders
class VectorEncoder(nn.Module):
    """φ(o) for vector observations: a two-layer MLP. ``[*, obs_dim] -> [*, encoding_dim]``."""

    def __init__(self, obs_dim: int, encoding_dim: int) -> None:
        super().__init__()
        self.net = mlp([obs_dim, encoding_dim, encoding_dim])

    def forward(self, observation: Tensor) -> Tensor:
        return self.net(observation)


class AtariEncoder(nn.Module):
    """φ(o) for ``84×84`` frames: the original's conv stack, then a linear layer.

    ``Conv(C→32, 8, stride 4) → Conv(32→64, 4, stride 2) → Conv(64→32, 3, stride 1)``, ReLU after each,
    gives ``[32, 7, 7]`` (84 → 20 → 9 → 7), flattened and mapped to ``encoding_dim``.
    ``[*, C, 84, 84] -> [*, encoding_dim]``.
    """

    conv_out_shape = (32, 7, 7)

    def __init__(self, channels: int, encoding_dim: int) -> None:
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv2d(channels, 32, 8, stride=4), nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(),
            nn.Conv2d(64, 32, 3, stride=1), nn.ReLU(),
        )
        self.linear = nn.Sequential(nn.Linear(math.prod(self.conv_out_shape), encoding_dim), nn.ReLU())

    def forward(self, observation: Tensor) -> Tensor:
        lead = observation.shape[:-3]
        x = self.conv(observation.reshape(-1, *observation.shape[-3:]))
        return self.linear(x.flatten(1)).reshape(*lead, -1)


class AtariDecoder(nn.Module):
    """The mirror of :class:`AtariEncoder`: ``[*, in_dim] -> [*, C, 84, 84]`` (7 → 9 → 20 → 84)."""

    def __init__(self, in_dim: int, channels: int) -> None:
        super().__init__()
        self.linear = nn.Sequential(nn.Linear(in_dim, math.prod(AtariEncoder.conv_out_shape)), nn.ReLU())
        self.deconv = nn.Sequential(
            nn.ConvTranspose2d(32, 64, 3, stride=1), nn.ReLU(),
            nn.ConvTranspose2d(64, 32, 4, stride=2), nn.ReLU(),
            nn.ConvTranspose2d(32, channels, 8, stride=4),
        )

    def forward(self, x: Tensor) -> Tensor:
        lead = x.shape[:-1]
        y = self.linear(x.reshape(-1, x.shape[-1])).reshape(-1, *AtariEncoder.conv_out_shape)
        y = self.deconv(y)
        return y.reshape(*lead, *y.shape[1:])


class MinAtarEncoder(nn.Module):
    """φ(o) for MinAtar's ``10×10`` grids: the conv layer of MinAtar's own DQN, then a linear layer.

    ``Conv(C→16, 3, stride 1)`` and ReLU give ``[16, 8, 8]``, flattened and mapped to ``encoding_dim``.
    ``[*, C, 10, 10] -> [*, encoding_dim]``.
    """

    conv_out_shape = (16, 8, 8)

    def __init__(self, channels: int, encoding_dim: int) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(channels, 16, 3, stride=1), nn.ReLU())
        self.linear = nn.Sequential(nn.Linear(math.prod(self.conv_out_shape), encoding_dim), nn.ReLU())

    def forward(self, observation: Tensor) -> Tensor:
        lead = observation.shape[:-3]
        x = self.conv(observation.reshape(-1, *observation.shape[-3:]))
        return self.linear(x.flatten(1)).reshape(*lead, -1)


class MinAtarDecoder(nn.Module):
    """The mirror of :class:`MinAtarEncoder`: ``[*, in_dim] -> [*, C, 10, 10]`` (8 → 10)."""

    def __init__(self, in_dim: int, channels: int) -> None:
        super().__init__()
        self.linear = nn.Sequential(nn.Linear(in_dim, math.prod(MinAtarEncoder.conv_out_shape)), nn.ReLU())
        self.deconv = nn.ConvTranspose2d(16, channels, 3, stride=1)

    def forward(self, x: Tensor) -> Tensor:
        lead = x.shape[:-1]
        y = self.deconv(self.linear(x.reshape(-1, x.shape[-1])).reshape(-1, *MinAtarEncoder.conv_out_shape))
        return y.reshape(*lead, *y.shape[1:])


FRAME_NETWORKS = {ATARI_SIZE: (AtariEncoder, AtariDecoder), MINATAR_SIZE: (MinAtarEncoder, MinAtarDecoder)}
"""Frame side -> (encoder, decoder) classes: Atari's ``84×84`` frames and MinAtar's ``10×10`` grids."""


def frame_networks(obs_shape: tuple[int, ...]) -> tuple[type[nn.Module], type[nn.Module]]:
    """The (encoder, decoder) classes for frames of ``obs_shape = (C, S, S)``; other shapes raise
    ``ValueError`` naming the sizes there are networks for."""
    if len(obs_shape) != 3 or obs_shape[1] != obs_shape[2] or obs_shape[1] not in FRAME_NETWORKS:
        sizes = ", ".join(f"(C, {s}, {s})" for s in FRAME_NETWORKS)
        raise ValueError(f"obs_shape: frames must be one of {sizes}, got {tuple(obs_shape)}")
    return FRAME_NETWORKS[obs_shape[1]]


# ---------------------------------------------------------------------------------- distributions
class GaussianHead(nn.Module):
    """A diagonal Gaussian from concatenated inputs: ``N(μ(x), diag σ(x)²)``, ``σ = softplus(·) + min_std``.

    ``forward(*inputs)`` concatenates ``inputs`` (each ``[*, n_i]``, ``Σ n_i = in_dim``) and returns an
    ``Independent(Normal, 1)`` with batch shape ``[*]`` and event shape ``[out_dim]``.
    Used for the transition prior ``p(z|h, a)`` and the proposal ``q(z|h, a, o)``.
    """

    def __init__(self, in_dim: int, out_dim: int, hidden: int, min_std: float = 1e-3) -> None:
        super().__init__()
        self.body = mlp([in_dim, hidden])
        self.mean = nn.Linear(hidden, out_dim)
        self.raw_std = nn.Linear(hidden, out_dim)
        self.min_std = min_std

    def forward(self, *inputs: Tensor) -> Independent:
        x = self.body(torch.cat(inputs, dim=-1))
        std = nn.functional.softplus(self.raw_std(x)) + self.min_std
        return Independent(Normal(self.mean(x), std), 1)


class GaussianEmission(nn.Module):
    """``p(o|h_{t-1}, z_t, a_{t-1})`` for vector observations: a :class:`GaussianHead` on
    ``[h, φ(z), φ(a)]``, with ``φ(z)`` the latent encoder shared with the recurrence.

    ``forward(h [B, K, H], z [B, K, Z], action_enc [B, K, E]) -> Independent(Normal)`` with event
    shape ``[obs_dim]``: ``log_prob(o [B, K, obs_dim]) -> [B, K]``.
    """

    def __init__(self, latent_encoder: nn.Module, in_dim: int, obs_dim: int, hidden: int) -> None:
        super().__init__()
        self.latent_encoder = latent_encoder
        self.head = GaussianHead(in_dim, obs_dim, hidden)

    def forward(self, h: Tensor, z: Tensor, action_enc: Tensor) -> Independent:
        return self.head(h, self.latent_encoder(z), action_enc)


class ImageEmission(nn.Module):
    """``p(o|h, z, a)`` for ``[C, S, S]`` frames: per-pixel Gaussians, the mean decoded from
    ``[h, φ(z), φ(a)]`` by the decoder of :func:`frame_networks` (:class:`AtariDecoder` for ``S = 84``,
    :class:`MinAtarDecoder` for ``S = 10``) and one learned standard deviation.

    ``log_prob(o [B, K, C, S, S]) -> [B, K]``.

    ``min_std`` floors the learned standard deviation (0: none). On frames the decoder can nearly
    reproduce (MinAtar's binary grids), the ELBO's optimum has the deviation shrink without end, and
    the ELBO and its gradient grow with ``−log σ`` until they drown the policy's gradient.
    """

    def __init__(self, latent_encoder: nn.Module, in_dim: int, channels: int, frame_size: int = ATARI_SIZE,
                 min_std: float = 0.0) -> None:
        super().__init__()
        self.latent_encoder = latent_encoder
        self.decoder = frame_networks((channels, frame_size, frame_size))[1](in_dim, channels)
        self.log_std = nn.Parameter(torch.zeros(()))
        self.min_log_std = math.log(min_std) if min_std > 0 else -math.inf

    def forward(self, h: Tensor, z: Tensor, action_enc: Tensor) -> Independent:
        mean = self.decoder(torch.cat([h, self.latent_encoder(z), action_enc], dim=-1))
        return Independent(Normal(mean, self.log_std.clamp_min(self.min_log_std).exp().expand_as(mean)), 3)


class FeatureEmission(nn.Module):
    """``p(φ(o)|h, z, a)``: a diagonal Gaussian over the observation's encoding instead of its pixels,
    the mean an MLP of ``[h, φ(z), φ(a)]`` and one learned standard deviation.

    The likelihood of an observation read in the encoder's feature space: an MLP pass per particle
    instead of a decoder pass. The caller gives the encoding detached (``log_prob(φ(o).detach())``), so
    that the encoder cannot shrink its features to raise the likelihood.
    ``forward(h [B, K, H], z [B, K, Z], action_enc [B, K, E]) -> Independent(Normal)`` with event shape
    ``[encoding_dim]``: ``log_prob(φ(o) [B, K, E]) -> [B, K]``. ``min_std`` floors the learned standard
    deviation, as :class:`ImageEmission`'s.
    """

    def __init__(self, latent_encoder: nn.Module, in_dim: int, encoding_dim: int, hidden: int,
                 min_std: float = 0.0) -> None:
        super().__init__()
        self.latent_encoder = latent_encoder
        self.mean = nn.Sequential(mlp([in_dim, hidden]), nn.Linear(hidden, encoding_dim))
        self.log_std = nn.Parameter(torch.zeros(()))
        self.min_log_std = math.log(min_std) if min_std > 0 else -math.inf

    def forward(self, h: Tensor, z: Tensor, action_enc: Tensor) -> Independent:
        mean = self.mean(torch.cat([h, self.latent_encoder(z), action_enc], dim=-1))
        return Independent(Normal(mean, self.log_std.clamp_min(self.min_log_std).exp().expand_as(mean)), 1)


# ---------------------------------------------------------------------------------------- recurrence
class GRURecurrence(nn.Module):
    """The deterministic update ``h_t = GRUCell([φ(z_t), φ(o_t), φ(a_{t-1})], h_{t-1})``.

    ``forward(h [B, K, H], z [B, K, Z], obs_enc [B, K, E_o], action_enc [B, K, E_a]) -> [B, K, H]``.
    """

    def __init__(self, latent_encoder: nn.Module, in_dim: int, hidden: int) -> None:
        super().__init__()
        self.latent_encoder = latent_encoder
        self.cell = nn.GRUCell(in_dim, hidden)

    def forward(self, h: Tensor, z: Tensor, obs_enc: Tensor, action_enc: Tensor) -> Tensor:
        x = torch.cat([self.latent_encoder(z), obs_enc, action_enc], dim=-1)
        lead = h.shape[:-1]
        return self.cell(x.reshape(-1, x.shape[-1]), h.reshape(-1, h.shape[-1])).reshape(*lead, -1)


# -------------------------------------------------------------------------------- belief summaries
class GRUSummary(nn.Module):
    """The original's belief summary: a GRU run over the particles in index order, its last hidden
    state the summary. Input per particle: ``[h_k, φ(z_k), K·w̄_k]`` (weights relative to uniform).

    ``forward(h [B, K, H], z_enc [B, K, E], log_w [B, K]) -> [B, out_dim]``.
    """

    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.gru = nn.GRU(in_dim + 1, out_dim, batch_first=True)

    def forward(self, h: Tensor, z_enc: Tensor, log_w: Tensor) -> Tensor:
        k = log_w.shape[-1]
        relative_w = (torch.log_softmax(log_w, dim=-1) + math.log(k)).exp().unsqueeze(-1)
        _, last = self.gru(torch.cat([h, z_enc, relative_w], dim=-1))
        return last[-1]


class DeepSetsSummary(nn.Module):
    """A permutation-invariant alternative: ``ρ(Σ_k w̄_k ψ([h_k, φ(z_k)]))``.

    ``forward(h [B, K, H], z_enc [B, K, E], log_w [B, K]) -> [B, out_dim]``.
    """

    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.psi = mlp([in_dim, out_dim, out_dim])
        self.rho = mlp([out_dim, out_dim])

    def forward(self, h: Tensor, z_enc: Tensor, log_w: Tensor) -> Tensor:
        w = torch.softmax(log_w, dim=-1).unsqueeze(-1)
        return self.rho((w * self.psi(torch.cat([h, z_enc], dim=-1))).sum(-2))


SUMMARIES = {"gru": GRUSummary, "deepsets": DeepSetsSummary}


# ---------------------------------------------------------------------------------------- readout
class StateReadout(nn.Module):
    """A probe from DVRL's belief summary to the env's state, for measuring position error.

    DVRL's latent ``z`` is not the state, so its belief has no position to compare with the truth. The
    readout is an MLP ``summary [*, S] -> state estimate [*, state_dim]``, trained by regression on the
    true states of the training trajectories, on a detached summary (it reads the belief, it does not
    shape it). ``(x - loc) / scale`` of the target is what the network fits, so that one learning rate
    suits maps of any size; the output is in state units.
    """

    def __init__(self, summary_dim: int, state_dim: int, hidden: int = 64, loc: float | list[float] = 0.0,
                 scale: float | list[float] = 1.0) -> None:
        super().__init__()
        scale_t = torch.as_tensor(scale, dtype=torch.float32).expand(state_dim).clone()
        if not bool((scale_t > 0).all()):
            raise ValueError(f"scale: must be positive, got {scale}")
        self.net = mlp([summary_dim, hidden, hidden, state_dim], last_activation=False)
        # non-persistent buffers: they follow .to(device), and checkpoints of earlier runs load unchanged
        self.register_buffer("loc", torch.as_tensor(loc, dtype=torch.float32).expand(state_dim).clone(),
                             persistent=False)
        self.register_buffer("scale", scale_t, persistent=False)

    def forward(self, summary: Tensor) -> Tensor:
        return self.net(summary) * self.scale + self.loc

    def loss(self, summary: Tensor, state: Tensor) -> Tensor:
        """Mean squared error in standardised units, ``mean(((f(s) - (x - loc)/scale))²)``."""
        return ((self.net(summary) - (state - self.loc) / self.scale) ** 2).mean()
