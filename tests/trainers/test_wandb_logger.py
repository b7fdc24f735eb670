"""``logger.backend=wandb``: TorchRL's ``WandbLogger``, offline by default (no network assumed)."""

from __future__ import annotations

import pytest

from conftest import tiny_overrides
from escort_rl.config import compose
from escort_rl.trainers.training import train


def test_a_wandb_run_logs_offline_into_the_run_folder(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = train(compose(tiny_overrides("trainer.iterations=2", "logger.backend=wandb", f"output_dir={tmp_path}")),
                progress=False)
    offline = list((run / "logs" / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(offline) == 1 and offline[0].stat().st_size > 0


def test_the_wandb_settings_are_checked():
    from conftest import config_error

    assert config_error(["logger.backend=mlflow"]) == \
        "config: logger.backend: must be one of csv, tensorboard, wandb; got 'mlflow'"
    assert config_error(["logger.offline=maybe"]) == "config: logger.offline: expected true or false, got 'maybe'"
