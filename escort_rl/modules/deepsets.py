"""DeepSetsActor: a permutation-invariant policy over a weighted particle set (paper §3.5)."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import Tensor, nn
from torch.distributions import Categorical
from torchrl.modules import ProbabilisticActor

from escort_rl.models.protocol import is_continuous
from escort_rl.modules.action_heads import DEFAULT_DISTRIBUTION, DEFAULT_MIN_SCALE, gaussian_in_box, normal_params


def _mlp(sizes: list[int], activation: type[nn.Module] = nn.Tanh, last_activation: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2 or last_activation:
            layers.append(activation())
    return nn.Sequential(*layers)


def thinned(particles: Tensor, log_weights: Tensor | None, max_particles: int | None) -> tuple[Tensor, Tensor | None]:
    """Every ``s``-th of ``N`` particles, ``s = ⌊N / M⌋``, the first ``M`` of them, with their log weights
    (``None`` stays ``None``); unchanged where ``max_particles`` ``M`` is ``None`` or ``N ≤ M``.
    ``[*B, N, d]``, ``[*B, N]`` -> ``[*B, M, d]``, ``[*B, M]``. After systematic resampling, which lists
    the copies of each ancestor together, the stride is a stratified subsample of the belief.

    Example:
        >>> x = torch.arange(10.0).reshape(1, 10, 1)
        >>> thinned(x, None, 4)[0].flatten().tolist()
        [0.0, 2.0, 4.0, 6.0]
    """
    n = particles.shape[-2]
    if max_particles is None or n <= max_particles:
        return particles, log_weights
    index = slice(0, (n // max_particles) * max_particles, n // max_particles)
    return particles[..., index, :], None if log_weights is None else log_weights[..., index]


class DeepSetsNet(nn.Module):
    """``out = g(ρ(Σ_i w_i φ(x_i)))``: a per-particle encoder φ, weighted pooling, an MLP ρ and a
    linear head g: the body of :class:`DeepSetsActor` (the head gives logits or a Gaussian's
    parameters) and :class:`DeepSetsCritic` (the head gives a value).

    With equal weights the pooling is the mean (the paper's ``(1/n) Σ_i h_i``); with SIR weights
    it is the weighted mean under ``softmax(log_weights)``. The output is invariant to any permutation
    of the particles (applied to particles and weights together).

    Args:
        state_dim: ``d``.
        n_actions: number of outputs: the discrete actions' logits, or ``2·action_dim`` (a Gaussian's
            loc and scale, see :func:`make_deepsets_policy`).
        hidden: width of φ and ρ.
        input_loc, input_scale: particles are standardised as ``(x - loc) / scale`` before φ
            (scalars or ``[d]``).
        encoder_layers: the depth of φ (1: one tanh layer per particle, whose pooled mean is a
            kernel-mean embedding of the belief; the cost of a forward pass is mostly φ over N
            particles, so depth 1 is about four times cheaper than 2 at width 32–64).
        periodic_dims: state indices that are angles (e.g. a pendulum's ``θ``, which its dynamics do
            not wrap): φ reads ``(cos x_i, sin x_i)`` for each instead of the standardised ``x_i``, so
            that ``x_i`` and ``x_i + 2π`` are one input.
        summary: ρ also reads the belief's weighted moments, per input coordinate of φ: the mean
            ``m = Σ_i w_i z_i`` and the log standard deviation ``½·log(Σ_i w_i (z_i − m)² + 10⁻⁶)`` of the
            standardised particles ``z_i``. The pooled embedding of one tanh layer carries the mean only
            through the encoder's saturation; this branch hands it to ρ exactly (a PD rule on the
            belief mean is then one linear map away).

        coordinate_groups: ``None`` (default): one linear head ``g`` on the pooled embedding. Otherwise
            ``G`` tuples of ``k`` state indices, one per group of outputs (e.g. Light-Dark's
            ``((0, 5), (1, 6), …)``: the position and velocity that a pair of actions pushes; a model's
            ``action_coordinates``). Each group ``j`` then gets ``n_actions / G`` outputs from one shared
            network, ``g_c(c_j + e_j, ρ(…))``, where ``c_j = Σ_i w_i φ_c(x_i[group j])`` pools a shared
            encoder of the group's own coordinates and ``e_j`` is a learned embedding of the group. The
            rule "score each coordinate, act on the best" is then learned once for all ``G`` groups
            instead of once per group.
        group_layout: how the ``[G, m]`` group outputs become ``n_actions``: ``group_major``
            (``a = m·j + r``, discrete actions, e.g. ``2i`` / ``2i+1``) or ``output_major``
            (``a = G·r + j``, a Gaussian's ``[loc_1..loc_G, scale_1..scale_G]``).
        group_hidden: the width of ``φ_c`` (16: ``φ_c`` runs on ``G`` times as many inputs as ``φ``; at
            64 the policy's forward pass cost about ten times the pooled head's).
        pooling: how ``φ(x_i)`` becomes one embedding. ``mean`` (default): the weighted mean ``Σ_i w_i φ(x_i)``.
            ``attention``: attention pooling by learned queries (a Set Transformer's PMA with one seed per
            head, as the attention-pooled particle policies use), with ``A = attention_heads`` heads of
            width ``H / A``::

                pooled_a = Σ_i softmax_i(u_aᵀ φ(x_i) + c_a + log w_i) · (V φ(x_i))_a,   a = 1..A,

            concatenated over the heads (a query ``q_a`` and a key map ``K`` enter only as ``u_a = Kᵀ q_a``,
            so they are one linear map). Adding ``log w_i`` to the scores makes it the weighted attention:
            with ``u = 0`` (its initial value) it is the weighted mean of ``V φ(x_i)``. The per-coordinate
            head's group pooling stays the weighted mean.
        attention_heads: ``A``, which must divide ``hidden``.
        max_particles: ``None`` (default): the network reads all ``N`` particles. ``M``: where ``N > M`` it
            reads ``M`` of them, every ``⌊N/M⌋``-th (:func:`thinned`), with their weights renormalised, so
            that its cost stays that of ``M`` particles whatever the filter's ``N`` (a filter with many
            cheap particles, such as SIR at equal time with a dearer one, then costs the policy no more).
            The subset is deterministic: a greedy policy stays a function of the belief.

    Shapes: ``particles`` ``[*B, N, d]``, ``log_weights`` ``[*B, N]`` or ``None`` -> ``[*B, n_actions]``.
    """

    def __init__(self, state_dim: int, n_actions: int, hidden: int = 64,
                 input_loc: float | list[float] = 0.0, input_scale: float | list[float] = 1.0,
                 encoder_layers: int = 2, periodic_dims: tuple[int, ...] | list[int] = (),
                 summary: bool = False, coordinate_groups: tuple[tuple[int, ...], ...] | None = None,
                 group_layout: str = "group_major", group_hidden: int = 16,
                 max_particles: int | None = None, pooling: str = "mean", attention_heads: int = 4) -> None:
        super().__init__()
        self.state_dim, self.n_actions = state_dim, n_actions
        if max_particles is not None and max_particles < 1:
            raise ValueError(f"max_particles: must be >= 1 or None, got {max_particles}")
        self.max_particles = max_particles
        periodic = sorted({int(i) for i in periodic_dims})
        if any(not 0 <= i < state_dim for i in periodic):
            raise ValueError(f"periodic_dims: state indices in [0, {state_dim}), got {list(periodic_dims)}")
        self.periodic = periodic
        self.linear = [i for i in range(state_dim) if i not in periodic]
        self.register_buffer("input_loc", torch.as_tensor(input_loc, dtype=torch.float32).expand(state_dim).clone())
        self.register_buffer("input_scale", torch.as_tensor(input_scale, dtype=torch.float32).expand(state_dim).clone())
        if encoder_layers < 1:
            raise ValueError(f"encoder_layers: must be >= 1, got {encoder_layers}")
        inputs = state_dim + len(periodic)
        self.summary = bool(summary)
        self.phi = _mlp([inputs] + [hidden] * encoder_layers)
        self.rho = _mlp([hidden + (2 * inputs if self.summary else 0), hidden])
        self.head = nn.Linear(hidden, n_actions)
        if pooling not in ("mean", "attention"):
            raise ValueError(f"pooling: mean or attention, got {pooling!r}")
        self.pooling = pooling
        if pooling == "attention":
            if attention_heads < 1 or hidden % attention_heads:
                raise ValueError(f"attention_heads: must be >= 1 and divide hidden={hidden}, got {attention_heads}")
            self.attention_scores = nn.Linear(hidden, attention_heads)  # u_a, c_a
            nn.init.zeros_(self.attention_scores.weight)
            nn.init.zeros_(self.attention_scores.bias)
            self.attention_values = nn.Linear(hidden, hidden, bias=False)  # V
        self.register_buffer("groups", None)
        if coordinate_groups is not None:
            self._build_group_head(coordinate_groups, group_layout, hidden, group_hidden, encoder_layers)

    def _build_group_head(self, coordinate_groups, group_layout: str, hidden: int, group_hidden: int,
                          encoder_layers: int) -> None:
        groups = [tuple(int(i) for i in g) for g in coordinate_groups]
        if not groups or len({len(g) for g in groups}) != 1 or not groups[0]:
            raise ValueError(f"coordinate_groups: expected G >= 1 groups of the same number k >= 1 of state indices, "
                             f"got {coordinate_groups!r}")
        if any(not 0 <= i < self.state_dim for g in groups for i in g):
            raise ValueError(f"coordinate_groups: state indices in [0, {self.state_dim}), got {coordinate_groups!r}")
        if self.periodic:
            raise ValueError("coordinate_groups: not supported with periodic_dims (the groups index the standardised "
                             "state, which periodic coordinates replace by their cosine and sine)")
        if self.n_actions % len(groups):
            raise ValueError(f"coordinate_groups: {len(groups)} groups must divide the {self.n_actions} outputs")
        if group_layout not in ("group_major", "output_major"):
            raise ValueError(f"group_layout: group_major or output_major, got {group_layout!r}")
        self.group_layout = group_layout
        self.register_buffer("groups", torch.tensor(groups, dtype=torch.long))  # [G, k]
        # one-hot [G, k, d']: φ_c's first layer on every group at once is one matmul with a block matrix
        self.register_buffer("group_selector", nn.functional.one_hot(self.groups, self.state_dim).float())
        if group_hidden < 1:
            raise ValueError(f"group_hidden: must be >= 1, got {group_hidden}")
        self.group_in = nn.Linear(len(groups[0]), group_hidden)  # φ_c's first layer (then tanh)
        self.group_rest = _mlp([group_hidden] * encoder_layers)  # its other layers (none at depth 1)
        self.group_embedding = nn.Parameter(torch.zeros(len(groups), group_hidden))
        self.group_head = nn.Sequential(nn.Linear(group_hidden + hidden, hidden), nn.Tanh(),
                                        nn.Linear(hidden, self.n_actions // len(groups)))

    def features(self, particles: Tensor) -> Tensor:
        """φ's input: ``(x − loc) / scale``, with each periodic coordinate as ``(cos x_i, sin x_i)``
        instead. ``[*B, N, d]`` -> ``[*B, N, d + len(periodic_dims)]``."""
        x = (particles - self.input_loc) / self.input_scale
        if not self.periodic:
            return x
        angle = particles[..., self.periodic]
        return torch.cat([x[..., self.linear], torch.cos(angle), torch.sin(angle)], dim=-1)

    def pool(self, particles: Tensor, log_weights: Tensor | None = None) -> Tensor:
        """The pooled belief embedding ``ρ(Σ_i w_i φ(x_i))``: ``[*B, hidden]``."""
        if particles.shape[-1] != self.state_dim:
            raise ValueError(
                f"particles: last dimension {particles.shape[-1]} does not match the actor's "
                f"state_dim {self.state_dim}"
            )
        z = self.features(particles)  # [*B, N, d']
        h = self.phi(z)  # [*B, N, H]
        if log_weights is None:
            w = torch.full_like(z[..., :1], 1.0 / z.shape[-2])
        else:
            w = torch.softmax(log_weights, dim=-1).unsqueeze(-1)  # [*B, N, 1]
        pooled = self.attend(h, log_weights) if self.pooling == "attention" else (w * h).sum(-2)
        if self.summary:
            mean = (w * z).sum(-2)  # [*B, d']
            log_std = 0.5 * torch.log((w * (z - mean.unsqueeze(-2)) ** 2).sum(-2) + 1e-6)
            pooled = torch.cat([pooled, mean, log_std], dim=-1)
        return self.rho(pooled)

    def attend(self, h: Tensor, log_weights: Tensor | None) -> Tensor:
        """Attention pooling (``pooling=attention``): ``h`` ``[*B, N, H]``, ``log_weights`` ``[*B, N]`` or
        ``None`` -> ``[*B, H]``, the heads' weighted attention averages concatenated."""
        scores = self.attention_scores(h)  # [*B, N, A]
        if log_weights is not None:
            scores = scores + torch.log_softmax(log_weights, dim=-1).unsqueeze(-1)
        attention = torch.softmax(scores, dim=-2)  # over the particles
        values = self.attention_values(h).unflatten(-1, (scores.shape[-1], -1))  # [*B, N, A, H/A]
        return (attention.unsqueeze(-1) * values).sum(-3).flatten(-2)

    def encode_group(self, z: Tensor) -> Tensor:
        """``φ_c`` on one group's standardised coordinates ``[*, k]`` -> ``[*, H_c]`` (what :meth:`forward`
        computes for every group at once)."""
        return self.group_rest(torch.tanh(self.group_in(z)))

    def forward(self, particles: Tensor, log_weights: Tensor | None = None) -> Tensor:
        particles, log_weights = thinned(particles, log_weights, self.max_particles)
        context = self.pool(particles, log_weights)  # [*B, H]
        if self.groups is None:
            return self.head(context)
        g, width = self.groups.shape[0], self.group_in.out_features
        # φ_c's first layer on all groups: z [*B, N, d] @ a block matrix [d, G·H_c] (gathering the groups'
        # coordinates instead costs several times more, mostly in the backward pass's scatter)
        block = torch.einsum("gkd,hk->dgh", self.group_selector, self.group_in.weight).flatten(1)
        h = torch.tanh(self.features(particles) @ block + self.group_in.bias.repeat(g))  # [*B, N, G·H_c]
        h = self.group_rest(h.unflatten(-1, (g, width))).flatten(-2)
        if log_weights is None:
            c = h.mean(-2)
        else:
            c = (torch.softmax(log_weights, dim=-1).unsqueeze(-2) @ h).squeeze(-2)  # [*B, G·H_c]
        c = c.unflatten(-1, (g, width)) + self.group_embedding  # [*B, G, H_c]
        out = self.group_head(torch.cat([c, context.unsqueeze(-2).expand(*c.shape[:-1], -1)], dim=-1))  # [*B, G, m]
        if self.group_layout == "output_major":
            out = out.transpose(-1, -2)
        return out.flatten(-2)


class DeepSetsActor(DeepSetsNet):
    """A belief policy's network: ``logits = g(ρ(Σ_i w_i φ(x_i)))`` (:class:`DeepSetsNet`) with
    ``n_actions`` outputs, the discrete actions' logits or ``2·action_dim`` for a Gaussian
    (:func:`make_deepsets_policy`).

    Example:
        >>> actor = DeepSetsActor(state_dim=10, n_actions=10, hidden=16)
        >>> actor(torch.randn(4, 100, 10), torch.zeros(4, 100)).shape
        torch.Size([4, 10])
    """


class DeepSetsCritic(DeepSetsNet):
    """A value network on the belief: ``V(b) = g(ρ(Σ_i w_i φ(x_i)))`` (:class:`DeepSetsNet` with one
    output), for ``trainer.critic_input=belief``. Takes :class:`DeepSetsNet`'s arguments but
    ``n_actions``.

    Example:
        >>> critic = DeepSetsCritic(state_dim=10, hidden=16)
        >>> critic(torch.randn(4, 100, 10), torch.zeros(4, 100)).shape
        torch.Size([4, 1])
    """

    def __init__(self, state_dim: int, **kwargs) -> None:
        super().__init__(state_dim, 1, **kwargs)


def make_deepsets_policy(actor: DeepSetsActor, particles_key: str = "particles",
                         log_weights_key: str | None = "particle_log_weights",
                         action_key: str = "action",
                         action_box: tuple[Tensor, Tensor] | None = None,
                         min_scale: float = DEFAULT_MIN_SCALE,
                         distribution: str = DEFAULT_DISTRIBUTION) -> ProbabilisticActor:
    """Wrap a :class:`DeepSetsActor` as a TorchRL ``ProbabilisticActor``.

    Discrete actions (``action_box=None``): a categorical head. Reads ``particles_key`` (and
    ``log_weights_key`` unless ``None``), writes ``"logits"``, ``action_key`` (int64 index ``[*B]``) and
    ``"action_log_prob"``.

    Continuous actions (``action_box = (low, high)``, tensors ``[A]``; the actor's ``n_actions`` is
    ``2A``): a Gaussian head. The actor's ``2A`` outputs split into ``"loc"`` and ``"scale"``
    (``NormalParamExtractor``: ``scale = max(biased_softplus(·), min_scale)``), and ``distribution`` (a key
    of :data:`~escort_rl.modules.action_heads.CONTINUOUS_DISTRIBUTIONS`) puts the Gaussian in the box:

    - ``tanh_normal``: ``a = low + (high − low)·(tanh(u) + 1)/2`` with ``u ~ N(loc, scale)``, its
      log-probability the change of variables. It has no closed-form entropy; ``ClipPPOLoss`` estimates
      it by sampling.
    - ``clipped_normal``: ``a = clamp(c + h·u, low, high)`` (``c``, ``h`` the box's centre and half-width),
      an atom on each face (:class:`~escort_rl.modules.clipped_normal.ClippedNormal`).

    Either writes a float ``action_key`` ``[*B, A]`` inside the box and ``"action_log_prob"`` ``[*B]``
    (summed over the ``A`` dimensions).

    Example:
        >>> from tensordict import TensorDict
        >>> actor = DeepSetsActor(state_dim=10, n_actions=2 * 5, hidden=16)
        >>> box = (-0.1 * torch.ones(5), 0.1 * torch.ones(5))
        >>> policy = make_deepsets_policy(actor, action_box=box)
        >>> td = TensorDict({"particles": torch.randn(3, 8, 10), "particle_log_weights": torch.zeros(3, 8)}, [3])
        >>> policy(td)["action"].shape
        torch.Size([3, 5])
    """
    in_keys = [particles_key] if log_weights_key is None else [particles_key, log_weights_key]
    if action_box is None:
        module = TensorDictModule(actor, in_keys=in_keys, out_keys=["logits"])
        return ProbabilisticActor(module, in_keys=["logits"], out_keys=[action_key], distribution_class=Categorical,
                                  return_log_prob=True, log_prob_key="action_log_prob")
    module = TensorDictSequential(TensorDictModule(actor, in_keys=in_keys, out_keys=["normal_params"]),
                                  normal_params(min_scale))
    return gaussian_in_box(module, action_box, actor.n_actions, action_key=action_key, distribution=distribution)


def policy_outputs(model) -> tuple[int, tuple[Tensor, Tensor] | None]:
    """What a belief policy of ``model`` outputs: ``(n_actions, None)`` for discrete actions (logits),
    ``(2·action_dim, (action_low, action_high))`` for continuous ones (a Gaussian's loc and scale)."""
    if is_continuous(model):
        return 2 * int(model.action_dim), (model.action_low.cpu(), model.action_high.cpu())
    return int(model.n_actions), None
