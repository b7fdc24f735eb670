"""Typed configs: the schemas of escort_rl.config.schema, the range checks, one-line errors, resuming by
recomposition, and building filters and models with hydra.utils.instantiate."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import MISSING, OmegaConf

from conftest import config_error
from escort_rl.cli import main
from escort_rl.config import ConfigError, bench_schemas, checking, compose, config_dir, option_names, schema
from escort_rl.trainers.builders import build_filter, build_model
from escort_rl.trainers.resume import merge_override_lists, recompose, saved_config_drift
from escort_rl.trainers.validation import validate_train_config

ENVS = option_names("env")
PACKAGE_ENVS = [e for e in ENVS if e not in ("custom", "popgym")]
"""The env options with a package model (``custom`` names the user's, with no default; ``popgym`` has
none: tests/trainers/test_popgym_training.py)."""
FILTERS = option_names("filter")
TRAINERS = option_names("trainer")




# ------------------------------------------------------------------------------ composing
def test_default_config_is_typed():
    cfg = compose()
    assert OmegaConf.get_type(cfg) is schema.Config
    assert OmegaConf.get_type(cfg.env) is schema.ENV_SCHEMAS["lightdark10d"]
    assert OmegaConf.get_type(cfg.env.model) is schema.MODEL_SCHEMAS["lightdark10d"]
    assert OmegaConf.get_type(cfg.filter) is schema.FILTER_SCHEMAS["escort"]
    assert OmegaConf.get_type(cfg.trainer) is schema.TRAINER_SCHEMAS["ppo"]
    assert OmegaConf.get_type(cfg.dvrl) is schema.DVRLConfig
    assert cfg.overrides is None and cfg.resume is None


def test_the_options_are_the_yaml_files():
    assert set(ENVS) == {"lightdark10d", "lightdark10d_continuous", "kidnapped20d", "mtt20d", "linear_gaussian",
                         "popgym_cartpole", "popgym_pendulum", "popgym", "custom", "hidden_goal"}
    assert {"sir", "enkf", "svgd", "escort", "escort_nocorr", "escort_train"} <= set(FILTERS)
    assert set(TRAINERS) == {"reinforce", "ppo", "dvrl_a2c", "recurrent_ppo"}


@pytest.mark.parametrize("env", ENVS)
@pytest.mark.parametrize("filt", FILTERS)
@pytest.mark.parametrize("trainer", TRAINERS)
def test_every_combination_composes(env, filt, trainer):
    cfg = compose([f"env={env}", f"filter={filt}", f"trainer={trainer}"])
    assert cfg.env.name == env and cfg.dvrl.name == env and cfg.filter.name in (filt, "escort")
    assert OmegaConf.get_type(cfg.env) is schema.ENV_SCHEMAS[env]
    assert OmegaConf.get_type(cfg.filter) is schema.FILTER_SCHEMAS[cfg.filter.kind]
    assert OmegaConf.get_type(cfg.trainer) is schema.TRAINER_SCHEMAS[trainer]
    assert cfg.trainer.algorithm == trainer


def test_inherited_filter_options_keep_their_parent():
    nocorr = compose(["filter=escort_nocorr"]).filter
    escort = compose(["filter=escort"]).filter
    assert nocorr.name == "escort_nocorr" and nocorr.lambda_corr == 0.0
    assert {k: v for k, v in nocorr.items() if k not in ("name", "lambda_corr")} == \
        {k: v for k, v in escort.items() if k not in ("name", "lambda_corr")}
    train = compose().filter
    assert train.num_steps == 15 and train.compile is True and train.name == "escort_train" and train.kind == "escort"


@pytest.mark.parametrize("env", PACKAGE_ENVS)
def test_every_env_builds_its_model(env):
    cfg = compose([f"env={env}"])
    model = build_model(cfg.env, cfg.device)
    assert type(model).__name__ == cfg.env.model._target_.rsplit(".", 1)[1]
    for key in ("input_loc", "input_scale"):  # a number, or one per state dimension
        value = cfg.env[key]
        assert isinstance(value, (int, float)) or model.state_dim == len(value)


@pytest.mark.parametrize("filt", FILTERS)
def test_every_filter_builds_its_class(filt):
    cfg = compose([f"filter={filt}"])
    built = build_filter(cfg.filter)
    assert type(built).__name__ == cfg.filter._target_.rsplit(".", 1)[1]
    if "num_steps" in cfg.filter:
        assert built.num_steps == cfg.filter.num_steps


def test_types_are_coerced():
    cfg = compose(["trainer.lr=1e-3", "env.model.goal=8", "trainer.iterations=5", "evaluate.greedy=true"])
    assert isinstance(cfg.trainer.lr, float) and cfg.trainer.lr == pytest.approx(1e-3)
    assert isinstance(cfg.env.model.goal, float) and cfg.env.model.goal == 8.0
    assert isinstance(cfg.trainer.iterations, int) and cfg.trainer.iterations == 5
    assert cfg.evaluate.greedy is True
    assert isinstance(compose(["trainer.gamma=1"]).trainer.gamma, float)


# ------------------------------------------------------------------------------ bad values
@pytest.mark.parametrize(("override", "key"), [
    ("num_particles=2.5", "num_particles"),
    ("trainer.iterations=2.9", "trainer.iterations"),
    ("trainer.iterations=abc", "trainer.iterations"),
    ("seed=abc", "seed"),
    ("trainer.lr=inf", "trainer.lr"),
    ("trainer.lr=0", "trainer.lr"),
    ("trainer.entropy_coef=nan", "trainer.entropy_coef"),
    ("env.model.dt=inf", "env.model.dt"),
    ("env.model.dt=-0.1", "env.model.dt"),
    ("trainer.iterations=0", "trainer.iterations"),
    ("trainer.gamma=1.5", "trainer.gamma"),
    ("num_particles=0", "num_particles"),
    ("collector.workers=0", "collector.workers"),
    ("logger.backend=mlflow", "logger.backend"),
    ("env.max_steps=0", "env.max_steps"),
    ("env.input_scale=0", "env.input_scale"),
    ("filter.num_steps=-1", "filter.num_steps"),
    ("filter.corr_form=diagonal", "filter.corr_form"),
    ("filter.kind=sir", "filter.kind"),
    ("trainer.warm_start_filter=nope", "trainer.warm_start_filter"),
    ("dvrl.loss.bptt_steps=0", "dvrl.loss.bptt_steps"),
    ("evaluate.greedy=maybe", "evaluate.greedy"),
])
def test_a_bad_value_names_its_key(override, key):
    assert config_error([override]).startswith(f"config: {key}: ")


def test_type_errors_say_what_was_expected():
    assert config_error(["num_particles=2.5"]) == "config: num_particles: expected an int, got '2.5'"
    assert config_error(["env=mtt20d", "env.model.goal=[1,a]"]) == \
        "config: env.model.goal[1]: expected a number, got 'a'"
    assert "must be a finite number" in config_error(["env.model.dt=inf"])


def test_values_of_other_options_are_checked_too():
    assert config_error(["env=kidnapped20d", "env.model.detection_prob=1.0"]).startswith(
        "config: env.model.detection_prob: must be < 1")
    assert config_error(["trainer=ppo", "trainer.gae_lambda=2"]).startswith("config: trainer.gae_lambda:")
    assert config_error(["filter=sir", "filter.resample_threshold=1.5"]).startswith(
        "config: filter.resample_threshold:")


def test_unknown_key_is_one_line_naming_the_full_key():
    message = config_error(["trainer.lrr=0.1"])
    assert message.startswith("config: unknown key 'trainer.lrr'; check the spelling against `escort-rl config`")
    assert config_error(["filter=sir", "filter.num_steps=3"]).startswith("config: unknown key 'filter.num_steps'")
    assert compose(["+trainer.note=hello"]).trainer.note == "hello"  # added on purpose


def test_unknown_option_and_unparsable_override():
    message = config_error(["filter=nope"])
    assert message.startswith("config: no filter config 'nope'; choose one of ") and "_schema" not in message
    assert config_error(["filter=escort_schema"]).startswith("config: no filter config 'escort_schema'")
    assert config_error(["trainer.iterations=[1"]).startswith(
        "config: cannot parse the override 'trainer.iterations=[1'")


def test_device_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    message = config_error(["device=cuda"])
    assert message.startswith("config: device: ") and "device=cpu" in message
    assert config_error(["device=tpu0"]).startswith("config: device: ")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert compose(["device=cuda:0"]).device == "cuda:0"
    assert config_error(["device=cuda:1"]).startswith("config: device: ")


def test_output_dir_that_is_a_file(tmp_path):
    f = tmp_path / "file.txt"
    f.write_text("x")
    assert config_error([f"output_dir={f}"]).startswith("config: output_dir: ")
    assert config_error([f"output_dir={f / 'run'}"]).startswith("config: output_dir: ")
    assert compose([f"output_dir={tmp_path / 'new' / 'run'}"]).output_dir == str(tmp_path / "new" / "run")


@pytest.fixture
def config_copy(tmp_path, monkeypatch):
    """A copy of configs/ that compose reads instead."""
    import escort_rl.config.files

    copy = tmp_path / "configs"
    shutil.copytree(config_dir(), copy)
    monkeypatch.setattr(escort_rl.config.files, "config_dir", lambda: copy)
    return copy


def test_a_yaml_key_the_schema_lacks_is_named(config_copy):
    with open(config_copy / "trainer" / "ppo.yaml", "a") as fh:
        fh.write("new_knob: 1\n")
    assert config_error(["trainer=ppo"]).startswith("config: trainer.new_knob: a key of the yaml that its schema "
                                              "PPOConfig lacks")
    with open(config_copy / "trainer" / "reinforce.yaml", "a") as fh:
        fh.write("iterations: many\n")
    assert config_error(["trainer=reinforce"]).startswith("config: trainer.iterations: expected an int, got 'many'")


# ------------------------------------------------------------------------------ before training
def test_train_validation_checks_configs_without_types():
    plain = OmegaConf.create(OmegaConf.to_container(compose(), resolve=True))
    validate_train_config(plain)
    plain.trainer.iterations = 0
    with pytest.raises(ConfigError, match=r"^trainer.iterations: must be >= 1"):
        validate_train_config(plain)
    plain.trainer.iterations = 2
    plain.env.model.dt = float("inf")
    with pytest.raises(ConfigError, match=r"^env.model.dt: must be a finite number"):
        validate_train_config(plain)


def test_train_validation_checks_the_train_stage_and_divisibility():
    cfg = compose(["trainer=reinforce", "trainer.baseline=mean"])  # composes: checked before training only
    with pytest.raises(ConfigError, match=r"^trainer.baseline: must be one of time, learned"):
        validate_train_config(cfg)
    with pytest.raises(ConfigError, match=r"^collector.workers: trainer.num_envs \(16\)"):
        validate_train_config(compose(["trainer=reinforce", "collector.workers=3"]))


# ------------------------------------------------------------------------------ the command
def test_config_command_prints_the_config(capsys):
    assert main(["config"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    expected = OmegaConf.to_container(compose(), resolve=True)
    assert printed == {**expected, "overrides": []}
    assert main(["config", "filter=sir", "trainer.lr=1e-3"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["filter"]["_target_"] == "escort_rl.belief.SIRFilter" and printed["trainer"]["lr"] == 0.001
    assert printed["overrides"] == ["filter=sir", "trainer.lr=1e-3"]


def test_config_command_error_is_one_line(capsys):
    assert main(["config", "num_particles=2.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: config: num_particles: expected an int, got '2.5'"


# ------------------------------------------------------------------------------ resuming
def test_override_lists_merge_later_wins():
    saved = ["filter=escort", "filter.num_steps=3", "+foo=1", "trainer.lr=0.1", "env.max_steps=5"]
    assert merge_override_lists(saved, ["filter=sir", "foo=2", "trainer.lr=0.2"]) == \
        ["+foo=1", "env.max_steps=5", "filter=sir", "foo=2", "trainer.lr=0.2"]
    assert merge_override_lists(["trainer.iterations=1"], ["trainer.iterations=2"]) == ["trainer.iterations=2"]


def test_resume_recomposes_a_group_override():
    saved_overrides = ["filter=escort", "filter.num_steps=3", "trainer.iterations=1", "num_particles=8"]
    saved = OmegaConf.to_container(compose(saved_overrides), resolve=True)
    saved["overrides"] = saved_overrides
    assert saved_config_drift(saved) == []
    cfg = recompose(saved, ["filter=sir", "trainer.iterations=2"])
    assert OmegaConf.get_type(cfg.filter) is schema.FILTER_SCHEMAS["sir"] and cfg.filter.name == "sir"
    assert "num_steps" not in cfg.filter and cfg.trainer.iterations == 2 and cfg.num_particles == 8
    assert list(cfg.overrides) == ["num_particles=8", "filter=sir", "trainer.iterations=2"]
    with pytest.raises(ConfigError, match="^config: trainer.gamma: must be <= 1"):
        recompose(saved, ["trainer.gamma=2"])


def test_resume_of_a_config_saved_without_overrides():
    saved = OmegaConf.to_container(compose(["filter=sir", "num_particles=9"]), resolve=True)
    saved["actor"]["input_loc"] = 4.0  # a key an older version wrote
    cfg = recompose(saved, ["trainer.iterations=3", "trainer.lr=1e-3"])
    assert cfg.filter.name == "sir" and cfg.num_particles == 9 and cfg.trainer.iterations == 3
    assert isinstance(cfg.trainer.lr, float) and cfg.actor.input_loc == 4.0
    with pytest.raises(ConfigError, match="^config: filter=escort: .*saved without the overrides"):
        recompose(saved, ["filter=escort"])
    with pytest.raises(ConfigError, match="^config: trainer.iterations: expected an int, got 'abc'"):
        recompose(saved, ["trainer.iterations=abc"])
    with pytest.raises(ConfigError, match="^config: unknown key 'trainer.lrr'"):
        recompose(saved, ["trainer.lrr=1"])


def test_train_records_overrides_and_resumes_with_another_filter(tmp_path, capsys):
    run = tmp_path / "run"
    tiny = ["trainer=reinforce", "trainer.num_envs=2", "env.max_steps=4", "num_particles=8", "actor.hidden=8",
            "trainer.minibatch_size=64", "trainer.checkpoint_every=1", "filter.compile=false",
            "filter.num_steps=2", "trainer.iterations=1", f"output_dir={run}"]
    assert main(["train", "--quiet", *tiny]) == 0
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["overrides"] == tiny and saved["filter"]["name"] == "escort_train"
    capsys.readouterr()

    assert main(["config", f"resume={run}", "filter=sir", "trainer.iterations=2"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["filter"]["kind"] == "sir" and shown["resume"].startswith(str(run))

    assert main(["train", "--quiet", f"resume={run}", "filter=sir", "trainer.iterations=2"]) == 0
    resumed = yaml.safe_load((run / "config.yaml").read_text())
    assert resumed["filter"]["name"] == "sir" and resumed["trainer"]["iterations"] == 2
    assert resumed["overrides"][-2:] == ["filter=sir", "trainer.iterations=2"]
    assert "filter.num_steps=2" not in resumed["overrides"]
    from escort_rl.trainers.checkpointing import load_checkpoint

    assert load_checkpoint(run)["trainer_state"]["iteration"] == 2


# ------------------------------------------------------------------------------ schemas vs classes
def _plain(value):
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict) or hasattr(value, "items"):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _schema_defaults(cls) -> dict:
    out = {}
    for f in dataclasses.fields(cls):
        if f.name.startswith("_"):
            continue
        if f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
        else:
            out[f.name] = f.default
    return out


def test_a_class_schema_has_its_params_fields_and_defaults():
    """The schema of a group option is made from the class's Params: the same fields and defaults
    (mappings have none in the schema: the yaml sets them), ``_target_`` naming the class."""
    from escort_rl.belief import ESCORTFilter
    from escort_rl.models import MultiTargetTracking20D

    for node, cls in ((schema.FILTER_SCHEMAS["escort"], ESCORTFilter), (schema.MODEL_SCHEMAS["mtt20d"],
                                                            MultiTargetTracking20D)):
        defaults = {k: v for k, v in _schema_defaults(node).items() if k not in ("name", "kind")}
        own = {f.name: (f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default)
               for f in dataclasses.fields(cls.Params)}
        assert set(defaults) == set(own)
        assert {k: v for k, v in defaults.items() if v is not MISSING} == {
            k: v for k, v in own.items() if defaults[k] is not MISSING}
        assert {k for k, v in defaults.items() if v is MISSING} == {
            k for k, v in own.items() if isinstance(v, dict)}
        assert node._target_ == f"escort_rl.{cls.__module__.split('.')[1]}.{cls.__name__}"


def test_svgd_schema_is_escort_without_the_regularisers():
    svgd, escort = _schema_defaults(schema.FILTER_SCHEMAS["svgd"]), _schema_defaults(schema.FILTER_SCHEMAS["escort"])
    assert set(svgd) < set(escort)
    assert all(svgd[k] == escort[k] for k in svgd if k not in ("name", "kind"))


# ------------------------------------------------------------------------------ files read without Hydra
@pytest.mark.parametrize(("name", "node"), [("bench/closed_loop.yaml", bench_schemas.ClosedLoopBenchConfig),
                                            ("bench/synthetic.yaml", bench_schemas.SyntheticBenchConfig)])
def test_bench_settings_load_typed(name, node):
    path = config_dir() / name
    cfg = checking.load_typed(path, node)
    assert OmegaConf.get_type(cfg) is node
    assert OmegaConf.to_container(cfg) == yaml.safe_load(path.read_text())


@pytest.mark.parametrize("domain", option_names("planner"))
def test_planner_settings_load_typed(domain):
    from escort_rl.planners import POMCPOWParams
    from escort_rl.planners.planner_config import load_planner_config

    values = load_planner_config(domain)
    assert values == OmegaConf.to_container(OmegaConf.load(config_dir() / "planner" / f"{domain}.yaml"))
    assert set(values) <= {f.name for f in dataclasses.fields(POMCPOWParams)}


def test_group_options_load_typed_without_hydra():
    cfg = checking.load_typed(config_dir() / "env" / "mtt20d.yaml", schema.ENV_SCHEMAS["mtt20d"])
    assert cfg.model.goal == [9.0, 9.0] and "defaults" not in cfg


def test_a_bad_bench_value_names_file_and_key(tmp_path):
    text = (config_dir() / "bench" / "closed_loop.yaml").read_text()
    bad = tmp_path / "closed_loop.yaml"
    bad.write_text(text.replace("episodes: 30", "episodes: 0"))
    with pytest.raises(ConfigError, match=r"closed_loop.yaml: episodes: must be >= 1, got 0$"):
        checking.load_typed(bad, bench_schemas.ClosedLoopBenchConfig)
    bad.write_text(text.replace("{iterations: 5, num_envs: 8}", "{iterations: five, num_envs: 8}"))
    with pytest.raises(ConfigError, match=r"closed_loop.yaml: train.lightdark10d.iterations: expected an int"):
        checking.load_typed(bad, bench_schemas.ClosedLoopBenchConfig)
    bad.write_text(text.replace("pomcpow_sir: {filter: sir}", "pomcpow_sir: {filter: sirr}"))
    with pytest.raises(ConfigError, match=r"planners.pomcpow_sir.filter: no filter config 'sirr'"):
        checking.load_typed(bad, bench_schemas.ClosedLoopBenchConfig)


# ------------------------------------------------------------------------------ building
def test_configs_saved_without_target_still_build():
    cfg = OmegaConf.to_container(compose(["filter=escort_nocorr"]), resolve=True)
    del cfg["filter"]["_target_"], cfg["env"]["model"]["_target_"]
    cfg = OmegaConf.create(cfg)
    assert build_filter(cfg.filter).lambda_corr == 0.0
    assert type(build_model(cfg.env)).__name__ == "LightDark10D"
    lightdark1d = OmegaConf.create({"name": "lightdark1d", "max_steps": 3, "model": {}})
    assert type(build_model(lightdark1d)).__name__ == "LightDark1D"


def test_build_errors_name_the_group():
    with pytest.raises(ConfigError, match="^filter: ESCORTFilter.corr_form"):
        build_filter(OmegaConf.create({"name": "escort", "kind": "escort", "corr_form": "diagonal"}))
    with pytest.raises(ConfigError, match="^filter.kind: unknown filter 'foo'"):
        build_filter(OmegaConf.create({"name": "foo"}))
    with pytest.raises(ConfigError, match="^env.model: LightDark10D: unknown parameter 'foo'; LightDark10D takes "):
        build_model(OmegaConf.create({"name": "lightdark10d", "model": {"foo": 1}}))
    with pytest.raises(ConfigError, match="^env.model._target_: cannot import 'escort_rl.models.Nope'"):
        build_model(OmegaConf.create({"name": "lightdark10d", "model": {"_target_": "escort_rl.models.Nope"}}))
    with pytest.raises(ConfigError, match="^env.name: unknown model 'x'; choose one of hidden_goal, kidnapped20d, "):
        build_model(OmegaConf.create({"name": "x", "model": {}}))


def test_every_packaged_yaml_is_covered():
    """Each yaml in configs/ is a group option composed above, config.yaml, or a file with a schema."""
    root = Path(config_dir())
    covered = {"config.yaml", "bench/closed_loop.yaml", "bench/synthetic.yaml", "bench/atari.yaml",
               "bench/minatar.yaml"}
    for group in ("env", "filter", "trainer", "dvrl", "planner"):
        covered |= {f"{group}/{option}.yaml" for option in option_names(group)}
    assert {str(p.relative_to(root)) for p in root.rglob("*.yaml")} == covered
    assert set(option_names("dvrl")) == set(ENVS)


def _option_values(group: str, option: str) -> dict:
    """The values a group option composes to (its parents' and its own)."""
    return OmegaConf.to_container(compose([f"{group}={option}"])[group], resolve=True)


def _parent_values(group: str, raw) -> dict:
    """What an option's first ``defaults`` entry composes to: a schema's defaults or another option."""
    parent = raw["defaults"][0]
    if parent.endswith("_schema"):
        node = {"filter": schema.FILTER_SCHEMAS, "env": schema.ENV_SCHEMAS,
                "trainer": schema.TRAINER_SCHEMAS}[group][parent[: -len("_schema")]]
        return OmegaConf.to_container(OmegaConf.structured(node), resolve=False)
    return _option_values(group, parent)


@pytest.mark.parametrize("group, option", [*(("filter", o) for o in FILTERS), *(("trainer", o) for o in TRAINERS)])
def test_a_group_yaml_holds_only_what_differs_from_its_parent(group, option):
    raw = OmegaConf.to_container(OmegaConf.load(config_dir() / group / f"{option}.yaml"))
    parent = _parent_values(group, raw)
    same = [k for k, v in raw.items() if k != "defaults" and parent.get(k) == v]
    assert not same, f"{group}/{option}.yaml repeats its parent's {same}"


@pytest.mark.parametrize("kind", ["model", "filter", "trainer"])
def test_every_registered_class_owns_the_params_its_schema_is_made_from(kind):
    from escort_rl.config import registry

    for name in registry.names(kind):
        cls = registry.resolve(kind, name)
        assert dataclasses.is_dataclass(cls.Params) and cls.Params.__dataclass_params__.frozen, name
        assert registry.params(kind, name) is cls.Params, name


@pytest.mark.parametrize("option", PACKAGE_ENVS)
def test_an_env_yaml_sets_only_model_values_that_differ_from_the_model_defaults(option):
    raw = OmegaConf.to_container(OmegaConf.load(config_dir() / "env" / f"{option}.yaml"))
    defaults = OmegaConf.to_container(OmegaConf.structured(type(schema.ENV_SCHEMAS[option]().model)),
                                      resolve=False)
    same = [k for k, v in (raw.get("model") or {}).items() if defaults.get(k) == v]
    assert not same, f"env/{option}.yaml repeats the model defaults {same}"
