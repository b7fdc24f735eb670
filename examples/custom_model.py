"""Your own POMDP, end to end: a model in one file, trained with PPO on ESCORT beliefs, evaluated,
and its policy loaded back.

The model is a room heater with a hidden drift: the state is (temperature, drift), the heater
pushes the temperature up, down or not at all, the drift wanders slowly and a noisy thermometer
reads the temperature. The reward is -|temperature| (hold it at 0): there is no goal and no end, so
evaluation reports the return alone. Nothing here imports escort_rl: any object with these
attributes and methods is a model (escort_rl.models.POMDPModel).

    python examples/custom_model.py            # a tiny budget: about a minute on two cores
    python examples/custom_model.py --iterations 30 --output outputs/heater
"""

from __future__ import annotations

import argparse
import math

import torch


class Heater:
    """State ``[temperature, drift]``; actions 0 (off), 1 (heat), 2 (cool); observation: the
    temperature with Gaussian noise of std ``obs_std``."""

    state_dim, obs_dim, n_actions = 2, 1, 3

    def __init__(self, obs_std: float = 0.5, power: float = 0.2, device: str = "cpu") -> None:
        self.obs_std, self.power, self.device = obs_std, power, torch.device(device)
        self.noise_std = torch.tensor([0.05, 0.01], device=self.device)  # process noise per coordinate
        self.push = torch.tensor([0.0, power, -power], device=self.device)

    def initial_state(self, shape, generator=None):
        return torch.randn(*shape, 2, generator=generator, device=self.device) * torch.tensor([1.0, 0.05])

    def initial_belief(self, shape, n, generator=None):
        return self.initial_state((*shape, n), generator)

    def transition_mean(self, s, a):
        temperature = s[..., 0] + s[..., 1] + self.push[a]
        return torch.stack([temperature, s[..., 1]], -1)

    def transition_scale_tril(self):
        return torch.diag(self.noise_std)

    def transition(self, s, a, generator=None):
        mean = self.transition_mean(s, a)
        return mean + torch.randn(mean.shape, generator=generator, device=self.device) * self.noise_std

    def transition_log_prob(self, s_next, s, a):
        z = (s_next - self.transition_mean(s, a)) / self.noise_std
        return (-0.5 * z**2 - torch.log(self.noise_std) - 0.5 * math.log(2 * math.pi)).sum(-1)

    def observe(self, s_next, a, generator=None):
        noise = torch.randn(s_next.shape[:-1] + (1,), generator=generator, device=self.device)
        return s_next[..., :1] + self.obs_std * noise

    def observation_log_prob(self, o, s_next, a):
        z = (o[..., 0] - s_next[..., 0]) / self.obs_std
        return -0.5 * z**2 - math.log(self.obs_std) - 0.5 * math.log(2 * math.pi)

    def reward(self, s, a, s_next):
        return -s_next[..., 0].abs()

    def is_terminal(self, s):
        return torch.zeros(s.shape[:-1], dtype=torch.bool, device=s.device)


def main() -> None:
    import escort_rl

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=2, help="PPO iterations (the first on SIR beliefs)")
    parser.add_argument("--output", default="outputs/examples/heater", help="the run directory")
    args = parser.parse_args()

    overrides = [f"trainer.iterations={args.iterations}", f"trainer.warm_start_iterations={args.iterations // 2}",
                 "trainer.num_envs=8", "trainer.rollout_steps=25", "trainer.minibatches=2",
                 "trainer.checkpoint_every=1", "env.max_steps=50", "env.input_scale=[2.0,0.1]",
                 "num_particles=32", "filter.compile=false", "evaluate.episodes=16", f"output_dir={args.output}"]
    run_dir = escort_rl.train(overrides, model=Heater(obs_std=0.5), progress=False)
    result = escort_rl.evaluate(run_dir)
    print("trained on", ", ".join(f"{frames} frames of {name}" for name, frames in
                                  result["training"]["frames_by_filter"].items()))
    for name in ("trained", "random"):
        print(f"{name}: return {result[name]['episode_return']:.1f} ± {result[name]['episode_return_se']:.1f}, "
              f"success {result[name]['success_rate']}")  # None: the heater has no goal

    policy = escort_rl.load_policy(run_dir)  # a TensorDictModule on the belief keys
    print(f"policy reads {policy.in_keys} and writes {policy.out_keys}; run: {run_dir}")


if __name__ == "__main__":
    main()
