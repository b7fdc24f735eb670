"""The Python entry point of training: :func:`train`, what ``escort-rl train`` runs, with an
optional model object of your own."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from escort_rl.config import ConfigError


def train(overrides: Sequence[str] = (), model=None, progress: bool = True) -> Path:
    """Train as ``escort-rl train OVERRIDES...`` does and return the run directory.

    Args:
        overrides: Hydra overrides, e.g. ``["trainer.iterations=10", "filter=sir"]``;
            ``resume=RUN_DIR`` continues that run.
        model: a model object of your own (any object on :class:`escort_rl.models.POMDPModel`),
            used in place of the config's. It is pickled into the run directory (``model.pt``) and
            the run's config names it there (``env=custom``, ``env.model._target_`` the loader,
            with the file's SHA-256), so that evaluation, ``escort_rl.load_policy`` and a resume
            rebuild the same object; its class must be importable where the run is read. A model
            given by class in the config needs no pickle: ``env=custom
            env.model._target_=pkg.module.Class +env.model.KEY=VALUE``.
        progress: show a progress bar.

    Example::

        run_dir = escort_rl.train(["trainer.iterations=5", "env.max_steps=50"], model=MyModel(noise=0.1))
        policy = escort_rl.load_policy(run_dir)
    """
    from escort_rl.trainers.resume import train_config
    from escort_rl.trainers.training import train as train_run

    overrides = list(overrides)
    if model is not None:
        overrides = saved_model_overrides(overrides, model)
    cfg, saved = train_config(overrides)
    if saved is not None:
        print(f"resuming from {saved['path']} (iteration {saved['trainer_state']['iteration']})")
    return train_run(cfg, resume_state=saved, progress=progress)


def saved_model_overrides(overrides: list[str], model) -> list[str]:
    """``overrides`` with the ``env.model`` of a saved ``model`` object: pickle it, check that the
    run directory may take it (:func:`~escort_rl.trainers.resume.check_new_run_dir`), write
    ``model.pt`` there and return the overrides that name it."""
    from escort_rl.models import check_model
    from escort_rl.models.saved import model_bytes, sha256
    from escort_rl.trainers.resume import check_new_run_dir, new_run_config, output_path, quoted_override

    if any(o.startswith("resume=") for o in overrides):
        raise ConfigError("model: a resumed run rebuilds the model it saved; drop model= (or resume=)")
    envs = [o.split("=", 1)[1] for o in overrides if o.startswith("env=")]
    if envs and envs[-1] != "custom":
        raise ConfigError(f"model: a model object replaces the env group's model only with env=custom (got "
                          f"env={envs[-1]}); drop env=, or set the package model's keys with env.model.KEY=VALUE")
    keys = [o for o in overrides if o.lstrip("+~").startswith("env.model.")]
    if keys:
        raise ConfigError(f"model: a model object is used as it is, so '{keys[0]}' would not reach it; drop it and "
                          "set the value on the object itself (MyModel(KEY=VALUE))")
    try:
        check_model(model)
        data = model_bytes(model)
    except TypeError as err:
        raise ConfigError(str(err)) from None
    digest = sha256(data)
    base = [o for o in overrides if not o.startswith("env=")]
    probe = new_run_config(["env=custom", "env.model._target_=escort_rl.models.saved.load_saved_model", *base])
    run_dir = output_path(probe.output_dir)
    path = (run_dir / "model.pt").resolve()
    result = ["env=custom", "env.model._target_=escort_rl.models.saved.load_saved_model",
              f"+env.model.path={quoted_override(str(path))}", f"+env.model.sha256={digest}", *base]
    check_new_run_dir(new_run_config(result), run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".pt.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    return result
