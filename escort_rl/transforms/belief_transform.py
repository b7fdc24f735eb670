"""BeliefTransform: keeps each environment's particle belief in the tensordict across steps."""

from __future__ import annotations

import hashlib

import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs.transforms import Compose, Transform, TransformedEnv

from escort_rl.belief.base import BeliefFilter
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.models.protocol import check_model, is_continuous


class BeliefTransform(Transform):
    """Tracks a particle belief per environment with any filter (SIR, SVGD, ESCORT).

    On reset it writes the prior ``filter.init(model, ...)`` into the rows being reset; on each step
    it reads the root particles and ``action`` and the next ``observation``, and writes the updated
    belief under ``next``. Keys (``B`` = env batch size, ``N`` = ``num_particles``, ``d`` = state dim):

    - ``particles_key`` (default ``"particles"``): ``[*B, N, d]``.
    - ``log_weights_key`` (default ``"particle_log_weights"``): ``[*B, N]``, normalised.
    - ``log_evidence_key`` (default ``"log_evidence"``): ``[*B]``, the belief's running
      ``log p̂(o_1:t)`` since the episode's reset (0 there; see
      :class:`~escort_rl.belief.ParticleBelief`).
    - ``ess_key`` (default ``"ess"``): ``[*B]``, the effective sample size of the update's weights
      before any resampling (``N`` at a reset).
    - ``resampled_key`` (default ``"resampled"``): bool ``[*B]``, whether the update resampled.

    A sensor dropout: where ``next`` holds a bool ``observed_key`` (default ``"observed"``, ``[*B]``;
    written by a transform before this one, or by the env), the rows where it is False predict only
    (the observation there is never read) and keep their log-evidence.

    Every key is registered in the observation spec; the belief and its log-evidence, which the next
    step reads, also in the state spec: ParallelEnv ships only state-spec keys to its workers, so an
    observation-only spec would lose the particles there.

    Args:
        model: the POMDP model the filter uses (the env's model, or an approximation of it).
        filter: a :class:`escort_rl.belief.BeliefFilter`.
        num_particles: ``N``.
        observation_key, action_key: where the observation and the action are read.
        particles_key, log_weights_key: where the belief is written.
        log_evidence_key, ess_key, resampled_key: where its diagnostics are written.
        observed_key: where an optional mask of the observations that arrived is read.
        seed: the seed of the filter's randomness until the env is seeded (see below).

    Seeding: ``env.set_seed(s)`` and ``collector.set_seed(s)`` seed the belief wherever the
    transform sits, directly on a :class:`escort_rl.envs.POMDPEnv` or on top of a ``SerialEnv`` or
    ``ParallelEnv``, and the same ``s`` reproduces the same particles, however often it is called:

    - ``seed=None`` on a base env that holds its own ``generator`` in this process (as
      :class:`escort_rl.envs.POMDPEnv` does): the filter draws from that generator, which
      ``env.set_seed`` reseeds.
    - Otherwise the transform has its own generator. ``env.set_seed(s)`` reseeds it with a seed
      hashed from ``(s, seed)`` (see :func:`derive_seed`: unrelated to the seeds the env gives its
      sub-envs, so the filter's noise does not replay the env's); before any ``env.set_seed`` it
      is seeded with ``seed``, or from OS entropy when ``seed`` is ``None`` (as an unseeded
      :class:`escort_rl.envs.POMDPEnv` is).

    Draws made before the first ``set_seed`` follow the construction seeds only. A collector resets
    its env when it is built, so reset it after ``collector.set_seed(s)`` (``collector.reset()``)
    when the transform has no seed of its own and sits on a batched env.

    TorchRL 0.14 gives transforms no seeding hook (``TransformedEnv.set_seed`` only seeds the base
    env), so when the transform joins a ``TransformedEnv`` it wraps that env's ``set_seed`` to seed
    the beliefs after the base env.
    """

    def __init__(
        self,
        model,
        filter: BeliefFilter,
        num_particles: int,
        observation_key: str = "observation",
        action_key: str = "action",
        particles_key: str = "particles",
        log_weights_key: str = "particle_log_weights",
        seed: int | None = None,
        log_evidence_key: str = "log_evidence",
        ess_key: str = "ess",
        resampled_key: str = "resampled",
        observed_key: str = "observed",
    ) -> None:
        check_model(model)
        if not isinstance(filter, BeliefFilter):
            raise TypeError(f"filter: expected a BeliefFilter, got {type(filter).__name__}")
        if not isinstance(num_particles, int) or num_particles < 1:
            raise ValueError(f"num_particles: expected a positive int, got {num_particles!r}")
        super().__init__(in_keys=[observation_key, action_key],
                         out_keys=[particles_key, log_weights_key, log_evidence_key, ess_key, resampled_key])
        self.model = model
        self.filter = filter
        self.num_particles = num_particles
        self.observation_key, self.action_key = observation_key, action_key
        self.particles_key, self.log_weights_key = particles_key, log_weights_key
        self.log_evidence_key, self.ess_key, self.resampled_key = log_evidence_key, ess_key, resampled_key
        self.observed_key = observed_key
        self._seed = seed
        self._env_seeded = False  # whether env.set_seed has reached the transform since `seed`
        self._env_seed: int | None = None
        self._generator: torch.Generator | None = None

    # ------------------------------------------------------------------ randomness
    def set_seed(self, seed: int | None) -> None:
        """Give the transform its own seed: its generator restarts from ``seed`` (``None``: OS
        entropy, or the base env's generator where it has one), and an earlier ``env.set_seed``
        no longer applies until the env is seeded again."""
        self._seed = seed
        self._env_seeded = False
        self._env_seed = None
        self._generator = None

    def _set_seed(self, seed: int | None) -> None:
        """Called by ``env.set_seed(seed)`` on the env that contains the transform: restart the
        generator from a seed derived from ``seed`` and the transform's own seed (``seed=None``:
        OS entropy, as the base env does)."""
        self._env_seeded = True
        self._env_seed = seed
        self._generator = None

    def _shared_generator(self, device) -> torch.Generator | None:
        """The base env's generator, where the filter shares it (no seed of its own, a base env
        holding a generator on ``device`` in this process)."""
        if self._seed is not None:
            return None
        try:
            container = self.container
        except (AttributeError, ValueError):  # not (yet) in an env
            return None
        base_env = getattr(container, "base_env", container)
        # read the instance dict: a batched env's attribute lookup would query its workers
        shared = getattr(base_env, "__dict__", {}).get("generator", None)
        if isinstance(shared, torch.Generator) and shared.device == torch.device(device):
            return shared
        return None

    def _get_generator(self, device: torch.device) -> torch.Generator:
        shared = self._shared_generator(device)
        if shared is not None:
            return shared
        if self._generator is None or self._generator.device != torch.device(device):
            self._generator = torch.Generator(device=device)
            if self._env_seeded:
                seed = None if self._env_seed is None else derive_seed(self._env_seed, self._seed)
            else:
                seed = self._seed
            if seed is None:
                self._generator.seed()
            else:
                self._generator.manual_seed(int(seed))
        return self._generator

    def generator_state(self) -> torch.Tensor | None:
        return None if self._generator is None else self._generator.get_state()

    # ------------------------------------------------------------------ specs
    def _belief_specs(self, batch_shape: torch.Size, device) -> dict:
        """The specs of what the next step reads: the belief and its running log-evidence."""
        n, d = self.num_particles, self.model.state_dim
        return {
            self.particles_key: Unbounded(shape=(*batch_shape, n, d), dtype=torch.float32, device=device),
            self.log_weights_key: Unbounded(shape=(*batch_shape, n), dtype=torch.float32, device=device),
            self.log_evidence_key: Unbounded(shape=tuple(batch_shape), dtype=torch.float32, device=device),
        }

    def _diagnostic_specs(self, batch_shape: torch.Size, device) -> dict:
        """The specs of the update's own diagnostics (observation only)."""
        return {
            self.ess_key: Unbounded(shape=tuple(batch_shape), dtype=torch.float32, device=device),
            self.resampled_key: Categorical(2, shape=tuple(batch_shape), dtype=torch.bool, device=device),
        }

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._check_env(observation_spec)
        shape, device = observation_spec.shape, observation_spec.device
        for key, spec in {**self._belief_specs(shape, device), **self._diagnostic_specs(shape, device)}.items():
            observation_spec[key] = spec
        return observation_spec

    def _check_env(self, observation_spec: Composite) -> None:
        """Refuse a model whose ``obs_dim``, ``state_dim`` or actions differ from the env's."""
        obs_spec = observation_spec.get(self.observation_key, None)
        if obs_spec is None:
            raise KeyError(
                f"BeliefTransform.observation_key: the env has no '{self.observation_key}' in its "
                "observation spec"
            )
        if obs_spec.shape[-1] != self.model.obs_dim:
            raise ValueError(
                f"BeliefTransform.model: model.obs_dim is {self.model.obs_dim} but the env's "
                f"'{self.observation_key}' has last dimension {obs_spec.shape[-1]}; pass the env's model"
            )
        true_state = observation_spec.get("true_state", None)
        if true_state is not None and true_state.shape[-1] != self.model.state_dim:
            raise ValueError(
                f"BeliefTransform.model: model.state_dim is {self.model.state_dim} but the env's "
                f"'true_state' has last dimension {true_state.shape[-1]}; pass the env's model"
            )
        self._check_actions()

    def _check_actions(self) -> None:
        """Refuse a model whose actions differ from the env's action spec: ``n_actions`` against a
        ``Categorical``'s ``n``, ``action_dim`` against a ``Bounded``'s last dimension."""
        parent = getattr(self, "parent", None)
        action_spec = parent.full_action_spec.get(self.action_key, None) if parent is not None else None
        if action_spec is None:
            return
        n = getattr(action_spec, "n", None)
        if is_continuous(self.model):
            if n is not None or action_spec.shape[-1:] != (self.model.action_dim,):
                raise ValueError(
                    f"BeliefTransform.model: the model takes real actions of action_dim {self.model.action_dim} but "
                    f"the env's '{self.action_key}' spec is {type(action_spec).__name__} of shape "
                    f"{tuple(action_spec.shape)}; pass the env's model"
                )
            space = getattr(action_spec, "space", None)
            low, high = getattr(space, "low", None), getattr(space, "high", None)
            if low is not None and high is not None and not (
                    torch.equal(low.reshape(-1, low.shape[-1])[0].cpu(), self.model.action_low.float().cpu())
                    and torch.equal(high.reshape(-1, high.shape[-1])[0].cpu(), self.model.action_high.float().cpu())):
                raise ValueError(
                    f"BeliefTransform.model: the model's action box [{self.model.action_low.tolist()}, "
                    f"{self.model.action_high.tolist()}] differs from the env's '{self.action_key}' bounds; pass the "
                    "env's model"
                )
        elif n is None or int(n) != int(self.model.n_actions):
            what = f"{n} actions" if n is not None else f"a {type(action_spec).__name__} spec (real actions)"
            raise ValueError(
                f"BeliefTransform.model: model.n_actions is {self.model.n_actions} but the env's "
                f"'{self.action_key}' has {what}; pass the env's model"
            )

    def set_container(self, container) -> None:
        super().set_container(container)
        parent = getattr(self, "parent", None)
        if parent is not None:  # check when the transform joins an env, not at its first reset
            self._check_env(parent.full_observation_spec)
        try:
            env = self.container
        except ValueError:  # inside a Compose that has no env yet: Compose.set_container calls again
            env = None
        if isinstance(env, TransformedEnv):
            _seed_beliefs_with_env(env)

    def transform_state_spec(self, state_spec: Composite) -> Composite:
        for key, spec in self._belief_specs(state_spec.shape, state_spec.device).items():
            state_spec[key] = spec
        return state_spec

    # ------------------------------------------------------------------ reset and step
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        device = tensordict_reset.device or torch.device("cpu")
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        rows = torch.ones(batch, dtype=torch.bool, device=device) if reset is None else reset.reshape(batch)
        n, d = self.num_particles, self.model.state_dim
        old_x = tensordict.get(self.particles_key, None) if tensordict is not None else None
        old_w = tensordict.get(self.log_weights_key, None) if tensordict is not None else None
        particles = old_x.clone() if old_x is not None else torch.zeros(*batch, n, d, device=device)
        log_w = (old_w.clone() if old_w is not None
                 else torch.full((*batch, n), -float(torch.log(torch.tensor(n))), device=device))
        k = int(rows.sum())
        if k:
            # the env's start state places the prior only where the model asks for it (exploring
            # starts with model.prior_width); the filter never sees it otherwise
            start = tensordict_reset.get("true_state", None)
            if start is None and getattr(self.model, "prior_width", None) is not None:
                raise ValueError("BeliefTransform: the model places its prior around each episode's start "
                                 f"(prior_width={self.model.prior_width}), but the env writes no 'true_state'; "
                                 "build the env with POMDPEnv(..., expose_state=True)")
            prior = self.filter.init(self.model, (k,), n, self._get_generator(device),
                                     start_state=None if start is None else start[rows])
            particles[rows] = prior.particles.to(device, torch.float32)
            log_w[rows] = prior.log_weights.to(device, torch.float32)
        tensordict_reset.set(self.particles_key, particles)
        tensordict_reset.set(self.log_weights_key, log_w)
        kept = ParticleBelief(particles, log_w)  # the rows being reset: log-evidence 0, ESS of equal weights
        for key, value, old in ((self.log_evidence_key, kept.log_evidence, self.log_evidence_key),
                                (self.ess_key, kept.ess, self.ess_key), (self.resampled_key, kept.resampled, None)):
            previous = tensordict.get(old, None) if tensordict is not None and old is not None else None
            tensordict_reset.set(key, value if previous is None else torch.where(rows, value, previous))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        particles = tensordict.get(self.particles_key, None)
        if particles is None:
            raise KeyError(
                f"BeliefTransform: '{self.particles_key}' is missing from the input tensordict; "
                "call env.reset() before env.step()"
            )
        belief = ParticleBelief(particles, tensordict.get(self.log_weights_key),
                                log_evidence=tensordict.get(self.log_evidence_key, None))
        action = tensordict.get(self.action_key)
        observation = next_tensordict.get(self.observation_key)
        device = particles.device
        observed = next_tensordict.get(self.observed_key, None)
        if observed is not None:
            observed = observed.reshape(belief.batch_shape)
        new = self.filter.update(self.model, belief, action, observation, self._get_generator(device),
                                 observed=observed)
        next_tensordict.set(self.particles_key, new.particles.to(torch.float32))
        next_tensordict.set(self.log_weights_key, new.log_weights.to(torch.float32))
        next_tensordict.set(self.log_evidence_key, new.log_evidence.to(torch.float32))
        next_tensordict.set(self.ess_key, new.ess.to(torch.float32))
        next_tensordict.set(self.resampled_key, new.resampled)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError(
            "BeliefTransform is an environment transform: append it to a TransformedEnv, "
            "it cannot be applied to stored data"
        )


def derive_seed(env_seed: int, own_seed: int | None) -> int:
    """The belief generator's seed after ``env.set_seed(env_seed)``: a 63-bit hash of both seeds,
    so that it differs from the seeds the env hands to its sub-envs."""
    own = None if own_seed is None else int(own_seed)
    digest = hashlib.sha256(f"escort_rl.BeliefTransform:{int(env_seed)}:{own}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2**63 - 1)


def _belief_transforms(transform) -> list[BeliefTransform]:
    if isinstance(transform, BeliefTransform):
        return [transform]
    if isinstance(transform, Compose):
        return [t for sub in transform.transforms for t in _belief_transforms(sub)]
    return []


class _SetSeedWithBeliefs:
    """Stands in for ``set_seed`` on a TransformedEnv holding a BeliefTransform: seeds the base env
    as TransformedEnv.set_seed does, then every BeliefTransform of the env with the same seed.
    A plain picklable object (no closure), so that the env can still be pickled or deep-copied."""

    def __init__(self, env: TransformedEnv) -> None:
        self.env = env

    def __call__(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        env = self.env
        out = type(env).set_seed(env, seed, static_seed=static_seed)
        for transform in _belief_transforms(env.transform):
            transform._set_seed(seed)
        return out


def _seed_beliefs_with_env(env: TransformedEnv) -> None:
    hook = env.__dict__.get("set_seed")
    if not (isinstance(hook, _SetSeedWithBeliefs) and hook.env is env):
        env.__dict__["set_seed"] = _SetSeedWithBeliefs(env)
