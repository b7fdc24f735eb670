"""The package's gymnasium ids, registered when ``escort_rl`` is imported (as ``import ale_py``
registers ALE's): ``gym.make("escort_rl/LightDark10D-v0")`` works after ``import escort_rl``.

Registering imports neither torch nor the models: each id names its entry point by path, and the
episode length is read from ``configs/env/<domain>.yaml`` with PyYAML.
"""

from __future__ import annotations

from functools import lru_cache

import gymnasium as gym

from escort_rl.config.files import config_dir

GYM_IDS = {
    "escort_rl/LightDark10D-v0": "lightdark10d",
    "escort_rl/LightDark10DContinuous-v0": "lightdark10d_continuous",
    "escort_rl/KidnappedRobot20D-v0": "kidnapped20d",
    "escort_rl/MultiTargetTracking20D-v0": "mtt20d",
}
"""gymnasium id -> domain: the model registered under that name with its parameter defaults, and the
episode length ``max_steps`` of ``configs/env/<domain>.yaml`` (which says why)."""


@lru_cache(maxsize=None)
def domain_max_steps(domain: str) -> int:
    """``max_steps`` of ``configs/env/<domain>.yaml``."""
    import yaml

    with open(config_dir() / "env" / f"{domain}.yaml", encoding="utf-8") as fh:
        return int(yaml.safe_load(fh)["max_steps"])


def register_gymnasium_envs() -> None:
    """Register the domains' ids and the flickering Atari and MinAtar ids (idempotent; imports nothing
    from ``ale_py`` or ``minatar``)."""
    from escort_rl.envs.atari import register_atari_envs
    from escort_rl.envs.minatar import register_minatar_envs

    for env_id, domain in GYM_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="escort_rl.envs.gym_adapter:make_domain_gym",
                         max_episode_steps=domain_max_steps(domain), kwargs={"domain": domain})
    register_atari_envs()
    register_minatar_envs()
