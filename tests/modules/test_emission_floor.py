"""The floor on the emission's learned standard deviation (``emission_min_std``), and the belief
agents' own rate (``trainer.belief_lr``) in the bench's settings."""

import math

import torch
from omegaconf import OmegaConf

from escort_rl.modules import DVRL, ESCORTLatent


def _scale(emission, *args):
    return emission(*args).base_dist.scale


def test_image_emission_std_is_floored_and_flat_below_the_floor():
    floored = DVRL((4, 10, 10), 3, latent_dim=4, hidden=8, num_particles=2, encoding_dim=8, emission_min_std=0.1)
    free = DVRL((4, 10, 10), 3, latent_dim=4, hidden=8, num_particles=2, encoding_dim=8)
    h, z, a = torch.zeros(1, 2, 8), torch.zeros(1, 2, 4), torch.zeros(1, 2, 8)
    for model in (floored, free):
        with torch.no_grad():
            model.emission.log_std.fill_(-10.0)
    assert torch.allclose(_scale(floored.emission, h, z, a), torch.tensor(0.1))
    assert torch.allclose(_scale(free.emission, h, z, a), torch.tensor(math.exp(-10.0)))
    frame = torch.zeros(1, 2, 4, 10, 10)
    floored.emission(h, z, a).log_prob(frame).sum().backward()
    assert floored.emission.log_std.grad.abs().item() == 0.0  # below the floor the ELBO cannot push it further


def test_feature_emission_of_escort_latent_is_floored_too():
    model = ESCORTLatent((4, 10, 10), 3, latent_dim=4, hidden=8, num_particles=2, encoding_dim=8,
                         likelihood="features", emission_min_std=0.1)
    with torch.no_grad():
        model.emission.log_std.fill_(-10.0)
    h, z, a = torch.zeros(1, 2, 8), torch.zeros(1, 2, 4), torch.zeros(1, 2, 8)
    assert torch.allclose(_scale(model.emission, h, z, a), torch.tensor(0.1))


def test_the_settings_give_the_belief_agents_their_floor_and_rate():
    from escort_rl.bench.atari.settings import load_settings
    from escort_rl.trainers.atari_a2c import agent_lr, build_atari_policy

    settings = load_settings(("trainer.belief_lr=0.0003",), tier="minatar")
    for agent, lr in (("gru", float(settings.trainer.lr)), ("dvrl", 3e-4), ("escort_latent", 3e-4)):
        cfg = OmegaConf.create({**OmegaConf.to_container(settings, resolve=True), "agent": agent})
        cfg.escort.compile = False
        assert agent_lr(cfg) == lr
        if agent != "gru":
            emission = build_atari_policy(cfg, (4, 10, 10), 3).dvrl.emission
            assert emission.min_log_std == math.log(float(settings.vrnn.emission_min_std))
    atari = load_settings(tier="atari")
    assert atari.trainer.belief_lr is None and atari.vrnn.emission_min_std == 0.0  # Atari keeps DVRL's own
