"""Every ``escort-rl bench`` subcommand's options: a shared option has one name and one meaning
wherever it appears, the retired forms are gone, every option says what it does, and the help shows
the defaults."""

from __future__ import annotations

import argparse

import pytest

from escort_rl.cli import _parser

RETIRED = ("--filter-set", "--set", "--compile", "--domain")
"""Options that no subcommand has: overrides are positional (``filter.compile=true``), and a domain
option is the plural ``--domains``."""


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _bench_parsers() -> dict[str, argparse.ArgumentParser]:
    return _subparsers(_subparsers(_parser())["bench"])


BENCH = _bench_parsers()


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings if s.startswith("--") and s != "--help"}


def test_every_bench_module_registers_its_subcommands():
    assert {"throughput", "cost", "synthetic", "scaling", "domains", "decisions", "frontier", "regime-map",
            "atari"} <= set(BENCH)


@pytest.mark.parametrize("name", sorted(BENCH))
def test_shared_options_mean_the_same_everywhere(name):
    opts = _options(BENCH[name])
    if "--output" in opts:  # a folder, never a file
        out = opts["--output"]
        assert out.metavar == "DIR" and out.nargs is None, f"bench {name} --output"
        assert "file" not in out.help.split(",")[0].split("(")[0], f"bench {name} --output: {out.help}"
    if "--seeds" in opts:  # a count
        assert opts["--seeds"].type is int and opts["--seeds"].nargs is None, f"bench {name} --seeds"
    if "--quick" in opts:
        assert isinstance(opts["--quick"], argparse._StoreTrueAction), f"bench {name} --quick"
    if "--workers" in opts:  # the runner's worker processes, a count
        assert opts["--workers"].type is int and opts["--workers"].nargs is None, f"bench {name} --workers"
    if "--threads" in opts:
        assert opts["--threads"].type is int and opts["--threads"].nargs is None, f"bench {name} --threads"
    if "--backend" in opts:
        assert tuple(opts["--backend"].choices) == ("inprocess", "process", "ray"), f"bench {name} --backend"
        assert {"--workers", "--threads", "--ray-address"} <= set(opts), f"bench {name}: the runner's options"
    if "--batches" in opts:  # a count; a list of sizes is --batch-sizes
        assert opts["--batches"].type is int and opts["--batches"].nargs is None, f"bench {name} --batches"


@pytest.mark.parametrize("name", sorted(BENCH))
def test_no_retired_option(name):
    opts = _options(BENCH[name])
    assert not [o for o in RETIRED if o in opts], f"bench {name}"
    assert BENCH[name].get_default("output_is_file") is None, f"bench {name}: --output names a file"


def test_one_name_for_the_domain_option():
    assert not any("--domain" in _options(p) for p in BENCH.values())
    assert any("--domains" in _options(p) for p in BENCH.values())


@pytest.mark.parametrize("name", sorted(BENCH))
def test_every_option_has_help_and_the_help_shows_its_default(name):
    parser = BENCH[name]
    assert issubclass(parser.formatter_class, argparse.ArgumentDefaultsHelpFormatter), f"bench {name}"
    formatter = parser._get_formatter()
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        what = "/".join(action.option_strings) or action.dest
        assert action.help and action.help.strip(), f"bench {name} {what}: no help"
        if action.required:  # a required argument has no default to show
            continue
        shown = formatter._get_help_string(action)
        assert "%(default)" in shown or "(default:" in shown, f"bench {name} {what}: the help hides the default"
    assert "(default:" in parser.format_help()


def test_top_level_commands_show_their_defaults_and_current_help():
    parsers = _subparsers(_parser())
    for name, parser in parsers.items():
        assert issubclass(parser.formatter_class, argparse.ArgumentDefaultsHelpFormatter), name
        for action in parser._actions:
            if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                assert action.help, f"{name} {action.dest}: no help"
    top = _parser().format_help()
    assert "REINFORCE" not in top and "trainer=ppo" in top
    assert "scripted controller" in top


def test_labelled_rows_and_filter_overrides_are_checked():
    from escort_rl.bench.core.options import compile_override, filter_overrides, labelled

    assert labelled([["mine", "filter=sir", "num_particles=50"]], "--add-row") == [
        ("mine", ("filter=sir", "num_particles=50"))]
    assert labelled([["escort K=15", "filter=escort"]], "--add-row")[0][0] == "escort K=15"
    for bad in (["mine"], ["filter=sir"], ["mine", "sir"], ["+filter.x=1", "filter=sir"]):
        with pytest.raises(ValueError, match="--add-row"):
            labelled([bad], "--add-row")
    with pytest.raises(ValueError, match="labels must differ"):
        labelled([["a", "filter=sir"], ["a", "filter=svgd"]], "--add-row")
    assert filter_overrides(["filter.num_steps=10"]) == (("num_steps", "10"),)
    with pytest.raises(ValueError, match="overrides: 'num_steps=10'"):
        filter_overrides(["num_steps=10"])
    assert compile_override(["filter.compile=true"]) and not compile_override([])
    with pytest.raises(ValueError, match="filter.compile"):
        compile_override(["filter.lambda_corr=0.3"])
