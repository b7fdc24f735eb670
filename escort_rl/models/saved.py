"""A model object saved with its run: ``escort_rl.train(overrides, model=obj)`` pickles ``obj``
into the run directory, and the run's config names :func:`load_saved_model` as ``env.model``'s
``_target_`` so that every later reader (collector workers, evaluation, ``load_policy``) rebuilds
the same object. Loading unpickles it: the model's class must be importable where it is loaded,
and a file is trusted only when its SHA-256 matches the one the config recorded."""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import torch


def model_bytes(model) -> bytes:
    """``model`` pickled by ``torch.save``; raises ``TypeError`` naming ``model`` when it cannot be
    (a lambda, an open file, a class defined inside a function)."""
    buffer = io.BytesIO()
    try:
        torch.save(model, buffer)
    except Exception as err:  # pickling raises many types (PicklingError, AttributeError, TypeError)
        raise TypeError(f"model: {type(model).__name__} cannot be pickled into the run directory ({err}); "
                        "define its class at the top level of an importable module") from None
    return buffer.getvalue()


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def load_saved_model(path: str, sha256: str, device: str | torch.device = "cpu"):
    """The model saved at ``path`` (``model.pt`` in a run directory), checked against ``sha256``.
    Raises ``ValueError`` naming ``env.model.path`` when the file is missing, damaged or another
    model's. ``device``: where a model with a ``to(device)`` method is moved."""
    file = Path(path)
    if not file.is_file():
        raise ValueError(f"env.model.path: '{path}' does not exist; the model is saved with its run "
                         "(model.pt): copy the run directory whole, or rebuild the model and train again")
    data = file.read_bytes()
    if hashlib.sha256(data).hexdigest() != sha256:
        raise ValueError(f"env.model.path: '{path}' is damaged or holds another model (its SHA-256 differs "
                         "from the one the run recorded)")
    model = torch.load(io.BytesIO(data), weights_only=False)
    to = getattr(model, "to", None)
    return to(device) if callable(to) and str(device) != "cpu" else model
