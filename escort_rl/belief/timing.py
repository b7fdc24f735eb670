"""Where a filter update's time goes: named parts, timed on demand and seen by ``torch.profiler``.

A filter marks the parts of its update with a :class:`PartTimer` (``with timer("predict"): ...``).
Nothing is timed unless asked:

- :meth:`BeliefFilter.timed_parts <escort_rl.belief.base.BeliefFilter.timed_parts>` collects the
  wall-clock seconds of each part over the updates made inside it::

      with filt.timed_parts() as parts:
          filt.update(model, belief, action, observation)
      parts  # {"checks": 0.0004, "predict": 0.0021, ..., "iterations": 0.041}

  On a CUDA device each part synchronises the device at its ends while timed, so its seconds are
  the part's, not its launch's (and the update is slower for it).
- under ``torch.profiler``, each part is also a ``record_function`` scope named
  ``filter::<part>``, so a profile's events group by part (``escort-rl bench profile``); the whole
  update is the scope ``filter::<class name>.update`` (e.g. ``filter::ESCORTFilter.update``).

The parts of every filter's :meth:`~escort_rl.belief.base.BeliefFilter.update`:

===================== ================================================================================
``checks``            input validation, the finiteness guard's checks and its one host sync
``update``            the rest of the update (SIR, EnKF), or, for ESCORT and SVGD:
``predict``           the transition, the predicted prior and the likelihood weights
``temporal_reference`` ``F_temp``'s directions (max-sliced ascent) and sorted reference, once an update
``bandwidth``         the median-heuristic bandwidth (a selection over the N² distances)
``projections``       the correlation projections (eigenvectors of ΔC refined by ascent)
``iterations``        the K iterations, when compiled (one fused graph: its parts are not separable)
``kernel``            eager iterations: the kernel and the SVGD direction φ (distances, exp, K·[s, x])
``score``             eager iterations: the target's score (likelihood and prior)
``correlation``       eager iterations: ``F_corr``
``temporal``          eager iterations: ``F_temp``
``step``              eager iterations: the AdaGrad step
``jitter``            the final jitter
===================== ================================================================================
"""

from __future__ import annotations

import time

import torch


class PartTimer:
    """Times named parts into ``store`` (seconds added per name) and, under ``torch.profiler``,
    opens a ``record_function`` scope ``filter::<name>`` for each. ``store=None``: no timing (the
    scopes still show in a profile). ``device``: a CUDA device is synchronised at each part's ends
    while timing."""

    def __init__(self, store: dict | None, device: torch.device | str | None = None) -> None:
        self.store = store
        self.cuda = store is not None and device is not None and torch.device(device).type == "cuda"

    def __call__(self, name: str | None, timed: bool = True) -> _PartScope:
        """The scope of part ``name`` (``None``: nothing); ``timed=False``: a profiler scope only."""
        return _PartScope(self, name, timed)


class _PartScope:
    __slots__ = ("timer", "name", "timed", "t0", "scope")

    def __init__(self, timer: PartTimer, name: str | None, timed: bool) -> None:
        self.timer, self.name, self.timed, self.scope = timer, name, timed and timer.store is not None, None

    def __enter__(self) -> None:
        if self.name is None:
            return
        if torch.autograd._profiler_enabled():
            self.scope = torch.autograd.profiler.record_function(f"filter::{self.name}")
            self.scope.__enter__()
        if self.timed:
            if self.timer.cuda:
                torch.cuda.synchronize()
            self.t0 = time.perf_counter()

    def __exit__(self, *exc) -> None:
        if self.name is None:
            return
        store = self.timer.store
        if self.timed:
            if self.timer.cuda:
                torch.cuda.synchronize()
            store[self.name] = store.get(self.name, 0.0) + time.perf_counter() - self.t0
        if self.scope is not None:
            self.scope.__exit__(*exc)


class _NoScope:
    __slots__ = ()

    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc) -> None:
        return None


class _NoTimer:
    """Neither times nor opens profiler scopes: what a compiled iteration gets, so that nothing of
    the timing is traced into its graph."""

    store = None

    def __call__(self, name: str | None, timed: bool = True) -> _NoScope:
        return _NoScope()


NO_TIMER = _NoTimer()
