"""Finiteness checks of a filter update: one host synchronisation when all is well, a named error when not.

A filter records what it must not let through silently as it goes: its input belief, what each
model method returned, the per-particle counts of bad scores met during an evolution, and its
result. Recording only queues small reductions (one pass each: :func:`all_finite`);
:meth:`FiniteGuard.verify` fuses them into one boolean and reads it once (the one host
synchronisation). Only when that boolean is false does the guard inspect the recorded tensors, in
the order they were recorded, and raise a :class:`NonFiniteError` that names the first culprit, e.g.
``model.observation_log_prob returned NaN for 3 particles of belief 0; ...``.

What counts as bad:

- particles, states and other values: NaN, +inf or -inf;
- a log-density (``observation_log_prob``): NaN or +inf. ``-inf`` is a zero likelihood, legitimate;
- log-weights: NaN or +inf, or a belief whose log-weights are all ``-inf`` (no particle has weight).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor

BELIEF_FIX = "check the previous update or the prior (the filter's init)"


class NonFiniteError(ValueError):
    """A filter met a NaN or an infinity: in its input belief, in what a model method returned, or in
    its own result. The message names the field or the method, the belief and the fix."""


# ------------------------------------------------------------------------------------ per-particle flags
# The flags below run inside the (possibly compiled) particle-evolution loop at every iteration. They
# are written with comparisons, which torch.compile vectorises on a CPU, where torch.isnan/isinf/
# isfinite compile to a scalar loop (about 5 ns an entry at [64, 100, 10]).
def is_nan(t: Tensor) -> Tensor:
    """``torch.isnan(t)`` as ``t != t`` (NaN is the only value unequal to itself)."""
    return t != t


def is_inf(t: Tensor) -> Tensor:
    """``torch.isinf(t)`` as ``|t| = inf``."""
    return t.abs() == math.inf


def is_finite(t: Tensor) -> Tensor:
    """``torch.isfinite(t)`` as ``|t| < inf`` (false for NaN and ±inf)."""
    return t.abs() < math.inf


def _true(t: Tensor) -> Tensor:
    """A 0-dim ``True`` on ``t``'s device."""
    return torch.ones((), dtype=torch.bool, device=t.device)


def all_finite(t: Tensor) -> Tensor:
    """0-dim bool: no NaN and no ±inf anywhere in ``t`` (true for an empty ``t``). One pass over memory:
    ``torch.aminmax`` propagates NaN into both ends, so ``min > −inf and max < inf`` holds exactly when every
    entry is finite; ``torch.isfinite(t).all()`` makes four passes and, at ``[64, 3000, 10]``, costs ten times
    as much."""
    if t.numel() == 0 or not t.is_floating_point():  # integers and booleans are finite
        return _true(t)
    low, high = torch.aminmax(t)
    return (low > -math.inf) & (high < math.inf)


def below_inf(t: Tensor) -> Tensor:
    """0-dim bool: no NaN and no +inf in ``t`` (``-inf`` allowed; true for an empty ``t``), in one pass:
    ``amax(t) < inf``, ``amax`` propagating NaN."""
    return _true(t) if t.numel() == 0 or not t.is_floating_point() else t.amax() < math.inf


def log_density_flags(log_density: Tensor, score: Tensor) -> Tensor:
    """Per-particle flags of a log-density and its score, for :func:`log_density_channels`.

    ``log_density`` ``[*S]`` and its gradient ``score`` ``[*S, d]`` -> bool ``[*S, 3]``: the value is
    NaN; the value is +inf; the value is finite but the gradient is not. (A ``-inf`` value is a zero
    density: its gradient is taken as 0, not flagged.)
    """
    finite = is_finite(log_density)
    bad_grad = finite & ~is_finite(score).all(-1)
    return torch.stack([is_nan(log_density), log_density == math.inf, bad_grad], dim=-1)


def log_density_channels(name: str, fix: str) -> tuple[tuple[str, str], ...]:
    """The ``(lead, fix)`` messages of the three flags of :func:`log_density_flags` for ``name``."""
    return ((f"{name} returned NaN", fix), (f"{name} returned +inf", fix),
            (f"{name} has a NaN or infinite gradient", fix))


def value_flags(t: Tensor) -> Tensor:
    """Per-particle flags of values ``t`` ``[*S, d]`` (e.g. a score) -> bool ``[*S, 2]``: some entry
    is NaN; some entry is ±inf."""
    return torch.stack([is_nan(t).any(-1), is_inf(t).any(-1)], dim=-1)


def value_channels(name: str, fix: str) -> tuple[tuple[str, str], ...]:
    """The ``(lead, fix)`` messages of the two flags of :func:`value_flags` for ``name``."""
    return (f"{name} returned NaN", fix), (f"{name} returned inf", fix)


# ------------------------------------------------------------------------------------ descriptions
def _plural(count: int, word: str) -> str:
    return f"{count} {word}" if count == 1 else f"{count} {word}s"


def _belief_name(index: tuple[int, ...]) -> str:
    if not index:
        return "the belief"
    return f"belief {index[0]}" if len(index) == 1 else f"belief {index}"


def _others(n_bad_beliefs: int) -> str:
    return "" if n_bad_beliefs <= 1 else f" (and {_plural(n_bad_beliefs - 1, 'more belief')})"


def _unravel(row: int, batch_shape: Sequence[int]) -> tuple[int, ...]:
    """The batch index of flat belief ``row`` of a ``batch_shape`` batch (``()`` for a single belief)."""
    if not batch_shape:
        return ()
    return tuple(int(i) for i in torch.unravel_index(torch.tensor(row), tuple(batch_shape)))


def describe_particles(kinds: dict[str, Tensor], batch_shape: Sequence[int]) -> str | None:
    """Where per-particle masks ``kinds`` (label -> bool ``[*B, N]``) are true, in words:
    ``"NaN for 3 particles and inf for 1 particle of belief 0 (and 2 more beliefs)"``, about the first
    belief with a true entry; ``None`` when none is. Diagnosis only: it reads the masks on the host."""
    masks = {label: m.detach().reshape(-1, m.shape[-1]).cpu() for label, m in kinds.items()}
    any_bad = torch.stack(list(masks.values())).any(0)  # [prod(B), N]
    rows = any_bad.any(-1).nonzero().flatten().tolist()
    if not rows:
        return None
    row = rows[0]
    parts = [f"{label} for {_plural(int(m[row].sum()), 'particle')}" for label, m in masks.items() if m[row].any()]
    return f"{' and '.join(parts)} of {_belief_name(_unravel(row, batch_shape))}{_others(len(rows))}"


def describe_entries(kinds: dict[str, Tensor]) -> str | None:
    """Like :func:`describe_particles` for a tensor without a particle axis (e.g. a ``[d, d]``
    matrix): ``"NaN in 2 of 16 entries"``; ``None`` when no mask is true."""
    parts = [f"{label} in {int(m.sum())} of {m.numel()} {'entry' if m.numel() == 1 else 'entries'}"
             for label, m in kinds.items() if bool(m.any())]
    return " and ".join(parts) if parts else None


# ------------------------------------------------------------------------------------ the guard
class FiniteGuard:
    """Collects the finiteness conditions of one filter update and checks them with one host sync.

    Args:
        owner: who runs the update, for messages about its own result (e.g. ``"ESCORTFilter"``).
        batch_shape: ``B`` of the beliefs ``[*B, N, d]``.
        enabled: ``False`` makes every method a no-op (no work, no sync).

    Each ``record`` method queues one 0-dim boolean (no sync). :meth:`verify` reads their
    conjunction once; :meth:`diagnosing` names a recorded culprit when an update fails with an
    exception (a NaN can make a decomposition fail before :meth:`verify` is reached).
    """

    def __init__(self, owner: str, batch_shape: Sequence[int], enabled: bool = True) -> None:
        self.owner = owner
        self.batch_shape = tuple(batch_shape)
        self.enabled = enabled
        self._ok: list[Tensor] = []
        self._entries: list[tuple] = []

    # ---------------------------------------------------------------- recording
    def _per_particle(self, t: Tensor) -> bool:
        n_b = len(self.batch_shape)
        return t.ndim >= n_b + 1 and tuple(t.shape[:n_b]) == self.batch_shape

    def values(self, lead: str, t: Tensor, fix: str, per_particle: bool = True) -> None:
        """Every entry of ``t`` must be finite. ``t`` is ``[*B, N, ...]``, counted per particle, or,
        with ``per_particle=False`` (e.g. a ``[d, d]`` matrix), counted per entry. ``lead`` starts
        the message, e.g. ``"model.transition returned"`` or ``"belief.particles:"``."""
        if self.enabled:
            self._ok.append(all_finite(t))
            self._entries.append(("values" if per_particle else "entries", lead, t, fix))

    def log_density(self, lead: str, t: Tensor, fix: str) -> None:
        """``t`` ``[*B, N]`` must hold no NaN and no +inf (``-inf``, a zero density, is allowed)."""
        if self.enabled:
            self._ok.append(below_inf(t))
            self._entries.append(("log_density", lead, t, fix))

    def log_weights(self, lead: str, t: Tensor, fix: str) -> None:
        """``t`` ``[*B, N]`` must hold no NaN and no +inf, and at least one finite value per belief."""
        if self.enabled:
            # each belief's largest log-weight: NaN or +inf propagate to it, and -inf means it has no weight
            largest = t.amax(-1) if t.numel() else t.new_zeros(())
            self._ok.append((largest < math.inf).all() & (largest > -math.inf).all())
            self._entries.append(("log_weights", lead, t, fix))

    def counts(self, channels: Sequence[tuple[str, str]], counts: Tensor | None, when: str) -> None:
        """``counts`` ``[*B, C]`` (integers) must be 0: channel ``c`` counts the particles of each
        belief flagged by ``channels[c] = (lead, fix)`` (e.g. the most flagged at any iteration of an
        evolution, ``when = "during the particle evolution"``). ``None`` records nothing."""
        if self.enabled and counts is not None:
            self._ok.append((counts == 0).all())
            self._entries.append(("counts", tuple(channels), counts, when))

    def input_belief(self, belief) -> None:
        """The input belief: finite particles, and log-weights that are finite or ``-inf`` with at
        least one finite per belief."""
        self.values("belief.particles:", belief.particles,
                    f"a belief's particles must be finite: {BELIEF_FIX}")
        self.log_weights("belief.log_weights:", belief.log_weights,
                         f"log-weights must be finite, or -inf for a zero weight: {BELIEF_FIX}")

    def model_values(self, method: str, t: Tensor, per_particle: bool = True) -> None:
        """What model method ``method`` (e.g. ``"model.transition"``) returned: every entry finite
        (``per_particle`` as :meth:`values`)."""
        self.values(f"{method} returned", t,
                    f"the model's {method.split('.')[-1]} must return finite values for finite inputs", per_particle)

    def model_log_density(self, method: str, t: Tensor) -> None:
        """A log-density ``[*B, N]`` that model method ``method`` returned: no NaN, no +inf."""
        self.log_density(f"{method} returned", t,
                         f"a log-density may be -inf (zero likelihood) but never NaN or +inf; check the model's "
                         f"{method.split('.')[-1]} for these states")

    def result(self, belief) -> None:
        """The belief an update returns (its inputs and the model's outputs having passed)."""
        fix = (f"the inputs and the model's outputs were finite, so the {belief.particles.dtype} arithmetic "
               "overflowed; check the scale of the model and of the filter's arguments")
        self.values(f"{self.owner}.update: its result's belief.particles have", belief.particles, fix)
        self.log_weights(f"{self.owner}.update: its result's belief.log_weights have", belief.log_weights, fix)

    # ---------------------------------------------------------------- checking
    def verify(self) -> None:
        """Raise :class:`NonFiniteError` naming the first culprit if any recorded condition fails.
        Costs one host synchronisation (none when nothing was recorded or the guard is off)."""
        if not self.enabled or not self._ok:
            return
        ok = self._ok[0] if len(self._ok) == 1 else torch.stack(self._ok).all()
        if bool(ok):  # the one host synchronisation
            return
        message = self.first_culprit()
        raise NonFiniteError(message or f"{self.owner}.update: a finiteness check failed, but its source could "
                                        "not be named; rerun with float64 and check the model's outputs")

    def first_culprit(self) -> str | None:
        """The message about the first recorded tensor that breaks its condition; ``None`` if none.
        Reads the recorded tensors on the host: for the failure path only."""
        for kind, lead, t, fix in self._entries:
            if kind == "counts":
                message = self._describe_counts(lead, t, fix)
                if message is not None:
                    return message
                continue
            where = self._describe(kind, t.detach())
            if where is not None:
                return f"{lead} {where}; {fix}"
        return None

    def _describe_counts(self, channels, counts: Tensor, when: str) -> str | None:
        flat = counts.detach().cpu().reshape(-1, counts.shape[-1])  # [prod(B), C]
        for c, (lead, fix) in enumerate(channels):
            rows = (flat[:, c] > 0).nonzero().flatten().tolist()
            if rows:
                row = rows[0]
                return (f"{lead} for up to {_plural(int(flat[row, c]), 'particle')} of "
                        f"{_belief_name(_unravel(row, self.batch_shape))}{_others(len(rows))} {when}; {fix}")
        return None

    def _describe(self, kind: str, t: Tensor) -> str | None:
        if kind in ("values", "entries"):
            kinds = {"NaN": torch.isnan(t), "inf": torch.isinf(t)}
        else:  # log_density, log_weights: -inf is allowed
            kinds = {"NaN": torch.isnan(t), "+inf": torch.isposinf(t)}
        if kind == "entries" or not self._per_particle(t):  # (a model may return an unexpected shape)
            return describe_entries(kinds)
        n_b = len(self.batch_shape)
        per_particle = {label: m.reshape(*m.shape[: n_b + 1], -1).any(-1) for label, m in kinds.items()}
        where = describe_particles(per_particle, self.batch_shape)
        if where is None and kind == "log_weights":
            rows = (~torch.isfinite(t).any(-1)).reshape(-1).nonzero().flatten().tolist()
            if rows:
                belief = _belief_name(_unravel(rows[0], self.batch_shape))
                where = f"every log-weight -inf in {belief}{_others(len(rows))} (no particle has weight)"
        return where

    @contextlib.contextmanager
    def diagnosing(self) -> Iterator[None]:
        """Run a block; if it raises (e.g. a Cholesky factorisation or an eigendecomposition fails
        because a NaN reached it), raise instead a :class:`NonFiniteError` naming a recorded
        non-finite culprit, when there is one. Otherwise the exception passes unchanged."""
        try:
            yield
        except NonFiniteError:
            raise
        except Exception:
            message = self.first_culprit() if self.enabled else None
            if message is None:
                raise
            raise NonFiniteError(message) from None


OFF = FiniteGuard("", (), enabled=False)
"""A guard that records nothing: what a filter's ``_update`` uses when it is called without one."""

