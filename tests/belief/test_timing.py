"""The parts of a filter update: timed on demand (``timed_parts``) and seen by ``torch.profiler``."""

import torch

import escort_rl
from escort_rl.models import LinearGaussian


def _update(filt, timed: bool = True):
    model = LinearGaussian(state_dim=2, obs_dim=1)
    g = torch.Generator().manual_seed(0)
    belief = filt.init(model, (3,), 16, g)
    if not timed:
        return filt.update(model, belief, torch.zeros(3, dtype=torch.long), torch.zeros(3, 1), g), None
    with filt.timed_parts() as parts:
        out = filt.update(model, belief, torch.zeros(3, dtype=torch.long), torch.zeros(3, 1), g)
    return out, parts


def test_escort_parts_eager():
    _, parts = _update(escort_rl.make_filter("escort", num_steps=2))
    assert set(parts) == {"checks", "predict", "temporal_reference", "bandwidth", "projections", "kernel", "score",
                          "correlation", "temporal", "step", "jitter"}
    assert all(v > 0 for v in parts.values())


def test_sir_is_one_part_and_the_checks():
    _, parts = _update(escort_rl.make_filter("sir"))
    assert set(parts) == {"checks", "update"}


def test_timing_ends_with_the_block():
    filt = escort_rl.make_filter("svgd", num_steps=2)
    _, parts = _update(filt)
    before = dict(parts)
    _update(filt, timed=False)
    assert parts == before  # an update outside the block adds nothing


def test_parts_are_profiler_scopes():
    filt = escort_rl.make_filter("escort", num_steps=2)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        _update(filt, timed=False)
    names = {e.key for e in prof.key_averages()}
    assert {"filter::checks", "filter::predict", "filter::projections", "filter::kernel"} <= names
