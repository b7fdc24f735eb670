"""``bench atari-cost``: the chain of ESCORT-latent's speed choices ends at the settings' defaults,
the timing runs the networks as the trainer does, and the projection's arithmetic."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf

from escort_rl.bench import atari_cost
from escort_rl.bench.atari.settings import load_settings
from escort_rl.modules import FrameGRU, FrameGRUPolicy


@pytest.mark.parametrize("tier", ["atari", "minatar"])
def test_the_chain_ends_at_the_settings_defaults(tier):
    escort = OmegaConf.to_container(load_settings(tier=tier).escort)
    chained = dict(escort)
    for _, change in atari_cost.CHAIN:
        assert set(change) <= set(escort)  # every choice is a setting
        chained.update(change)
    assert chained == escort


def test_a_window_is_timed_with_its_backward_pass():
    torch.manual_seed(0)
    policy = FrameGRUPolicy(FrameGRU(4, 3, hidden=8, frame_size=10))
    seconds = atari_cost.window_seconds_per_frame(policy, (4, 10, 10), num_envs=2, steps=3, repeats=1, device="cpu")
    assert 0 < seconds < math.inf
    assert all(p.grad is not None for p in policy.parameters())  # the loss reached every network


def test_table4_hours():
    assert atari_cost.table4_hours(fps=100.0, frames=50_000_000, games=4, seeds=3) == pytest.approx(
        50_000_000 * 12 / 100 / 3600)


def test_bad_repeats_are_named():
    import argparse

    parser = argparse.ArgumentParser()
    atari_cost.register(parser.add_subparsers())
    args = parser.parse_args(["atari-cost", "--repeats", "0"])
    with pytest.raises(ValueError, match="--repeats: must be at least 1"):
        args.handler(args)
