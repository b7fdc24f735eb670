"""Parameters owned by their classes, and the one checker of their ranges.

A model, filter or planner declares its parameters once, as a frozen dataclass whose fields carry
their range in the field metadata (:func:`param`). Its constructor takes keyword arguments (or a
ready ``params`` object), builds that dataclass and checks it with :func:`build_params`; the class
reads its parameters as attributes (:class:`HasParams`). Hydra's ConfigStore registers a schema made
from the same dataclass (:func:`escort_rl.config.schema.class_schema`), and the composed config is
checked by the same function, :func:`value_problem`, so there is one definition of each parameter
and one checker.

Field metadata:

- ``ge``, ``gt``, ``le``, ``lt``: bounds on a number (on every number of a list or mapping);
- ``choices``: the allowed values (of every element of a list);
- ``finite``: every float must be finite (the default); ``finite=False`` opts out;
- ``check``: a function ``value -> message | None`` for what bounds cannot say;
- ``stage="train"``: checked only before training, not while composing a config.

Examples:
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class DemoParams:
    ...     rate: float = param(0.1, gt=0)
    ...     mode: str = param("fast", choices=["fast", "slow"])
    >>> build_params(DemoParams, None, {"rate": 0.5}, owner="Demo")
    DemoParams(rate=0.5, mode='fast')
    >>> build_params(DemoParams, None, {"rate": -1.0}, owner="Demo")
    Traceback (most recent call last):
    ...
    escort_rl.config.errors.ConfigError: Demo.rate: must be > 0, got -1.0
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any, Callable, Dict, List

from escort_rl.config.errors import ConfigError

MISSING = dataclasses.MISSING
# Adam's first step moves a float32 parameter by lr / (1 - beta1) = 10 lr: a larger rate overflows
MAX_LR = 1e37


def param(default: Any = MISSING, **meta) -> Any:
    """A dataclass field with ``default`` and ``meta`` (the range keys above) as its metadata; a
    list or dict default is copied for every instance."""
    if isinstance(default, (list, dict)):
        value = default
        return dataclasses.field(default_factory=lambda: plain_value(value), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def plain_value(value):
    """``value`` as a plain config value, copied: every mapping (a ``dict``, an OmegaConf
    ``DictConfig``) a ``dict``, every sequence but a string (a tuple, a ``ListConfig``) and every
    array or tensor (anything with ``tolist``) a ``list``, recursively; other values unchanged.

    Examples:
        >>> plain_value(((1.0, 2.0), (3.0, 4.0)))
        [[1.0, 2.0], [3.0, 4.0]]
    """
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return value.tolist()
    if isinstance(value, Mapping):
        return {k: plain_value(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [plain_value(v) for v in value]
    return value


# ------------------------------------------------------------------------------------- types
_NAMES = {int: ("an int", "ints"), float: ("a number", "numbers"), bool: ("true or false", "booleans"),
          str: ("a string", "strings")}


def _is_union(origin) -> bool:
    return origin is typing.Union or origin is types.UnionType


def describe_type(hint, plural: bool = False) -> str:
    """``int`` -> ``an int``; ``List[float]`` -> ``a list of numbers``; ``Optional[X]`` -> ``... or null``.

    Examples:
        >>> describe_type(typing.Optional[typing.List[float]])
        'a list of numbers or null'
    """
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if _is_union(origin) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return f"{describe_type(rest[0], plural)} or null" if len(rest) == 1 else "a value"
    if hint in _NAMES:
        return _NAMES[hint][plural]
    if origin in (list, List, tuple):
        return "lists" if plural else f"a list of {describe_type(args[0], True) if args else 'values'}"
    if origin in (dict, Dict):
        return "mappings" if plural else f"a mapping to {describe_type(args[1], True) if args else 'values'}"
    if dataclasses.is_dataclass(hint):
        return "mappings" if plural else "a mapping"
    return "values" if plural else "a value"


def type_ok(value, hint) -> bool:
    """Whether a plain value (numbers, strings, lists, dicts) has the type ``hint`` (an int is a
    number; a bool is neither)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True
    if _is_union(origin):
        return any(type_ok(value, a) for a in args)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if origin in (list, List, tuple):
        return isinstance(value, (list, tuple)) and (not args or all(type_ok(v, args[0]) for v in value))
    if origin in (dict, Dict):
        return isinstance(value, dict) and (not args or all(type_ok(v, args[1]) for v in value.values()))
    if dataclasses.is_dataclass(hint):
        return isinstance(value, dict)
    return True


def _show(value) -> str:
    return repr(value) if value is None or isinstance(value, (list, dict, tuple)) else f"'{value}'"


def numbers(value):
    """Every number in ``value`` (a number, or nested lists and mappings), booleans excluded."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield value
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from numbers(v)
    elif isinstance(value, dict):
        for v in value.values():
            yield from numbers(v)


_BOUNDS = (("ge", lambda v, b: v >= b, ">="), ("gt", lambda v, b: v > b, ">"),
           ("le", lambda v, b: v <= b, "<="), ("lt", lambda v, b: v < b, "<"))


# ----------------------------------------------------------------------------------- checker
def value_problem(value, hint, meta: typing.Mapping, key: str, stage: str = "compose") -> str | None:
    """``"<key>: <what is wrong>"`` for a plain value that breaks its type ``hint`` or its field
    metadata ``meta``, or ``None``. The one checker of parameters and configs.

    Examples:
        >>> value_problem(0.0, float, {"gt": 0}, "step_size")
        'step_size: must be > 0, got 0.0'
        >>> value_problem([1, -2], typing.List[int], {"ge": 0}, "sizes")
        'sizes: must be >= 0, got -2'
        >>> value_problem("x", str, {"choices": ["a", "b"]}, "mode")
        "mode: must be one of a, b; got 'x'"
    """
    if not type_ok(value, hint):
        return f"{key}: expected {describe_type(hint)}, got {_show(value)}"
    if value is None:
        return None
    if meta.get("finite", True):
        bad = next((v for v in numbers(value) if isinstance(v, float) and not math.isfinite(v)), None)
        if bad is not None:
            return f"{key}: must be a finite number, got {bad}"
    if meta.get("stage", "compose") == "train" and stage != "train":
        return None
    for name, ok, what in _BOUNDS:
        if name in meta:
            bad = next((v for v in numbers(value) if not ok(v, meta[name])), None)
            if bad is not None:
                return f"{key}: must be {what} {meta[name]}, got {bad}"
    if "choices" in meta:
        items = value if isinstance(value, (list, tuple)) else [value]
        bad = [v for v in items if v not in meta["choices"]]
        if bad:
            return f"{key}: must be one of {', '.join(str(c) for c in meta['choices'])}; got '{bad[0]}'"
    check: Callable | None = meta.get("check")
    if check is not None:
        msg = check(value)
        if msg:
            return f"{key}: {msg}"
    return None


def params_problem(params, prefix: str = "", stage: str = "train") -> str | None:
    """The first field of a parameters dataclass instance that breaks its metadata, as
    ``"<prefix><field>: ..."``, or ``None``."""
    hints = typing.get_type_hints(type(params))
    for f in dataclasses.fields(params):
        problem = value_problem(getattr(params, f.name), hints[f.name], f.metadata, prefix + f.name, stage)
        if problem is not None:
            return problem
    return None


def build_params(cls: type, params=None, kwargs: typing.Mapping | None = None, *, owner: str):
    """An instance of the parameters dataclass ``cls``, checked: ``params`` (an instance of
    ``cls``, or ``None`` for the defaults) with the fields in ``kwargs`` replaced, each made a plain
    value first (:func:`plain_value`: a tuple or a ``ListConfig`` becomes a list). Raises
    :class:`ConfigError` ``"<owner>.<field>: ..."`` for a bad value and names the known
    parameters for an unknown one."""
    kwargs = dict(kwargs or {})
    if params is not None and not isinstance(params, cls):
        raise ConfigError(f"{owner}: params must be a {cls.__name__}, got {type(params).__name__}")
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in kwargs if k not in known]
    if unknown:
        raise ConfigError(f"{owner}: unknown parameter '{unknown[0]}'; {owner} takes {', '.join(known)}")
    kwargs = {k: plain_value(v) for k, v in kwargs.items()}  # tuples, OmegaConf containers, tensors
    built = dataclasses.replace(params, **kwargs) if params is not None else cls(**kwargs)
    problem = params_problem(built, prefix=f"{owner}.")
    if problem is not None:
        raise ConfigError(problem)
    return built


class HasParams:
    """A class that owns a frozen parameters dataclass (its ``Params``) in ``self.params``: each
    field reads as an attribute (``filter.num_steps`` is ``filter.params.num_steps``) unless the
    object sets an attribute of that name itself (a model's ``goal`` tensor built from the ``goal``
    parameter). To change a parameter, build a new object:
    ``type(obj)(params=dataclasses.replace(obj.params, name=value))``."""

    Params: typing.ClassVar[type]

    def __getattr__(self, name: str):
        params = self.__dict__.get("params")
        if params is not None and name in type(params).__dataclass_fields__:
            return getattr(params, name)
        raise AttributeError(f"'{type(self).__name__}' object has no attribute '{name}'")
