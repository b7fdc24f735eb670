"""The filter interface that SIR, SVGD and ESCORT share, with input validation.

A filter is stateless apart from its configuration: the belief is passed in and returned.
Filters know nothing of TorchRL; they see plain tensors and a model.

Filters never return NaN or inf silently. With ``check_finite`` on (the default), ``init`` and
``update`` raise :class:`~escort_rl.belief.checks.NonFiniteError` (a ``ValueError``) naming the
culprit: a non-finite ``belief.particles`` or ``belief.log_weights`` in the input, a model method that
returned NaN or inf (``-inf`` from a log-density is a zero likelihood, and allowed), or a result that
overflowed. The checks cost one host synchronisation per update when all is finite
(:class:`~escort_rl.belief.checks.FiniteGuard`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

from escort_rl.belief.checks import FiniteGuard
from escort_rl.belief.denormals import flush_denormals
from escort_rl.belief.importance import effective_sample_size
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.belief.timing import PartTimer
from escort_rl.models.protocol import (
    action_in_range,
    action_shape,
    check_model_structure,
    describe_action_range,
    is_continuous,
    per_particle,
)


class BeliefFilter(ABC):
    """Base class: ``init`` draws the prior, ``update`` folds in one (action, observation) pair.

    Attributes:
        check_finite: check that the input belief, what the model's methods return and the result
            are finite, and raise a ``ValueError`` naming the culprit if not (default ``True``). The
            check costs one host synchronisation per update; turn it off (``filt.check_finite =
            False``) only where the caller validates the beliefs and the model elsewhere.
    """

    times_own_parts = False
    """Whether :meth:`_update` marks its own parts (:mod:`escort_rl.belief.timing`); if not, the
    whole of it is the part ``update``."""

    @contextmanager
    def timed_parts(self) -> Iterator[dict[str, float]]:
        """Wall-clock seconds of each part of the updates made inside the block, summed over them:
        ``checks`` (validation and the finiteness guard with its host sync), then the filter's own
        parts (ESCORT and SVGD: ``predict``, ``bandwidth``, ``projections``, ``iterations``, ...; the
        others: ``update``), as listed in :mod:`escort_rl.belief.timing`.

        Example:
            >>> import torch, escort_rl
            >>> from escort_rl.models import LinearGaussian
            >>> model, filt = LinearGaussian(state_dim=2, obs_dim=1), escort_rl.make_filter("svgd", num_steps=3)
            >>> belief = filt.init(model, (4,), 20, torch.Generator().manual_seed(0))
            >>> with filt.timed_parts() as parts:
            ...     belief = filt.update(model, belief, torch.zeros(4, dtype=torch.long), torch.zeros(4, 1))
            >>> sorted(parts)
            ['bandwidth', 'checks', 'jitter', 'kernel', 'predict', 'score', 'step']
        """
        parts: dict[str, float] = {}
        previous = self.__dict__.get("_part_times")
        self._part_times = parts
        try:
            yield parts
        finally:
            self._part_times = previous

    def part_timer(self, device: torch.device | str | None = None) -> PartTimer:
        """The :class:`~escort_rl.belief.timing.PartTimer` of this filter's updates: it times into
        the dict of an enclosing :meth:`timed_parts` block, if any."""
        return PartTimer(self.__dict__.get("_part_times"), device)

    @property
    def check_finite(self) -> bool:
        return self.__dict__.get("_check_finite", True)

    @check_finite.setter
    def check_finite(self, value: bool) -> None:
        self._check_finite = validate_check_finite(type(self).__name__, value)

    def _record_importance(self, ess_fraction: Tensor, beta: Tensor) -> None:
        """Accumulate the ESS fractions and tempering exponents ``[*B]`` of one update (no host sync)."""
        e, b = ess_fraction.detach().reshape(-1), beta.detach().reshape(-1)
        stats = (e.sum(), e.min() if e.numel() else e.new_tensor(1.0), (b < 1).sum().to(e.dtype), b.sum(),
                 e.new_tensor(float(e.numel())))
        if self.__dict__.get("_importance") is None:
            self._importance = stats
        else:
            old = self._importance
            self._importance = (old[0] + stats[0], torch.minimum(old[1], stats[1]), old[2] + stats[2],
                                old[3] + stats[3], old[4] + stats[4])

    def importance_diagnostics(self) -> dict:
        """The importance weights the filter formed, over every belief it updated since it was built
        (SIR: its weights before resampling; ESCORT: the target samples of its correlation
        projections): ``mean_ess_fraction`` and ``min_ess_fraction`` (ESS / N, before any
        tempering), ``tempered_fraction`` (the share of beliefs whose weights were tempered),
        ``mean_beta`` (the tempering exponent, 1 when untempered) and ``count`` (beliefs). Empty for a
        filter that formed none."""
        if self.__dict__.get("_importance") is None:
            return {}
        total, low, tempered, beta, count = (float(t) for t in self._importance)
        return {"mean_ess_fraction": total / count, "min_ess_fraction": low, "tempered_fraction": tempered / count,
                "mean_beta": beta / count, "count": int(count)}

    def init(
        self,
        model,
        batch_shape: tuple[int, ...] | torch.Size,
        num_particles: int,
        generator: torch.Generator | None = None,
        start_state: Tensor | None = None,
    ) -> ParticleBelief:
        """The prior belief: ``num_particles`` draws of ``model.initial_belief`` per batch element.

        ``start_state`` ``[*batch_shape, d]``: the episode's start, for a model whose prior is placed
        around it (exploring starts: ``model.prior_width`` set, and ``model.initial_belief_around``);
        ignored otherwise. Returns a belief with particles ``[*batch_shape, num_particles, d]`` and
        equal weights.
        """
        check_model_structure(model)  # the filters check their inputs per update; envs and runs probe the model
        if not isinstance(num_particles, int) or isinstance(num_particles, bool) or num_particles < 1:
            raise ValueError(f"num_particles: expected a positive int, got {num_particles!r}")
        validate_generator(generator)
        batch_shape = validate_batch_shape(batch_shape)
        if start_state is not None and getattr(model, "prior_width", None) is not None:
            if tuple(start_state.shape) != (*batch_shape, model.state_dim):
                raise ValueError(f"start_state: expected shape {(*batch_shape, model.state_dim)}, "
                                 f"got {tuple(start_state.shape)}")
            particles = model.initial_belief_around(start_state, num_particles, generator)
        else:
            particles = model.initial_belief(batch_shape, num_particles, generator)
        if particles.shape[-1] != model.state_dim:
            raise ValueError(
                f"model.initial_belief: returned last dimension {particles.shape[-1]}, "
                f"but model.state_dim is {model.state_dim}"
            )
        guard = FiniteGuard(type(self).__name__, batch_shape, enabled=self.check_finite)
        guard.model_values("model.initial_belief", particles)
        guard.verify()
        return ParticleBelief.uniform(particles)

    def update(
        self,
        model,
        belief: ParticleBelief,
        action: Tensor,
        observation: Tensor | None = None,
        generator: torch.Generator | None = None,
        *,
        observed: Tensor | None = None,
    ) -> ParticleBelief:
        """Fold in ``action`` ``[*B]`` (integer; ``[*B, action_dim]`` real for a model with continuous
        actions) and the next ``observation`` ``[*B, obs_dim]``.

        A missing observation (a sensor dropout): ``observation=None`` predicts only
        (:meth:`predict`); ``observed``, a bool mask ``[*B]``, predicts only the rows where it is
        False (their observation is never read, NaN allowed there). A row that only predicts keeps
        its weights and its log-evidence.

        Returns the posterior belief with particles ``[*B, N, d]``. With ``check_finite``, raises
        ``NonFiniteError`` (a ``ValueError``) naming ``belief.particles``, ``belief.log_weights`` or the
        model method that gave a NaN or inf, after one host synchronisation. When the update fails
        because a model method returns the wrong shape or dtype, or fails on the belief's dtype, the
        ``ValueError`` names that method (see :func:`diagnose_model_outputs`).
        """
        if not isinstance(belief, ParticleBelief):
            raise ValueError(f"belief: expected a ParticleBelief, got {type(belief).__name__}; build it with the "
                             "filter's init, or wrap particles [*B, N, d] with ParticleBelief.uniform(particles)")
        validate_generator(generator)
        if observation is None:
            return self.predict(model, belief, action, generator)
        if observed is not None:
            return self._partly_observed_update(model, belief, action, observation, generator, observed)
        timer = self.part_timer(belief.particles.device)
        with timer(f"{type(self).__name__}.update", timed=False):
            return self._checked_update(timer, model, belief, action, observation, generator)

    def predict(self, model, belief: ParticleBelief, action: Tensor,
                generator: torch.Generator | None = None) -> ParticleBelief:
        """The belief after ``action`` with no observation: every particle moved by
        ``model.transition``, the weights and the log-evidence kept, ``ess`` that of the weights, no
        resampling."""
        with self.part_timer(belief.particles.device)("checks"):
            validate_update_inputs(model, belief, action, None)
        guard = FiniteGuard(type(self).__name__, belief.batch_shape, enabled=self.check_finite)
        guard.input_belief(belief)
        x_next, _ = self._predict(model, belief, action, generator, guard)
        guard.verify()
        ess = effective_sample_size(belief.log_weights)
        return ParticleBelief(x_next, belief.log_weights, belief.log_evidence, ess)

    def _partly_observed_update(self, model, belief, action, observation, generator, observed) -> ParticleBelief:
        """:meth:`update` of the rows where ``observed`` (bool ``[*B]``) is True and :meth:`predict` of the
        others. Every row is updated, the unobserved ones on a stand-in observation (``model.observe``
        of the predicted weighted-mean particle: finite and plausible), then their result is replaced
        by the prediction."""
        if not isinstance(observed, Tensor) or observed.dtype != torch.bool or observed.shape != belief.batch_shape:
            got = (f"dtype {observed.dtype}, shape {tuple(observed.shape)}" if isinstance(observed, Tensor)
                   else type(observed).__name__)
            raise ValueError(f"observed: expected a bool mask of shape {tuple(belief.batch_shape)} (True where the "
                             f"observation arrived), got {got}")
        prediction = self.predict(model, belief, action, generator)
        if isinstance(observation, Tensor) and observation.shape == (*belief.batch_shape, model.obs_dim):
            a = per_particle(model, action, (*belief.batch_shape, 1))
            mean = prediction.mean().unsqueeze(-2)  # [*B, 1, d]
            stand_in = model.observe(mean.to(belief.particles.dtype), a, generator).squeeze(-2)
            observation = torch.where(observed.unsqueeze(-1), observation, stand_in.to(observation.dtype))
        posterior = self.update(model, belief, action, observation, generator)
        keep = observed.unsqueeze(-1)
        return ParticleBelief(torch.where(keep.unsqueeze(-1), posterior.particles, prediction.particles),
                              torch.where(keep, posterior.log_weights, prediction.log_weights),
                              torch.where(observed, posterior.log_evidence, prediction.log_evidence),
                              torch.where(observed, posterior.ess, prediction.ess), posterior.resampled & observed)

    def _checked_update(self, timer: PartTimer, model, belief: ParticleBelief, action: Tensor, observation: Tensor,
                        generator: torch.Generator | None) -> ParticleBelief:
        """:meth:`update`'s checks around :meth:`_update`, each part scoped by ``timer``."""
        with timer("checks"):
            validate_update_inputs(model, belief, action, observation)
            if observation.dtype != belief.particles.dtype:  # e.g. float64 observations of a float32 belief
                observation = observation.to(belief.particles.dtype)
            guard = FiniteGuard(type(self).__name__, belief.batch_shape, enabled=self.check_finite)
            guard.input_belief(belief)
        try:  # a NaN that makes a factorisation fail is named, not a deep traceback
            with guard.diagnosing(), flush_denormals():  # subnormals: slow, and zero to the result
                with timer(None if self.times_own_parts else "update"):
                    posterior = self._update(model, belief, action, observation, generator, guard=guard)
        except (RuntimeError, TypeError, IndexError):  # a model output that does not fit, named
            message = diagnose_model_outputs(model, belief, action, observation)
            if message is None:
                raise
            raise ValueError(message) from None
        with timer("checks"):
            guard.result(posterior)
            guard.verify()
        return posterior

    @staticmethod
    def _predict(model, belief: ParticleBelief, action: Tensor, generator, guard) -> tuple[Tensor, Tensor]:
        """``x̃ = model.transition(x, a)`` for the belief's particles, its shape and values checked
        (``guard`` records them): returns ``x̃`` ``[*B, N, d]`` and the action expanded to ``[*B, N]``
        (``[*B, N, action_dim]`` for real actions)."""
        x = belief.particles
        a = per_particle(model, action, x.shape[:-1])
        x_next = model.transition(x, a, generator)
        check_output_shape("model.transition", x_next, x.shape, "the particles' shape [*B, N, d]")
        guard.model_values("model.transition", x_next)
        return x_next, a

    @abstractmethod
    def _update(
        self,
        model,
        belief: ParticleBelief,
        action: Tensor,
        observation: Tensor,
        generator: torch.Generator | None,
        *,
        guard: FiniteGuard | None = None,
    ) -> ParticleBelief:
        """The update itself, on validated inputs. It records what the model's methods return in
        ``guard`` (``None``: no checks), which :meth:`update` then verifies with one host sync."""


def validate_batch_shape(batch_shape) -> tuple[int, ...]:
    """``batch_shape`` as a tuple of ints ``>= 0``, else ``ValueError`` naming ``batch_shape``."""
    try:
        shape = tuple(batch_shape)
    except TypeError:
        shape = None
    if shape is None or not all(isinstance(b, int) and not isinstance(b, bool) and b >= 0 for b in shape):
        raise ValueError(f"batch_shape: expected a tuple of ints >= 0 (e.g. (32,)), got {batch_shape!r}")
    return shape


def validate_generator(generator) -> None:
    """``ValueError`` naming ``generator`` unless it is a ``torch.Generator`` or ``None``."""
    if generator is not None and not isinstance(generator, torch.Generator):
        raise ValueError(f"generator: expected a torch.Generator or None, got {type(generator).__name__} "
                         f"{generator!r}; pass torch.Generator().manual_seed(seed)")


def validate_update_inputs(model, belief: ParticleBelief, action: Tensor, observation: Tensor | None) -> None:
    """Raise ``ValueError`` naming the field when the update inputs do not fit together
    (``observation=None``: a prediction, whose observation is not checked)."""
    check_model_structure(model)
    x, log_w = belief.particles, belief.log_weights
    if not isinstance(x, Tensor) or x.ndim < 2 or not x.dtype.is_floating_point:
        what = f"shape {tuple(x.shape)}, dtype {x.dtype}" if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"belief.particles: expected a floating-point tensor [*B, N, d], got {what}; build the "
                         "belief with the filter's init")
    if not isinstance(log_w, Tensor) or log_w.shape != x.shape[:-1] or not log_w.dtype.is_floating_point:
        what = f"shape {tuple(log_w.shape)}, dtype {log_w.dtype}" if isinstance(log_w, Tensor) else type(log_w).__name__
        raise ValueError(f"belief.log_weights: expected a floating-point tensor of shape {tuple(x.shape[:-1])} (one "
                         f"per particle, [*B, N]), got {what}")
    batch = belief.batch_shape
    if belief.state_dim != model.state_dim:
        raise ValueError(
            f"belief.particles: last dimension is {belief.state_dim} but model.state_dim is "
            f"{model.state_dim}; build the filter's belief for this model"
        )
    continuous = is_continuous(model)
    shape = (*batch, *action_shape(model))
    if not isinstance(action, Tensor) or action.shape != shape:
        got = tuple(action.shape) if isinstance(action, Tensor) else type(action).__name__
        one = f"a real vector of model.action_dim = {shape[-1]}" if continuous else "one integer"
        raise ValueError(f"action: expected shape {shape} ({one} per belief), got {got}")
    floating = action.dtype.is_floating_point
    if (continuous and not floating) or (not continuous and (floating or action.dtype == torch.bool)):
        kind = "a floating-point tensor (continuous actions)" if continuous else "an integer tensor"
        raise ValueError(f"action: expected {kind}, got dtype {action.dtype}")
    if observation is None:
        if action.numel() and not bool(action_in_range(model, action).all()):
            raise ValueError(f"action: {describe_action_range(model, action)}")
        return
    if not isinstance(observation, Tensor) or observation.shape != (*batch, model.obs_dim):
        shape = tuple(observation.shape) if isinstance(observation, Tensor) else type(observation).__name__
        raise ValueError(
            f"observation: expected shape {(*batch, model.obs_dim)} (batch, model.obs_dim), got {shape}"
        )
    # the action range and the observation's finiteness in one host sync; the messages only on failure
    ok = torch.isfinite(observation).all()
    if action.numel():
        ok = ok & action_in_range(model, action).all()
    if bool(ok):
        return
    if action.numel() and not bool(action_in_range(model, action).all()):
        raise ValueError(f"action: {describe_action_range(model, action)}")
    bad = (~torch.isfinite(observation)).reshape(-1, model.obs_dim).any(-1).nonzero().flatten()
    raise ValueError(
        f"observation: contains NaN or Inf (flat batch indices {bad.tolist()[:8]}); "
        "filters need finite observations"
    )


def check_output_shape(method: str, t: Tensor, shape: tuple[int, ...], what: str,
                       dtype: torch.dtype | None = None) -> None:
    """Raise ``ValueError`` naming model method ``method`` unless it returned a tensor of ``shape``
    (``what`` says what that shape is, e.g. ``"the particles' [*B, N, d]"``) in a floating dtype
    (``dtype``: that one, the particles'). Reads shapes only (no sync)."""
    if not isinstance(t, Tensor) or tuple(t.shape) != tuple(shape) or not t.dtype.is_floating_point \
            or (dtype is not None and t.dtype != dtype):
        got = f"shape {tuple(t.shape)}, dtype {t.dtype}" if isinstance(t, Tensor) else type(t).__name__
        kind = "a floating-point tensor" if dtype is None else f"a {dtype} tensor (the particles' dtype)"
        raise ValueError(f"{method}: returned {got}, expected {kind} of shape {tuple(shape)} ({what})")


def diagnose_model_outputs(model, belief: ParticleBelief, action: Tensor, observation: Tensor) -> str | None:
    """Why an update failed, when a model method is the cause: it raises on the belief's inputs, or
    returns the wrong shape or dtype. Calls ``model.transition``, ``model.observation_log_prob`` and
    ``model.observe`` once on the validated inputs (``action`` ``[*B]``, ``observation`` ``[*B, obs_dim]``
    in the belief's dtype); returns the message naming the method, or ``None`` when all behave. For the
    failure path of :meth:`BeliefFilter.update` only."""
    x = belief.particles
    a = per_particle(model, action, x.shape[:-1])
    fix = "a model method must keep the particles' shape [*B, N, d] and dtype"

    def call(name, fn):
        try:
            return fn(), None
        except Exception as err:  # noqa: BLE001 - named below, with the first line of the cause
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            return None, (f"model.{name}: fails on belief.particles of shape {tuple(x.shape)} and dtype {x.dtype} "
                          f"({type(err).__name__}: {first}); {fix}")

    with torch.no_grad():
        x_next, problem = call("transition", lambda: model.transition(x, a, None))
        if problem is not None:
            return problem
        if not isinstance(x_next, Tensor) or x_next.shape != x.shape or x_next.dtype != x.dtype:
            got = (f"shape {tuple(x_next.shape)}, dtype {x_next.dtype}" if isinstance(x_next, Tensor)
                   else type(x_next).__name__)
            return (f"model.transition: returned {got} for belief.particles of shape {tuple(x.shape)}, dtype "
                    f"{x.dtype}; {fix}")
        lp, problem = call("observation_log_prob",
                           lambda: model.observation_log_prob(observation.unsqueeze(-2), x_next, a))
        if problem is None and (not isinstance(lp, Tensor) or lp.shape != x.shape[:-1]
                                or not lp.dtype.is_floating_point):
            got = f"shape {tuple(lp.shape)}, dtype {lp.dtype}" if isinstance(lp, Tensor) else type(lp).__name__
            problem = (f"model.observation_log_prob: returned {got}, expected one log-density per particle, shape "
                       f"{tuple(x.shape[:-1])} ([*B, N]) in a floating dtype")
        if problem is None:  # the EnKF draws perturbed observations with model.observe
            _, problem = call("observe", lambda: model.observe(x_next, a, None))
    return problem


def validate_check_finite(owner: str, value: object) -> bool:
    """``value`` if it is a bool, else ``ValueError`` naming ``{owner}.check_finite``."""
    if not isinstance(value, bool):
        raise ValueError(f"{owner}.check_finite: must be True or False, got {value!r}")
    return value
