"""The options the ``escort-rl bench`` subcommands share, each defined once, so that a name means
the same everywhere:

- ``--output DIR``: the folder the results go to (always a folder, created before any work);
- ``--seeds N``: a count (seeds ``0 .. N-1``); ``--quick``: a smoke run, flags given explicitly win;
- ``--backend``, ``--workers K``, ``--ray-address``, ``--threads T``, ``--seeds-per-cell S``: where and
  how a grid's cells run (:mod:`escort_rl.bench.core.runner`); ``--threads`` alone where a benchmark
  has no cells;
- positional ``OVERRIDE ...``: Hydra overrides (``filter.lambda_corr=0.3 filter.compile=true``);
- ``--FLAG LABEL OVERRIDE [OVERRIDE ...]``, repeatable: a labelled row or variant with its own
  overrides (:func:`add_labelled_option`).

A list of sizes has a plural, self-explaining name (``--batch-sizes``, ``--collector-workers``); a
count keeps the plain one (``--batches``). Every parser shows each option's default
(:class:`HelpFormatter`).
"""

from __future__ import annotations

import argparse
import re

from escort_rl.bench.core.runner import BACKENDS


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``argparse.ArgumentDefaultsHelpFormatter``: every option's help ends with its default; a help
    that states its default itself (``(default: ...)``, for a default that depends on other flags)
    is left as written."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "(default:" in text or "%(default)" in text:
            return text
        return super()._get_help_string(action)


class BenchParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose help shows the defaults (:class:`HelpFormatter`); the ``bench``
    subparsers are of this class, so a benchmark's ``register`` needs nothing more."""

    def __init__(self, *args, formatter_class=HelpFormatter, **kwargs) -> None:
        super().__init__(*args, formatter_class=formatter_class, **kwargs)


def add_output_option(parser, default: str | None, contents: str) -> None:
    """``--output DIR``: the folder that gets ``contents`` (e.g. ``"cost.md and cost.json"``)."""
    parser.add_argument("--output", default=default, metavar="DIR", help=f"folder for {contents}")


def add_seeds_option(parser, default: int | None, what: str = "seeds 0..N-1", shown: str | None = None) -> None:
    """``--seeds N``, a count; ``shown``: the default as the help states it, where ``default`` is
    ``None`` because it depends on other flags (``--quick``)."""
    parser.add_argument("--seeds", type=int, default=default, metavar="N",
                        help=what + (f" (default: {shown})" if shown is not None else ""))


def add_quick_option(parser, what: str) -> None:
    """``--quick``: a smoke run doing ``what``; flags given explicitly win over it."""
    parser.add_argument("--quick", action="store_true", help=f"smoke run (flags given explicitly win): {what}")


def add_threads_option(parser, help: str = "torch threads (default: torch's own choice)") -> None:
    """``--threads T`` for a benchmark without cells: torch's thread count for the whole run."""
    parser.add_argument("--threads", type=int, default=None, metavar="T", help=help)


def add_runner_options(parser, threads_help: str = "torch threads in each cell (default: 1)",
                       seeds_per_cell: bool = True) -> None:
    """The options of a benchmark that runs a grid of cells: ``--backend``, ``--workers``,
    ``--ray-address``, ``--threads`` and (``seeds_per_cell``) ``--seeds-per-cell``."""
    parser.add_argument("--backend", choices=BACKENDS, default=None,
                        help="where the cells run: inprocess, process (--workers local processes) or ray (a Ray "
                        "task per cell); every backend gives the same numbers (default: inprocess, or process "
                        "with --workers K > 1)")
    parser.add_argument("--workers", type=int, default=1, metavar="K",
                        help="local worker processes for --backend process (K > 1 implies it)")
    parser.add_argument("--ray-address", default=None, metavar="ADDRESS",
                        help="--backend ray: a running cluster, auto or HOST:PORT (default: RAY_ADDRESS, else a "
                        "local Ray)")
    add_threads_option(parser, threads_help)
    if seeds_per_cell:
        parser.add_argument("--seeds-per-cell", type=int, default=None, metavar="S",
                            help="seeds per cell, run as one batch; 1 gives the most cells to spread over a cluster; "
                            "part of each cell, so it changes the filters' noise streams (default: all seeds of a "
                            "row in one cell)")


def add_overrides_argument(parser, help: str, metavar: str = "OVERRIDE") -> None:
    """Positional Hydra overrides (``KEY=VALUE``), e.g. ``filter.lambda_corr=0.3 filter.compile=true``."""
    parser.add_argument("overrides", nargs="*", default=[], metavar=metavar, help=f"{help} (default: none)")


def add_labelled_option(parser, flag: str, what: str, example: str) -> None:
    """``flag LABEL OVERRIDE [OVERRIDE ...]``, repeatable: one labelled ``what`` with its own Hydra
    overrides; read with :func:`labelled`. ``example``: one use, shown in the help."""
    parser.add_argument(flag, action="append", nargs="+", default=[], metavar=("LABEL", "OVERRIDE"),
                        help=f"{what}; give a label, then its Hydra overrides; repeat the option for more, and give "
                        f"positional overrides before it, e.g. {flag} {example} (default: none)")


OVERRIDE = re.compile(r"[+~]?[A-Za-z_][\w./@-]*=")
"""The start of a Hydra override, ``KEY=`` (a key has no spaces)."""


def labelled(items, flag: str) -> list[tuple[str, tuple[str, ...]]]:
    """The ``(label, overrides)`` pairs of a :func:`add_labelled_option` option, checked: each a
    label that is not itself an override (``"escort K=15"`` is a label, ``filter=sir`` is not)
    followed by at least one ``KEY=VALUE``; labels unique."""
    out = []
    for item in items or ():
        label, overrides = item[0], tuple(item[1:])
        if not label.strip() or OVERRIDE.match(label):
            raise ValueError(f"{flag}: give a label first, then its overrides (LABEL KEY=VALUE ...), got "
                             f"{' '.join(item)!r}")
        bad = [o for o in overrides if "=" not in o]
        if not overrides or bad:
            raise ValueError(f"{flag}: '{label}' needs overrides of the form KEY=VALUE"
                             + (f", got '{bad[0]}'" if bad else ""))
        out.append((label, overrides))
    labels = [label for label, _ in out]
    if len(set(labels)) != len(labels):
        raise ValueError(f"{flag}: labels must differ, got {', '.join(labels)}")
    return out


def filter_overrides(overrides, allowed=None) -> tuple[tuple[str, str], ...]:
    """``["filter.num_steps=10", ...]`` -> ``(("num_steps", "10"), ...)``: positional overrides of the
    filter's keys. ``allowed``: the only keys a benchmark takes (``None``: any but the filter's name)."""
    out = []
    for item in overrides or ():
        key, sep, value = item.partition("=")
        if not sep or not key.startswith("filter.") or key == "filter.":
            raise ValueError(f"overrides: '{item}' is not a filter override filter.KEY=VALUE (e.g. "
                             "filter.num_steps=10 filter.compile=true)")
        key = key.removeprefix("filter.")
        if key in ("name", "kind"):
            raise ValueError(f"overrides: cannot set filter.{key}; pick the filters with --methods")
        if allowed is not None and key not in allowed:
            raise ValueError(f"overrides: this benchmark takes only {', '.join('filter.' + k for k in allowed)}, "
                             f"got '{item}'")
        out.append((key, value))
    return tuple(out)


def compile_override(overrides) -> bool:
    """Whether positional overrides set ``filter.compile=true`` (the only override taken by a
    benchmark that builds its filters itself); any other is an error naming it."""
    value = dict(filter_overrides(overrides, allowed=("compile",))).get("compile", "false")
    if value.lower() not in ("true", "false"):
        raise ValueError(f"overrides: filter.compile must be true or false, got '{value}'")
    return value.lower() == "true"


def given(args, *names: str) -> dict:
    """The options among ``names`` that the command line set (not ``None``), by name: what a spec's
    ``replace`` takes over its defaults.

    Example:
        >>> from argparse import Namespace
        >>> given(Namespace(seeds=3, frames=None, threads=1), "seeds", "frames", "threads")
        {'seeds': 3, 'threads': 1}
    """
    return {name: getattr(args, name) for name in names if getattr(args, name) is not None}


def set_threads(args) -> None:
    """Apply ``--threads`` (when given) to torch, for a benchmark without cells."""
    threads = getattr(args, "threads", None)
    if threads is not None:
        import torch

        torch.set_num_threads(threads)


__all__ = ["BenchParser", "HelpFormatter", "add_labelled_option", "add_output_option", "add_overrides_argument",
           "add_quick_option", "add_runner_options", "add_seeds_option", "add_threads_option", "compile_override",
           "filter_overrides", "labelled", "set_threads"]
