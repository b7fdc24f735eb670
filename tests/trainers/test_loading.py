"""``escort_rl.load_policy``: a trained policy for a user's own TorchRL loop, the same in a fresh
process as in the one that trained it."""

from __future__ import annotations

import subprocess
import sys

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

import escort_rl
from conftest import tiny_overrides
from escort_rl.config import compose
from escort_rl.trainers.builders import build_actor, build_model
from escort_rl.trainers.checkpointing import load_checkpoint
from escort_rl.trainers.training import train

FRESH = """
import sys, torch, escort_rl
from torchrl.envs.utils import ExplorationType, set_exploration_type
policy = escort_rl.load_policy(sys.argv[1])
td = torch.load(sys.argv[2], weights_only=False)
with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
    out = policy(td.clone())
torch.save({"logits": out["logits"], "action": out["action"]}, sys.argv[3])
"""


def test_a_loaded_policy_acts_as_the_trained_one_in_a_fresh_process(tmp_path):
    run = tmp_path / "run"
    cfg = compose(tiny_overrides("trainer.iterations=1", f"output_dir={run}"))
    train(cfg, progress=False)
    model = build_model(cfg.env)
    trained = build_actor(cfg, model.state_dim, model.n_actions, model)
    load_checkpoint(run, actor=trained)  # the actor as training left it
    g = torch.Generator().manual_seed(0)
    particles = model.initial_belief((6,), int(cfg.num_particles), g)
    td = TensorDict({"particles": particles, "particle_log_weights": torch.zeros(6, particles.shape[-2])},
                    batch_size=[6])
    torch.save(td, tmp_path / "input.pt")

    policy = escort_rl.load_policy(run)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        here = policy(td.clone())
        expected = trained(td["particles"], td["particle_log_weights"])
    torch.testing.assert_close(here["logits"], expected, rtol=0, atol=0)
    assert torch.equal(here["action"], expected.argmax(-1))

    subprocess.run([sys.executable, "-c", FRESH, str(run), str(tmp_path / "input.pt"), str(tmp_path / "out.pt")],
                   check=True, capture_output=True)
    fresh = torch.load(tmp_path / "out.pt")
    torch.testing.assert_close(fresh["logits"], expected, rtol=0, atol=0)
    assert torch.equal(fresh["action"], here["action"])
