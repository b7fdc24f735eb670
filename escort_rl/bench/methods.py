"""The method registry: every benchmark and the CLI take their method and domain names from here.

- **Filter methods** are the filter configs under ``configs/filter/`` (:func:`filter_methods`): a new
  yaml is a new row of every belief benchmark, with no code change. Protocol (a)'s default rows are
  :data:`PROTOCOL_A_METHODS`; its ``--quick`` rows :data:`QUICK_METHODS`.
- **Named rows** of protocol (b) (planners, scripted controllers, the learned belief, the recurrent
  policy) are the sections of ``configs/bench/closed_loop.yaml`` (:func:`load_settings`,
  :func:`named_rows`); the ``learned`` section (DVRL) is also a row of protocol (a)
  (:func:`learned_methods`).
- **Static-target rows** of the synthetic benchmark: :data:`SYNTHETIC_METHODS` (and
  :data:`SCALING_METHODS` for the dimension sweep).

Examples:
    >>> from escort_rl.bench import methods
    >>> methods.PROTOCOL_A_METHODS[:2]
    ('escort', 'escort_nocorr')
    >>> "sir" in methods.filter_methods()
    True
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

PROTOCOL_A_METHODS = ("escort", "escort_nocorr", "escort_notemp", "escort_noproj", "svgd", "sir", "enkf")
"""Protocol (a)'s default rows (filter configs); protocol (b) adds the named rows of its yaml."""
QUICK_METHODS = ("escort", "svgd", "sir")
"""The rows of ``bench domains --quick``."""
DOMAINS = ("lightdark10d", "kidnapped20d", "mtt20d")
"""The paper's domains (env configs), the default columns of the domain benchmark."""
SYNTHETIC_METHODS = ("escort", "escort_nocorr", "svgd", "sir", "dvrl", "oracle")
"""The synthetic benchmark's rows (static targets, see :mod:`escort_rl.bench.synthetic`)."""
SCALING_METHODS = ("escort", "escort_nocorr", "svgd", "oracle")
"""The rows of the RMSE-against-dimension sweep (``bench scaling``)."""
RANDOM = "random"
"""Protocol (b)'s reference row: a uniform-random policy, always run."""
SECTIONS = {"planners": "planner", "scripted": "scripted", "learned": "learned", "recurrent": "learned"}
"""The sections of ``configs/bench/closed_loop.yaml`` that name rows -> the row's policy kind
(recurrent rows are trained by their own trainer and evaluated like the learned belief)."""


def filter_methods() -> list[str]:
    """The filter configs (``configs/filter/*.yaml``), sorted: each is a method."""
    from escort_rl.config import config_dir

    return sorted(p.stem for p in (config_dir() / "filter").glob("*.yaml"))


def domain_names() -> list[str]:
    """The env configs (``configs/env/*.yaml``), sorted."""
    from escort_rl.config import config_dir

    return sorted(p.stem for p in (config_dir() / "env").glob("*.yaml"))


def settings_path() -> Path:
    """``configs/bench/closed_loop.yaml``: protocol (b)'s budget and named rows."""
    from escort_rl.config import config_dir

    return config_dir() / "bench" / "closed_loop.yaml"


def load_settings() -> dict:
    """``configs/bench/closed_loop.yaml`` as a plain dict, checked against
    :class:`escort_rl.config.bench_schemas.ClosedLoopBenchConfig` (a bad value raises ``ConfigError``
    naming the key)."""
    from omegaconf import OmegaConf

    from escort_rl.config.bench_schemas import ClosedLoopBenchConfig
    from escort_rl.config.checking import load_typed

    return OmegaConf.to_container(load_typed(settings_path(), ClosedLoopBenchConfig), resolve=True)


def named_rows(settings: dict) -> list[str]:
    """The row names of the yaml's sections (planners, scripted, learned, recurrent), in order.
    Raises ``ValueError`` for a name in two sections or one that shadows a filter config."""
    names, filters = {}, set(filter_methods())
    for section in SECTIONS:
        for m in settings.get(section) or {}:
            if m in names or m in filters or m == RANDOM:
                other = f"the {names[m]} section" if m in names else "a filter config" if m in filters else "a row"
                raise ValueError(f"{settings_path().name}: '{m}' in {section} is also {other}; rename it")
            names[m] = section
    return list(names)


def protocol_b_methods(settings: dict | None = None) -> list[str]:
    """Protocol (b)'s default rows (the random row is always added): :data:`PROTOCOL_A_METHODS`,
    then every named row of the yaml's sections."""
    return [*PROTOCOL_A_METHODS, *named_rows(settings if settings is not None else load_settings())]


def learned_methods(settings: dict | None = None) -> dict:
    """The learned-belief methods (``learned`` in ``configs/bench/closed_loop.yaml``, e.g. ``dvrl``):
    name -> ``{"trainer": ...}``."""
    return dict((settings if settings is not None else load_settings()).get("learned") or {})


def methods_help() -> str:
    """The ``--methods`` help of ``bench domains``, from the registry (a broken yaml is reported when
    a benchmark reads it, not while the command line is built)."""
    try:
        settings = load_settings()
    except (ValueError, OSError):
        settings = {}
    rows = {s: ", ".join(settings.get(s) or {}) for s in SECTIONS}
    return (f"filter configs (default: {' '.join(PROTOCOL_A_METHODS)}; any of {' '.join(filter_methods())}); "
            f"protocol b adds the planner rows {rows['planners']}, the scripted rows {rows['scripted']}, the "
            f"learned belief {rows['learned']} and the recurrent policy {rows['recurrent']}; protocol a also "
            f"takes the learned belief (trained first in <output>/runs with protocol b's budget)")


def check_names(domains, methods, filter_set: tuple = ()) -> None:
    """Raise ``ValueError`` naming ``--domains``, ``--methods`` or the filter overrides for a bad name."""
    if not domains:
        raise ValueError("--domains: give at least one domain")
    if not methods:
        raise ValueError("--methods: give at least one method")
    known_d, known_m, learned = domain_names(), filter_methods(), learned_methods()
    for d in domains:
        if d not in known_d:
            raise ValueError(f"--domains: unknown domain '{d}'; choose from {', '.join(known_d)}")
    for m in methods:
        if m not in known_m and m not in learned:
            raise ValueError(f"--methods: unknown method '{m}'; the methods are the filter configs "
                             f"{', '.join(known_m)} and the learned beliefs {', '.join(learned)}")
    if len(set(methods)) != len(methods):
        raise ValueError("--methods: a method is listed twice")
    filters = [m for m in methods if m not in learned]
    for key, _ in filter_set:
        if not any(key in applied_filter_set(m, ((key, ""),)) for m in filters):
            raise ValueError(f"overrides: no method in --methods has the filter key '{key}' (filter.{key}=...)")


def check_choices(flag: str, given, known, what: str = "name") -> None:
    """Raise ``ValueError`` naming ``flag`` for the first ``what`` of ``given`` not in ``known``."""
    unknown = [m for m in given if m not in known]
    if unknown:
        raise ValueError(f"{flag}: unknown {what} '{unknown[0]}'; choose from {', '.join(known)}")


def check_at_least_one(**flags) -> None:
    """Raise ``ValueError`` naming the flag (``particles`` -> ``--particles``) of the first count
    below 1; a flag's value may be a list of counts. ``None`` (not given) and values that are not
    ints (or are bools) pass.

    Examples:
        >>> check_at_least_one(particles=100, dims=[2, 4], threads=None)
        >>> check_at_least_one(particles=100, dims=[2, -4])
        Traceback (most recent call last):
        ...
        ValueError: --dims: must be a positive int, got -4
    """
    for name, value in flags.items():
        for v in (value if isinstance(value, list) else [value]):
            if isinstance(v, int) and not isinstance(v, bool) and v < 1:
                raise ValueError(f"--{name.replace('_', '-')}: must be a positive int, got {v}")


@lru_cache(maxsize=None)
def method_config(domain: str, method: str, filter_set: tuple = ()):
    """The composed config for ``filter=method env=domain``, with each ``filter_set`` (key, value)
    applied where the method's config has that key (``num_steps`` changes ESCORT and SVGD, not SIR)."""
    from escort_rl.config import compose

    base = [f"filter={method}", f"env={domain}"]
    if not filter_set:
        return compose(base)
    keys = set(compose(base).filter.keys()) - own_ablation_keys(method)
    return compose(base + [f"filter.{k}={v}" for k, v in filter_set if k in keys])


ABLATION_KEYS = ("lambda_corr", "lambda_temp", "projection")
"""The keys an ablation is defined by: a filter config that sets one of them itself (``escort_nocorr``
sets ``lambda_corr: 0``) keeps its value whatever a ``filter.lambda_corr=`` override says, so that a sweep of
``lambda_corr`` moves ESCORT and leaves ESCORT-NoCorr what its name says."""


@lru_cache(maxsize=None)
def own_ablation_keys(method: str) -> frozenset:
    """The :data:`ABLATION_KEYS` that ``configs/filter/<method>.yaml`` sets over the filter config it
    derives from (its ``defaults`` name another filter config); none for a base config."""
    import yaml

    from escort_rl.config import config_dir

    folder = config_dir() / "filter"
    path = folder / f"{method}.yaml"
    own = (yaml.safe_load(path.read_text()) if path.exists() else None) or {}
    parents = [d for d in own.get("defaults", []) if isinstance(d, str) and (folder / f"{d}.yaml").exists()]
    return frozenset(k for k in ABLATION_KEYS if k in own) if parents else frozenset()


def applied_filter_set(method: str, filter_set: tuple) -> dict:
    """The subset of ``filter_set`` that applies to ``method``: the keys its config has, less the
    ablation keys it is defined by (:data:`ABLATION_KEYS`)."""
    keys = set(method_config(DOMAINS[0], method).filter.keys()) - own_ablation_keys(method)
    return {k: v for k, v in filter_set if k in keys}


@lru_cache(maxsize=None)
def build_domain(domain: str):
    """The model of ``configs/env/<domain>.yaml`` and its ``max_steps``."""
    from escort_rl.trainers.builders import build_model

    cfg = method_config(domain, "sir")
    return build_model(cfg.env), int(cfg.env.max_steps)


def build_method(domain: str, method: str, filter_set: tuple = ()):
    """The filter of ``configs/filter/<method>.yaml`` (with ``filter_set`` applied) for ``domain``."""
    from escort_rl.trainers.builders import build_filter

    return build_filter(method_config(domain, method, tuple(filter_set)).filter)
