"""Input checks shared by the metrics: tensors converted to a real floating dtype, sample sets
``[..., N, d]``, dtype promotion and normalised weights. Bad shapes or values raise
:class:`ValueError` naming the argument."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["as_float", "check_finite", "sample_set", "promoted", "normalised_weights", "weights_or_uniform"]


def as_float(name: str, t) -> Tensor:
    if not isinstance(t, Tensor):
        try:
            t = torch.as_tensor(t)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(f"{name}: expected a tensor, got {type(t).__name__} ({err})") from None
    if not t.is_floating_point():
        if t.is_complex():
            raise ValueError(f"{name}: expected a real tensor, got dtype {t.dtype}")
        t = t.to(torch.get_default_dtype())
    return t


def check_finite(name: str, t: Tensor) -> None:
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or Inf")


def sample_set(name: str, t, min_n: int = 1, allow_batch: bool = True) -> Tensor:
    """A sample set ``[..., N, d]`` (``[N]`` is read as ``[N, 1]``)."""
    t = as_float(name, t)
    if t.dim() == 1:
        t = t[:, None]
    if t.dim() < 2 or (not allow_batch and t.dim() != 2):
        want = "[N, d] or [..., N, d]" if allow_batch else "[N, d]"
        raise ValueError(f"{name}: expected {want}, got shape {list(t.shape)}")
    if t.shape[-2] < min_n:
        raise ValueError(f"{name}: expected at least {min_n} sample(s) along dim -2, got shape {list(t.shape)}")
    if t.shape[-1] < 1:
        raise ValueError(f"{name}: expected d >= 1, got shape {list(t.shape)}")
    check_finite(name, t)
    return t


def promoted(*ts: Tensor) -> list[Tensor]:
    dtype = ts[0].dtype
    for t in ts[1:]:
        dtype = torch.promote_types(dtype, t.dtype)
    device = ts[0].device
    return [t.to(device=device, dtype=dtype) for t in ts]


def normalised_weights(name: str, w, batch_n: tuple[int, ...], like: Tensor) -> Tensor:
    """Normalised non-negative weights broadcast to ``batch_n`` = ``(..., N)``."""
    w = as_float(name, w).to(device=like.device, dtype=like.dtype)
    try:
        w = torch.broadcast_to(w, batch_n)
    except RuntimeError:
        raise ValueError(f"{name}: expected shape {list(batch_n)} (or broadcastable), got {list(w.shape)}") from None
    check_finite(name, w)
    if bool((w < 0).any()):
        raise ValueError(f"{name}: weights must be non-negative")
    total = w.sum(-1, keepdim=True)
    if bool((total <= 0).any()):
        raise ValueError(f"{name}: weights must not all be zero")
    return w / total


def weights_or_uniform(name: str, w, like: Tensor) -> Tensor:
    """Weights ``w`` ``[..., N]`` normalised along the last dim (uniform when None); ``like``
    ``[..., N]`` gives N, the dtype and the device."""
    if w is None:
        return torch.full(like.shape, 1.0 / like.shape[-1], dtype=like.dtype, device=like.device)
    w = as_float(name, w)
    try:
        shape = torch.broadcast_shapes(w.shape, like.shape)
    except RuntimeError:
        raise ValueError(f"{name}: expected shape {list(like.shape)} (or broadcastable), got {list(w.shape)}") from None
    return normalised_weights(name, w, shape, like)

