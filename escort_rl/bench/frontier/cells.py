"""The frontier's cells: one filter at one cost setting (N, and K for SVGD/ESCORT) on a model's shared
trajectories, timed per update and compared with the reference posterior at every step.

**The model** is named by a string and its arguments, so that a cell is plain data:

- ``env:<name>`` with Hydra overrides of the env group (``model.state_dim=100``): a package domain or
  family (``configs/env/<name>.yaml``);
- ``class:<pkg.module>:<Class>`` with ``key=value`` keyword arguments: a user's own model class,
  anything on the model protocol.

**The reference** is the exact posterior where the model has one
(:func:`~escort_rl.metrics.reference.has_exact_posterior`): the linear-Gaussian family's Kalman filter,
computed in each cell; a Gaussian sum (the synthetic tracking family), computed once by
:class:`FrontierReferenceCell` with ``exact=True``. Otherwise a large SIR reference
(:class:`FrontierReferenceCell`). A reference cell runs once per seed block and every cell loads its
file, its hash checked.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import torch

from escort_rl.bench.core.runner import Cell
from escort_rl.bench.reference_cell import ReferenceCell
from escort_rl.config import registry
from escort_rl.config.errors import first_line
from escort_rl.metrics.reference import Reference, exact_reference, has_exact_posterior

FILTER_METHODS = tuple(registry.REGISTRY["filter"])
"""The frontier's filters: SIR and EnKF cost N; SVGD and ESCORT cost N × K."""
ITERATIVE = tuple(m for m in FILTER_METHODS
                  if "num_steps" in {f.name for f in dataclasses.fields(registry.params("filter", m))})


def _parse_value(text: str, option: str = "--model-arg"):
    """``text`` read as OmegaConf reads a dotlist's value (a number, a list, a string); ``ValueError``
    naming ``option`` when it does not parse."""
    from omegaconf import OmegaConf

    try:
        return OmegaConf.from_dotlist([f"value={text}"])["value"]
    except Exception as err:  # noqa: BLE001 - yaml and OmegaConf raise several types
        raise ValueError(f"{option}: cannot read the value '{text}' ({first_line(err)}); quote a string, close a "
                         "list") from None


@lru_cache(maxsize=16)
def frontier_model(model: str, model_args: tuple = ()):
    """The model of a cell: ``env:<name>`` with env-group overrides, or ``class:<module>:<Class>`` with
    ``key=value`` arguments (values read as OmegaConf reads a dotlist). Raises ``ValueError`` naming
    ``--model`` or the argument that does not fit."""
    kind, _, target = model.partition(":")
    if kind == "env":
        from escort_rl.config import compose
        from escort_rl.trainers.builders import build_model as build_env_model

        cfg = compose([f"env={target}", *(f"env.{a}" for a in model_args)])
        return build_env_model(cfg.env)
    module, _, name = target.partition(":")
    if kind != "class" or not module or not name.isidentifier():
        raise ValueError(f"--model: expected pkg.module:Class (or env=NAME), got {target or model!r}")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"--model: cannot import {module}:{name} ({err}); is the module on the path?") from None
    except Exception as err:  # noqa: BLE001 - the module's own code fails (a SyntaxError, an error in its body)
        raise ValueError(f"--model: cannot import {module}:{name} ({type(err).__name__}: {first_line(err)})") from None
    if not callable(cls):
        raise ValueError(f"--model: {module}:{name} is a {type(cls).__name__}, not a class; name the model's class")
    kwargs = {}
    for item in model_args:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--model-arg: '{item}' is not of the form KEY=VALUE")
        if key in kwargs:
            raise ValueError(f"--model-arg: {key} is given twice; give each keyword once")
        kwargs[key] = _parse_value(value)
    try:
        built = cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise ValueError(f"--model-arg: {name}({', '.join(kwargs)}) failed: {first_line(err)}; check the keywords and "
                         "values against the class") from None
    check_user_model(built)
    return built


def check_user_model(model) -> None:
    """The model protocol's probe (:func:`~escort_rl.models.check_model`) on a model built from
    ``--model``, before any cell runs: ``ValueError`` with the probe's line naming the method."""
    from escort_rl.models import check_model

    try:
        check_model(model)
    except TypeError as err:
        raise ValueError(str(err)) from None


def model_label(model: str, model_args: tuple = ()) -> str:
    """A short file-safe name of a model spec, for cell keys and titles."""
    raw = model.split(":")[-1] + ("-" + "-".join(model_args) if model_args else "")
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", raw.replace("model.", ""))[:80]


def frontier_filter(method: str, num_steps: int = 0, compile: bool = False, filter_args: tuple = ()):
    """The filter of a frontier row: SIR, EnKF, SVGD or ESCORT (its class defaults), with
    ``K = num_steps`` and ``compile`` for the iterative two, and ``filter_args`` (``key=value``
    strings, a variant's settings) as keyword arguments."""
    if method not in FILTER_METHODS:
        raise ValueError(f"--methods: unknown filter '{method}'; choose from {', '.join(FILTER_METHODS)}")
    cls = registry.resolve("filter", method)
    kwargs = dict(num_steps=int(num_steps), compile=bool(compile)) if method in ITERATIVE else {}
    for item in filter_args:
        key, _, value = item.partition("=")
        kwargs[key] = _parse_value(value, "--variant")
    try:
        return cls(**kwargs)
    except TypeError as err:
        raise ValueError(f"--variant: {cls.__name__} does not take {sorted(kwargs)} ({err})") from None
    except ValueError as err:
        if not filter_args:
            raise
        raise ValueError(f"--variant: {err}") from None


VARIANT_SYNTAX = "--variant NAME filter=METHOD filter.KEY=VALUE [filter.KEY=VALUE ...]"


def parse_variant(item) -> tuple[str, str, tuple]:
    """``--variant NAME filter=METHOD filter.KEY=VALUE ...`` (the option's words, a list) ->
    ``(name, method, ("KEY=VALUE", ...))``: a filter of the frontier with its own settings, swept over
    ``METHOD``'s N (and K), e.g. ``escort_stop filter=escort filter.stop_tolerance=0.05`` or
    ``enkf_loc filter=enkf filter.localisation_radius=2``."""
    name, overrides = item[0], list(item[1:])
    methods = [o.split("=", 1)[1] for o in overrides if o.startswith("filter=")]
    items = tuple(o[len("filter."):] for o in overrides if o.startswith("filter.") and "=" in o)
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
        raise ValueError(f"--variant: the name {name!r} must be a letter, then letters, digits or '_' (it names "
                         "the row and its cells), e.g. escort_eps002")
    if len(methods) != 1 or methods[0] not in FILTER_METHODS \
            or not items or len(items) + 1 != len(overrides):
        raise ValueError(f"--variant: expected {VARIANT_SYNTAX} with METHOD one of {', '.join(FILTER_METHODS)}, "
                         f"got {' '.join(item)!r}")
    if name in FILTER_METHODS:
        raise ValueError(f"--variant: the name '{name}' is a filter's own; choose another")
    return name, methods[0], items


@dataclass(frozen=True)
class FrontierReferenceCell(ReferenceCell):
    """The SIR reference posterior (:class:`~escort_rl.bench.reference_cell.ReferenceCell`) of a frontier
    model: ``domain`` is the model's label, ``model_spec``/``model_args`` build it."""

    model_spec: str = ""
    model_args: tuple = ()
    exact: bool = False
    """The model's exact posterior (a Gaussian sum, :func:`~escort_rl.metrics.reference.exact_reference`),
    computed once and saved, instead of SIR with ``particles``."""

    def model(self):
        return frontier_model(self.model_spec, tuple(self.model_args))

    def spec(self) -> dict:
        spec = super().spec()
        if not self.exact:  # a SIR reference keeps the spec (and saved file) it had before exact ones
            spec.pop("exact")
        return spec

    def posterior(self, model, traj: dict, seeds: list[int]) -> dict:
        if self.exact:
            return exact_reference(model, traj, seeds, self.sample, self.base_seed, name=self.domain)
        return super().posterior(model, traj, seeds)


@dataclass(frozen=True)
class FrontierCell(Cell):
    """One filter at one cost on the shared trajectories of ``seeds`` (one batch ``[S, N, d]``).

    Returns ``per_seed``: each distance to the reference (``<part>/<metric>``, :meth:`Reference.compare`)
    averaged over steps 1..T, per seed; ``timing``: the wall-clock of the updates after the first (the
    first warms up, and compiles with ``compile``), as seconds per update of one belief (the batch's
    time over its ``S`` beliefs); ``failed`` when the belief diverged.

    Examples:
        >>> cell = FrontierCell(model="env:linear_gaussian", method="enkf", particles=50, seeds=(0, 1), steps=3)
        >>> out = cell.run()
        >>> sorted(out["per_seed"])[:2], len(out["per_seed"]["position/mean"])
        (['position/cov', 'position/mean'], 2)
    """

    model: str
    method: str
    particles: int
    seeds: tuple
    steps: int
    num_steps: int = 0
    compile: bool = False
    model_args: tuple = ()
    base_seed: int = 0
    reference: tuple = ()
    """``(file, hash)`` of the SIR reference (:class:`FrontierReferenceCell`); empty for an exact one."""
    reference_folder: str = ""
    variant: str = ""
    """The row's name when it is a variant of ``method`` (:func:`parse_variant`); empty for the filter itself."""
    filter_args: tuple = ()
    """The variant's ``key=value`` settings."""

    def key(self) -> str:
        k = f"-K{self.num_steps}" if self.method in ITERATIVE else ""
        return (f"frontier/{model_label(self.model, self.model_args)}/{self.variant or self.method}/"
                f"N{self.particles}{k}-T{self.steps}-seeds{self.seeds[0]}-{self.seeds[-1]}")

    def spec(self) -> dict:
        spec = super().spec()
        spec.pop("reference_folder")
        if not self.variant:  # a filter's own rows keep the spec (and saved cells) they had before variants
            spec.pop("variant")
            spec.pop("filter_args")
        return spec

    def load_reference(self, model, traj: dict, seeds: list[int]) -> Reference:
        if not self.reference:
            if not has_exact_posterior(model):
                raise ValueError(f"{self.key()}: the model has no exact posterior and no reference file was given")
            return Reference(exact_reference(model, traj, seeds, base_seed=self.base_seed,
                                             name=model_label(self.model, self.model_args)))
        file, digest = self.reference
        ref = Reference.load(Path(self.reference_folder) / file, digest)
        if ref.data["input_hashes"] != list(traj["hashes"]):
            raise RuntimeError(f"{self.key()}: its reference posterior was computed on other trajectories")
        return ref

    def run(self) -> dict:
        from escort_rl.belief.seeding import derived_seed, initial_beliefs
        from escort_rl.bench.trajectories import belief_failures, generate_trajectories

        model = frontier_model(self.model, tuple(self.model_args))
        seeds = list(self.seeds)
        traj = generate_trajectories(model, self.steps, seeds, self.base_seed)
        ref = self.load_reference(model, traj, seeds)
        filt = frontier_filter(self.method, self.num_steps, self.compile, self.filter_args)
        belief, _ = initial_beliefs(filt, model, seeds, self.particles, self.base_seed)
        g = torch.Generator().manual_seed(derived_seed("filter", self.base_seed, seeds[0]))
        series, seconds, failed = [], 0.0, None
        for t in range(self.steps):
            t0 = time.perf_counter()
            try:
                belief = filt.update(model, belief, traj["actions"][:, t], traj["observations"][:, t], g)
            except belief_failures() as err:
                failed = {"step": t + 1, "message": str(err).splitlines()[0]}
                break
            if t > 0:
                seconds += time.perf_counter() - t0
            series.append(ref.compare(belief.particles.detach(), belief.log_weights.detach(), t + 1))
        out = {"failed": failed, "importance": filt.importance_diagnostics(),
               "timing": {"seconds_per_update": seconds / max(self.steps - 1, 1) / len(seeds)}}
        if failed is None:
            out["per_seed"] = {k: torch.stack([s[k] for s in series], 1).mean(1).tolist() for k in series[0]}
        return out
