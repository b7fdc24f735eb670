"""What kind of action a model takes: integers (``n_actions``) or real vectors (``action_dim``)."""

from __future__ import annotations


def is_continuous(model) -> bool:
    """Whether ``model``'s actions are real vectors: it declares ``action_dim`` and no ``n_actions``."""
    return getattr(model, "n_actions", None) is None and getattr(model, "action_dim", None) is not None


def action_shape(model) -> tuple[int, ...]:
    """The shape of one action: ``()`` for an integer action, ``(action_dim,)`` for a real one."""
    return (int(model.action_dim),) if is_continuous(model) else ()
