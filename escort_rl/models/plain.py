"""Keyword arguments as plain config values, before a model's parameters are built and checked.

A model's parameters are plain numbers, strings, lists and dicts (the values a config holds). Its
constructor also takes what callers naturally hand it: tuples, read-only mappings, OmegaConf
containers (``Model(**cfg.model)``) and tensors; :func:`plain_values` turns those into lists and
dicts, so that one checker sees one kind of value.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch


def plain_value(value):
    """``value`` with every mapping made a ``dict``, every sequence (not a string) and tensor a
    ``list``, recursively; other values unchanged.

    Examples:
        >>> plain_value(((1.0, 2.0), (3.0, 4.0)))
        [[1.0, 2.0], [3.0, 4.0]]
    """
    if isinstance(value, torch.Tensor):
        return value.tolist()
    if isinstance(value, Mapping):
        return {k: plain_value(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [plain_value(v) for v in value]
    return value


def plain_values(kwargs: Mapping) -> dict:
    """:func:`plain_value` of every keyword argument."""
    return {k: plain_value(v) for k, v in kwargs.items()}
