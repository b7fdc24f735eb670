"""Training and evaluating policies on particle beliefs: :func:`train` (what ``escort-rl train``
runs) and :func:`load_policy`; the evaluation is :func:`escort_rl.trainers.evaluate.evaluate`
(``escort_rl.evaluate``). Each is imported on first use, so that importing a submodule (the
trainers' parameters, read when a config is composed) does not import TorchRL."""

_EXPORTS = {"train": "escort_rl.trainers.entry", "load_policy": "escort_rl.trainers.loading"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'escort_rl.trainers' has no attribute '{name}'")
