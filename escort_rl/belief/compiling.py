"""``torch.compile`` for a filter, kept apart from its maths.

A filter with ``compile=True`` runs some pure functions of its update through ``torch.compile``
(ESCORT: each iteration, :func:`~escort_rl.belief.evolution.evolution_step`, and the ranks of its
projections). :class:`CompiledFunctions` builds each compiled function once per filter and leaves
them out of a pickled filter (filters travel to env and collector workers; compiled functions do not
pickle, and each worker compiles its own).

What a compiled function needs from its caller:

- **Static shapes** (``dynamic=False``): each shape of the particles is compiled once, then reused.
- **No aliased arguments that alias differently from call to call.** A compiled function is
  specialised on which of its arguments share memory: :func:`unaliased` copies one that would.
- **Enough cache entries.** Dynamo keeps one cache per function, shared by every filter of the
  process: each model, shape and variant (``F_corr``/``F_temp`` on or off) is an entry. Past its
  default limit of 8 it would silently run eager, so the limit is raised to
  :data:`COMPILE_CACHE_ENTRIES`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

COMPILE_CACHE_ENTRIES = 64  # compiled variants kept per function


class CompiledFunctions:
    """``self(fn)``: ``fn`` itself when ``enabled`` is false, else ``torch.compile(fn, dynamic=False)``,
    built on the first call and kept (one per function name)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self._built: dict[str, Callable] = {}

    def __call__(self, fn: Callable) -> Callable:
        if not self.enabled:
            return fn
        if fn.__name__ not in self._built:
            torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, COMPILE_CACHE_ENTRIES)
            self._built[fn.__name__] = torch.compile(fn, dynamic=False)
        return self._built[fn.__name__]

    def __getstate__(self) -> dict:
        return {"enabled": self.enabled, "_built": {}}


def unaliased(anchor: Tensor, t: Tensor | None) -> Tensor | None:
    """``t``, copied if it is ``anchor`` itself: a compiled function taking both would otherwise be
    specialised on their aliasing, which changes once ``anchor`` is replaced."""
    return t.clone() if t is anchor else t
