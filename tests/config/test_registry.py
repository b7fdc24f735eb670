"""One registry (escort_rl.config.registry): the schemas, the frontier and the trainers read it, and no
trainer or env is recognised by its name outside its own module."""

from __future__ import annotations

import re
from pathlib import Path

import escort_rl
from escort_rl.config import registry, schema


def test_every_registered_class_has_its_schema_and_nothing_else_does():
    assert set(schema.FILTER_SCHEMAS) == set(registry.names("filter"))
    assert set(schema.TRAINER_SCHEMAS) == set(registry.names("trainer"))
    assert set(schema.MODEL_SCHEMAS) == set(registry.names("model"))
    assert set(schema.ENV_SCHEMAS) == set(registry.names("model")) | set(registry.TASK_ONLY_ENVS) | {"custom"}
    for name in registry.names("trainer"):  # each trainer's parameters are its class's Params
        assert registry.params("trainer", name) is registry.resolve("trainer", name).Params


def test_the_frontier_and_the_synthetic_rows_take_their_filters_from_the_registry():
    from escort_rl.bench.frontier.cells import FILTER_METHODS, ITERATIVE, frontier_filter
    from escort_rl.bench.synthetic.cells import ROW_FILTERS

    assert set(FILTER_METHODS) == set(registry.names("filter")) and set(ITERATIVE) == {"svgd", "escort"}
    assert all(isinstance(frontier_filter(m), registry.resolve("filter", m)) for m in FILTER_METHODS)
    assert {kind for kind, _, _ in ROW_FILTERS.values()} <= set(registry.names("filter"))


def test_the_trainers_ask_the_trainer_class_not_its_name():
    from escort_rl.trainers.algorithm import Algorithm

    classes = {name: registry.resolve("trainer", name) for name in registry.names("trainer")}
    assert [n for n, c in classes.items() if c.model_free] == ["recurrent_ppo"]
    assert classes["dvrl_a2c"].reads_true_state(None) and classes["dvrl_a2c"].watch == ("episode_return", "elbo")
    assert all(issubclass(c, Algorithm) and c.trained_policy is not Algorithm.trained_policy for c in classes.values())
    names = "|".join(map(re.escape, [*registry.names("trainer"), *registry.TASK_ONLY_ENVS]))
    compared = re.compile(rf"""[=!]=\s*["']({names})["']""")
    trainers = Path(escort_rl.__file__).parent / "trainers"
    found = [f"{p.name}:{i}" for p in sorted(trainers.glob("*.py"))
             for i, line in enumerate(p.read_text().splitlines(), 1) if compared.search(line)]
    assert not found, found
