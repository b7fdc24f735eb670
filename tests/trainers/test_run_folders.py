"""One run per folder: the default ``output_dir`` is derived from env, filter, trainer and seed, and
a folder that holds another run is refused unless ``resume=`` names it."""

from __future__ import annotations

import pytest

from conftest import tiny_overrides
from escort_rl.config import ConfigError, compose
from escort_rl.trainers.resume import train_config
from escort_rl.trainers.training import train


def test_the_default_folder_names_env_filter_trainer_and_seed():
    assert compose().output_dir == "outputs/lightdark10d/escort_train-ppo-seed0"
    cfg = compose(["env=mtt20d", "filter=sir", "trainer=reinforce", "seed=7"])
    assert cfg.output_dir == "outputs/mtt20d/sir-reinforce-seed7"


def test_a_folder_holding_another_run_is_refused_unless_resumed(tmp_path):
    run = tmp_path / "run"
    first = tiny_overrides("trainer.iterations=1", f"output_dir={run}")
    train(compose(first), progress=False)
    saved = (run / "config.yaml").read_text()
    with pytest.raises(ConfigError) as info:
        train(compose(tiny_overrides("trainer.iterations=1", "seed=5", f"output_dir={run}")), progress=False)
    message = str(info.value)
    assert message.startswith(f"output_dir: '{run}' already holds another run") and "seed" in message
    assert f"resume={run}" in message and "\n" not in message
    assert (run / "config.yaml").read_text() == saved  # nothing of the refused run was written
    train(compose(first), progress=False)  # the same config may start again in its folder
    cfg, state = train_config([f"resume={run}", "trainer.iterations=2"])  # and resume= continues it
    assert state is not None
    train(cfg, resume_state=state, progress=False)


def test_a_multirun_trains_one_run_per_seed_each_in_its_own_folder(tmp_path, capsys):
    from escort_rl.cli import main

    overrides = tiny_overrides("trainer.iterations=1", "seed=3,4", f"output_dir={tmp_path}/seed" + "${seed}")
    assert main(["train", "--quiet", "-m", *overrides]) in (0, None)
    printed = capsys.readouterr().out
    assert "[1/2]" in printed and "[2/2]" in printed
    for seed in (3, 4):
        saved = (tmp_path / f"seed{seed}" / "config.yaml").read_text()
        assert f"seed: {seed}" in saved


def test_options_may_follow_the_overrides_and_every_command_takes_quiet():
    from escort_rl.cli import parse_args

    args = parse_args(["train", "trainer.iterations=2", "--quiet", "seed=1"])
    assert args.quiet and args.overrides == ["trainer.iterations=2", "seed=1"]
    assert parse_args(["run", "seed=1", "--quiet"]).quiet
    assert parse_args(["evaluate", "--checkpoint", "r", "--quiet"]).quiet
    with pytest.raises(SystemExit):
        parse_args(["train", "seed=1", "--no-such-option"])


def test_a_resume_of_a_finished_run_says_so(tmp_path, capsys):
    run = tmp_path / "run"
    train(compose(tiny_overrides("trainer.iterations=1", f"output_dir={run}")), progress=False)
    cfg, state = train_config([f"resume={run}"])
    train(cfg, resume_state=state, progress=False)
    assert "has finished its 1 iterations; nothing to train" in capsys.readouterr().out


def test_a_resume_names_every_key_it_changes_before_loading_weights(tmp_path, capsys):
    from escort_rl.cli import main

    run = tmp_path / "run"
    train(compose(tiny_overrides("trainer.iterations=1", f"output_dir={run}")), progress=False)
    capsys.readouterr()
    train_config([f"resume={run}", "trainer.iterations=2", "trainer.minibatch_size=32"])
    err = capsys.readouterr().err
    assert ("resuming with 2 changes to the run's config: trainer.iterations: 1 → 2; "
            "trainer.minibatch_size: 64 → 32") in err
    train_config([f"resume={run}"])
    assert "resuming with" not in capsys.readouterr().err  # nothing changed, nothing said
    # a change the weights cannot take is named before the checkpoint refuses it
    assert main(["train", "--quiet", f"resume={run}", "trainer.iterations=2", "actor.hidden=32"]) == 2
    err = capsys.readouterr().err
    assert err.index("actor.hidden: 16 → 32") < err.index("error: checkpoint: actor:")
