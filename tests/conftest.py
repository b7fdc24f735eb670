"""Shared test helpers: seeded generators and tiny configs.

- :func:`config_error` (import it too): the one-line message of the ``ConfigError`` an override
  list raises.
- :func:`gen` (import it: ``from conftest import gen``): a CPU generator with a given seed, for tests
  whose expected values were worked out for that seed.
- :func:`hoeffding` (import it): the half-width of a confidence bound on a mean of draws in [0, 1].
- The ``per_test_seed`` and ``per_test_generator`` fixtures: a seed of the test's own, stable (hashed
  from the test's id, so a failure replays) and different between tests (they do not share random
  streams).
- ``pytest --seed-offset K`` shifts every such seed by ``K``, and the ``seed_offset`` fixture hands
  ``K`` to tests that draw from a window of seeds (they start it at ``K``): tests written on these
  fixtures must pass for any offset.
- :func:`actor_of` (import it): the untrained actor of a run's overrides, to load its checkpoints into.
- :func:`one_line_error` (import it): the one-line message of the error a call raises.
- :data:`DRIFT_MODEL_SOURCE` (import it): a user's model module as source text, for `--model` tests.
- :data:`TINY_TRAIN`, :func:`tiny_overrides` and the ``tiny_config`` fixture: the default training job
  at a size that trains in seconds.
"""

from __future__ import annotations

import hashlib
import textwrap

import pytest
import torch

TINY_TRAIN = ["trainer=reinforce", "trainer.num_envs=4", "env.max_steps=12", "num_particles=16", "actor.hidden=16",
              "trainer.minibatch_size=64", "trainer.checkpoint_every=1", "filter.compile=false"]
"""The default job's filter (ESCORT) at a tiny size; eager, because compiling in every test process would
dominate the test time (``tests/belief/test_escort.py`` checks that compiled and eager updates agree)."""


def actor_of(overrides):
    """The actor a run of ``overrides`` trains (the config's head and sizes, for its model), untrained: to
    load a run's checkpoint into."""
    from escort_rl.config import compose
    from escort_rl.modules import policy_outputs
    from escort_rl.trainers.builders import build_actor, build_model

    cfg = compose(list(overrides))
    model = build_model(cfg.env)
    return build_actor(cfg, model.state_dim, policy_outputs(model)[0], model)


def config_error(overrides) -> str:
    """The message of the ``ConfigError`` that composing ``overrides`` raises (it must be one line)."""
    from escort_rl.config import ConfigError, compose

    with pytest.raises(ConfigError) as info:
        compose(overrides)
    message = str(info.value)
    assert "\n" not in message, message
    return message


def hoeffding(n: int, delta: float = 1e-9) -> float:
    """Half-width of a two-sided Hoeffding bound on the mean of ``n`` draws in [0, 1]: a correct
    sampler's mean lies this close to its expectation with probability ``1 - delta``, whatever the seed."""
    import math

    return math.sqrt(math.log(2 / delta) / (2 * n))


def gen(seed: int) -> torch.Generator:
    """A CPU generator seeded with ``seed``."""
    return torch.Generator().manual_seed(seed)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--seed-offset", type=int, default=0,
                     help="shift the seeds of the tests that take the per_test_seed, per_test_generator or "
                          "seed_offset fixture (they must pass for any offset)")


def stable_seed(test_id: str, offset: int = 0) -> int:
    """A 31-bit seed hashed from a test id (stable across runs and machines), plus ``offset``."""
    digest = hashlib.sha256(test_id.encode()).digest()
    return (int.from_bytes(digest[:4], "little") + offset) % 2**31


@pytest.fixture
def seed_offset(request: pytest.FixtureRequest) -> int:
    """``--seed-offset`` (default 0): where a test that draws from a window of seeds starts it."""
    return request.config.getoption("--seed-offset")


@pytest.fixture
def per_test_seed(request: pytest.FixtureRequest, seed_offset: int) -> int:
    """This test's seed: hashed from its id (parameters included), shifted by ``--seed-offset``."""
    return stable_seed(request.node.nodeid, seed_offset)


@pytest.fixture
def per_test_generator(per_test_seed: int) -> torch.Generator:
    """A CPU generator seeded with this test's :func:`per_test_seed`."""
    return gen(per_test_seed)


def tiny_overrides(*overrides: str) -> list[str]:
    """:data:`TINY_TRAIN` with ``overrides`` on top: an override replaces the tiny entry of the same key,
    and one that picks a group's option (``filter=sir``) drops the tiny entries inside that group
    (``filter.compile``, a key of the default filter only)."""
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    kept = [t for t in TINY_TRAIN
            if (key := t.split("=", 1)[0]) not in keys and not any(key.startswith(f"{k}.") for k in keys)]
    return [*kept, *overrides]


@pytest.fixture
def tiny_config():
    """``tiny_config(*overrides)``: the composed config of :func:`tiny_overrides`."""
    from escort_rl.config import compose

    def make(*overrides: str):
        return compose(tiny_overrides(*overrides))

    return make


@pytest.fixture(scope="module")
def local_ray():
    """A fresh local Ray of 2 CPUs for one test module, whatever the machine's ``RAY_ADDRESS`` or
    last-started cluster says (``address="local"``, with ``RAY_ADDRESS`` unset meanwhile)."""
    import ray  # the ray extra: make test installs it

    with pytest.MonkeyPatch.context() as patch:
        patch.delenv("RAY_ADDRESS", raising=False)
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
        try:
            yield ray
        finally:
            ray.shutdown()


DRIFT_MODEL_SOURCE = textwrap.dedent('''
    import math
    import torch

    class Drift:
        """A 2-D random walk seen through noise, on the model protocol (no escort_rl import)."""
        n_actions = 2

        def __init__(self, obs_std=0.5):
            if float(obs_std) <= 0:
                raise ValueError(f"obs_std must be > 0, got {obs_std}")
            self.state_dim = self.obs_dim = 2
            self.obs_std = float(obs_std)

        def initial_state(self, shape, generator=None):
            return torch.randn(*shape, 2, generator=generator)

        def initial_belief(self, shape, n, generator=None):
            return torch.randn(*shape, n, 2, generator=generator)

        def transition_mean(self, s, a):
            return s + 0.1 * (2.0 * a.unsqueeze(-1).to(s.dtype) - 1.0)

        def transition_scale_tril(self):
            return 0.3 * torch.eye(2)

        def transition(self, s, a, generator=None):
            return self.transition_mean(s, a) + 0.3 * torch.randn(s.shape, generator=generator)

        def transition_log_prob(self, s_next, s, a):
            z = (s_next - self.transition_mean(s, a)) / 0.3
            return -0.5 * (z * z).sum(-1) - 2 * math.log(0.3) - math.log(2 * math.pi)

        def observe(self, s_next, a, generator=None):
            return s_next + self.obs_std * torch.randn(s_next.shape, generator=generator)

        def observation_log_prob(self, o, s_next, a):
            z = (o - s_next) / self.obs_std
            return -0.5 * (z * z).sum(-1) - 2 * math.log(self.obs_std) - math.log(2 * math.pi)

        def reward(self, s, a, s_next):
            return torch.zeros(s.shape[:-1])

        def is_terminal(self, s):
            return torch.zeros(s.shape[:-1], dtype=torch.bool)
''')
"""The source of a user's model module (a 2-D random walk seen through noise, class ``Drift``, on the model
protocol without importing escort_rl): the frontier's ``--model`` tests write it to a file and name it."""


def one_line_error(fn, kind: type[Exception] = ValueError) -> str:
    """The message of the ``kind`` error that ``fn()`` raises, which must be one line."""
    with pytest.raises(kind) as info:
        fn()
    message = str(info.value)
    assert "\n" not in message, message
    return message
