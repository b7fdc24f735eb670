"""`escort-rl bench domains`, protocol (a) shared trajectories: tiny runs only."""

import json
import math

import pytest
import torch

from escort_rl.belief import ParticleBelief
from escort_rl.belief.seeding import initial_beliefs
from escort_rl.bench import domains as dom
from escort_rl.bench import methods as registry
from escort_rl.bench import trajectories as tr
from escort_rl.cli import main


def test_quick_cli_writes_tables_and_plots(tmp_path, capsys):
    """The quick run (3 steps here) writes JSON, markdown and one PNG per domain; every method saw
    the same trajectories and priors; errors are finite and non-negative."""
    assert main(["bench", "domains", "--quick", "--steps", "3", "--output", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "domains.json").read_text())
    assert result["domains"] == ["lightdark10d", "kidnapped20d", "mtt20d"]
    assert result["methods"] == ["escort", "svgd", "sir"]
    assert {(r["domain"], r["method"]) for r in result["rows"]} == {
        (d, m) for d in result["domains"] for m in result["methods"]}
    for d in result["domains"]:
        rows = [r for r in result["rows"] if r["domain"] == d]
        assert all(r["input_hashes"] == result["domain_info"][d]["trajectory_hashes"] for r in rows)
        assert len({tuple(r["initial_belief_hashes"]) for r in rows}) == 1
        assert len(set(result["domain_info"][d]["trajectory_hashes"])) == 2  # two seeds, two trajectories
        assert (tmp_path / f"error_over_time_{d}.png").stat().st_size > 0
    for r in result["rows"] + result["equal_time"]["rows"]:
        assert r["steps"] == 3 and len(r["error_over_time"]["mean"]) == 4
        values = r["per_seed"]["final_error"] + r["per_seed"]["mean_error"] + r["error_over_time"]["mean"]
        assert all(math.isfinite(v) and v >= 0 for v in values)
        assert r["seconds_per_step"] > 0
    assert result["equal_time"]["domains"]["mtt20d"]["chosen"]["escort"] == 30
    md = (tmp_path / "domains.md").read_text()
    for heading in ("## Final position error", "## Time-averaged position error", "## Wall-clock per filter update",
                    "## Equal wall-clock per step", "protocol (b)"):
        assert heading in md
    assert "| escort | " in md and "| lightdark10d | kidnapped20d | mtt20d |" in md
    assert "final error" in capsys.readouterr().out
    # the distances to the reference posterior (quick: 2000 particles, checked at 4000)
    for d in result["domains"]:
        info = result["reference"][d]
        assert info["particles"] == [2000, 4000] and info["seconds"]["2000"] > 0
        assert (tmp_path / f"accuracy_over_time_{d}.png").stat().st_size > 0
    for r in result["rows"] + result["equal_time"]["rows"]:
        acc = r["accuracy"]
        assert acc["references"] == [2000, 4000] and len(acc["checks"]) == 1
        assert set(acc["summary"]) == {f"{p}/{m}" for p in ("position", "velocity")
                                       for m in ("w1", "mmd2", "mean", "cov")}
        assert all(len(v["mean"]) == 4 and all(math.isfinite(x) and x >= 0 for x in v["mean"])
                   for v in acc["over_time"].values())
    for heading in ("## Distance to the reference posterior", "### sliced W1", "### MMD²",
                    "### The reference and its convergence", "at equal wall-clock: sliced W1",
                    "at equal wall-clock: MMD²", "at equal wall-clock: ‖cov − cov_ref‖_F"):
        assert heading in md


def test_a_damaged_reference_file_is_computed_again(tmp_path):
    """A reference file that no longer matches its saved cell is recomputed on the next run, and
    the rows come out the same."""
    from escort_rl.bench.domains import DomainsSpec, run_domains

    spec = DomainsSpec(domains=["lightdark10d"], methods=["sir"], seeds=2, particles=20, steps=2, equal_time=False,
                       reference_particles=200, reference_sample=20, output=tmp_path)
    first = run_domains(spec)
    files = sorted((tmp_path / "cells" / "reference-data").rglob("*.pt"))
    assert len(files) == 2  # N_ref and 2 N_ref
    files[0].write_bytes(files[0].read_bytes()[:64])
    second = run_domains(spec)
    assert second["rows"][0]["accuracy"]["summary"] == first["rows"][0]["accuracy"]["summary"]
    assert files[0].stat().st_size > 64


def test_trajectories_are_seeded_per_seed():
    model, _ = registry.build_domain("mtt20d")
    a = tr.generate_trajectories(model, 4, [0, 1, 2])
    b = tr.generate_trajectories(model, 4, [0, 1, 2])
    c = tr.generate_trajectories(model, 4, [2])
    for k in ("states", "actions", "observations"):
        assert torch.equal(a[k], b[k])
        assert torch.equal(a[k][2], c[k][0])  # a seed's trajectory does not depend on the others
    assert a["hashes"] == b["hashes"] and a["hashes"][2] == c["hashes"][0]
    assert a["states"].shape == (3, 5, 20) and a["actions"].shape == (3, 4) and a["observations"].shape[:2] == (3, 4)
    filt = registry.build_method("mtt20d", "sir")
    prior, hashes = initial_beliefs(filt, model, [0, 1, 2], 8)
    assert prior.particles.shape == (3, 8, 20) and len(set(hashes)) == 3
    assert not torch.isclose(prior.particles[:, 0], a["states"][:, 0]).all()  # independent of the true start


def test_unknown_method_is_one_line_naming_the_flag(tmp_path, capsys):
    assert main(["bench", "domains", "--methods", "sir", "nosuchfilter", "--output", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--methods" in err and "nosuchfilter" in err
    assert main(["bench", "domains", "--domains", "nowhere", "--output", str(tmp_path)]) == 2
    assert "--domains" in capsys.readouterr().err


def test_non_finite_belief_names_method_and_domain():
    x = torch.zeros(2, 3, 4)
    x[1, 0, 0] = float("nan")
    with pytest.raises(tr.NonFiniteBeliefError, match="method 'svgd' on domain 'mtt20d'.*step 5.*seeds \\[7\\]"):
        tr.check_finite(ParticleBelief.uniform(x), "svgd", "mtt20d", 5, [6, 7])


def test_a_diverged_method_is_a_failed_row_and_the_run_goes_on(monkeypatch):
    real = tr.check_finite

    def diverge_svgd(belief, method, domain, step, seeds):
        if method == "svgd" and step == 3:
            raise tr.NonFiniteBeliefError(f"method '{method}' on domain '{domain}': diverged (test)")
        real(belief, method, domain, step, seeds)

    monkeypatch.setattr(tr, "check_finite", diverge_svgd)
    result = dom.run_domains(dom.DomainsSpec(domains=["lightdark10d"], methods=["sir", "svgd", "escort"], seeds=2,
                                             particles=10, steps=4, equal_time=True, particle_grid=(10, 20),
                                             max_particles=20, calibration_steps=1, threads=1,
                                             filter_set=(("num_steps", "2"),), reference_particles=0))
    by = {r["method"]: r for r in result["rows"]}
    assert by["svgd"]["failed"]["step"] == 3 and "diverged (test)" in by["svgd"]["failed"]["message"]
    assert by["sir"]["failed"] is None and by["escort"]["failed"] is None
    assert math.isfinite(by["sir"]["summary"]["final_error"][0])
    eq = {r["method"]: r for r in result["equal_time"]["rows"]}
    assert eq["svgd"]["failed"] and eq["svgd"]["reused_equal_n"]
    md = dom.domains_markdown(result)
    assert "| svgd | failed at step 3 |" in md and "## Failed runs" in md and "diverged (test)" in md


def test_learned_belief_row_reads_the_shared_trajectories(tmp_path, monkeypatch):
    settings = registry.load_settings()
    settings["train"] = {d: {"iterations": 1, "num_envs": 2} for d in settings["train"]}
    monkeypatch.setattr(registry, "load_settings", lambda: settings)
    with pytest.raises(ValueError, match="--output"):
        dom.run_domains(dom.DomainsSpec(domains=["lightdark10d"], methods=["dvrl"], seeds=2, particles=10, steps=3,
                                        reference_particles=0))
    result = dom.run_domains(dom.DomainsSpec(domains=["lightdark10d"], methods=["sir", "dvrl"], seeds=2, particles=10,
                                             steps=4, equal_time=True, max_particles=10, calibration_steps=1,
                                             output=tmp_path, threads=1, reference_particles=0))
    rows = {r["method"]: r for r in result["rows"]}
    assert rows["dvrl"]["input_hashes"] == rows["sir"]["input_hashes"]  # the same sequences
    assert len(rows["dvrl"]["error_over_time"]["mean"]) == 5 and rows["dvrl"]["failed"] is None
    assert all(e >= 0 for e in rows["dvrl"]["per_seed"]["final_error"])
    assert [r["method"] for r in result["equal_time"]["rows"]] == ["sir"]  # no particle count to match
    assert (tmp_path / "runs" / "lightdark10d" / "dvrl" / "checkpoints").is_dir()
    assert "| DVRL (learned belief, readout) |" in dom.domains_markdown(result)


def test_explicit_flags_win_over_quick_and_the_spec_checks_its_fields(tmp_path):
    """The command line's spec: the defaults, ``--quick``'s settings under the flags given, and the
    spec's own checks, each naming the option."""
    import argparse

    parser = argparse.ArgumentParser()
    dom.register(parser.add_subparsers())

    def spec(*argv):
        return dom.spec_from_args(parser.parse_args(["domains", *argv, "--output", str(tmp_path)]))

    quick = spec("--quick", "--particles", "50", "filter.num_steps=2")
    assert (quick.particles, quick.seeds, quick.steps, quick.calibration_steps) == (50, 2, 20, 1)
    assert quick.methods == registry.QUICK_METHODS and quick.reference_particles == 2000
    assert quick.filter_set == (("num_steps", "2"),) and quick.output == tmp_path
    assert spec("--no-equal-time") == dom.DomainsSpec(output=tmp_path, equal_time=False)
    assert spec().calibration_steps == 3 and spec().reference_particles == 100_000
    b = spec("--protocol", "b", "--quick", "--train-envs", "4")
    assert (b.particles, b.steps, b.train_iterations, b.train_envs) == (20, 10, 1, 4)
    assert b.train_overrides() == {"iterations": 1, "num_envs": 4}
    full_b = spec("--protocol", "b")
    assert full_b.seeds is None and full_b.particles is None  # the yaml's episodes and N
    assert full_b.methods == tuple(registry.protocol_b_methods())
    for bad, flag in ((dict(reference_particles=-1), "--reference-particles"),
                      (dict(reference_particles=10, reference_sample=11), "--reference-sample"),
                      (dict(seeds_per_cell=0), "--seeds-per-cell"), (dict(protocol="c"), "--protocol"),
                      (dict(train_envs=2), "--train-iterations/--train-envs: only for --protocol b"),
                      (dict(protocol="b", seeds_per_cell=2), "--seeds-per-cell")):
        with pytest.raises(ValueError, match=flag):
            dom.DomainsSpec(**bad)
    with pytest.raises(ValueError, match="run_closed_loop"):
        dom.run_domains(dom.DomainsSpec.quick("b", output=tmp_path))
