"""The benchmark runner: cells, the on-disk store, the backends (in-process, processes, Ray) and the
cell-by-cell comparison. The backend tests run a tiny protocol (a) grid and require bit-identical
numbers; the Ray test needs the ``ray`` extra, which ``make test`` installs."""

from __future__ import annotations

import json
import math

import pytest

from escort_rl.bench import domains as dom
from escort_rl.bench.compare import compare_runs, differences
from escort_rl.bench.core.runner import CellStore, make_backend, run_cells, seed_blocks
from escort_rl.bench.domains import cells as domain_cells
from escort_rl.cli import main

GRID = dict(domains=["lightdark10d", "kidnapped20d"], methods=["sir", "svgd"], seeds=4, particles=10, steps=3,
            equal_time=False, seeds_per_cell=2, filter_set=(("num_steps", "2"),), reference_particles=0)


def _per_seed(result):
    return {(r["domain"], r["method"]): r["per_seed"] for r in result["rows"]}


def test_seed_blocks_and_resources():
    assert seed_blocks([0, 1, 2, 3, 4], 2) == [(0, 1), (2, 3), (4,)]
    assert seed_blocks([0, 1, 2], None) == [(0, 1, 2)]
    cpu = dom.FilterCell(domain="lightdark10d", method="sir", particles=5, steps=2, seeds=(0,), threads=3)
    gpu = dom.FilterCell(domain="lightdark10d", method="sir", particles=5, steps=2, seeds=(0,), device="cuda:0")
    assert cpu.resources() == {"num_cpus": 3, "num_gpus": 0}
    assert gpu.resources() == {"num_cpus": 1, "num_gpus": 1}


def test_a_rerun_loads_finished_cells_and_reruns_changed_ones(tmp_path, monkeypatch):
    first = dom.run_domains(dom.DomainsSpec(**GRID, output=tmp_path))
    saved = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*.json"))
    assert len(saved) == 2 * 2 * 2  # domains x methods x seed blocks

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished cell ran again")

    monkeypatch.setattr(domain_cells, "filter_trajectories", must_not_run)
    again = dom.run_domains(dom.DomainsSpec(**GRID, output=tmp_path))
    assert _per_seed(again) == _per_seed(first)
    with pytest.raises(AssertionError, match="ran again"):  # another horizon is another cell
        dom.run_domains(dom.DomainsSpec(**{**GRID, "steps": 4}, output=tmp_path))
    # a file written for another spec under the same name is not reused
    store = CellStore(tmp_path / "cells")
    cell = dom.FilterCell(domain="lightdark10d", method="sir", particles=10, steps=3, seeds=(0, 1),
                          filter_set=(("num_steps", "2"),))
    path = store.path(cell)
    saved = json.loads(path.read_text())
    saved["spec"]["particles"] = 11
    path.write_text(json.dumps(saved))
    assert store.load(cell) is None


def test_the_seed_split_is_part_of_the_cell_not_of_the_backend():
    """Trajectories and priors are per seed, so any split shares them; the prior's error (step 0)
    is the same whatever the split."""
    one = dom.run_domains(dom.DomainsSpec(**{**GRID, "seeds_per_cell": None}))
    two = dom.run_domains(dom.DomainsSpec(**GRID))
    for r1, r2 in zip(one["rows"], two["rows"]):
        assert r1["input_hashes"] == r2["input_hashes"] == one["domain_info"][r1["domain"]]["trajectory_hashes"]
        assert r1["initial_belief_hashes"] == r2["initial_belief_hashes"]
        assert r1["error_over_time"]["mean"][0] == pytest.approx(r2["error_over_time"]["mean"][0], abs=1e-12)
        assert all(math.isfinite(v) and v >= 0 for v in r2["per_seed"]["final_error"])
    assert two["seeds_per_cell"] == 2 and one["seeds_per_cell"] == 4


@pytest.mark.slow
def test_process_backend_gives_the_inprocess_numbers(tmp_path):
    here = dom.run_domains(dom.DomainsSpec(**GRID, output=tmp_path / "a"))
    there = dom.run_domains(dom.DomainsSpec(**GRID, output=tmp_path / "b"), make_backend("process", workers=2))
    assert there["backend"] == "process" and there["workers"] == 2
    assert _per_seed(there) == _per_seed(here)
    assert compare_runs(tmp_path / "a", tmp_path / "b") == (8, [])


@pytest.mark.slow
def test_ray_backend_gives_the_inprocess_numbers(tmp_path, local_ray):
    here = dom.run_domains(dom.DomainsSpec(**GRID, output=tmp_path / "a"))
    there = dom.run_domains(dom.DomainsSpec(**GRID, output=tmp_path / "b"), make_backend("ray"))
    assert there["backend"] == "ray"
    assert _per_seed(there) == _per_seed(here)
    assert compare_runs(tmp_path / "a", tmp_path / "b") == (8, [])


def test_compare_finds_a_changed_number_and_ignores_timings(tmp_path, capsys):
    dom.run_domains(dom.DomainsSpec(**{**GRID, "domains": ["lightdark10d"], "methods": ["sir"], "filter_set": ()},
                                    output=tmp_path / "a"))
    (tmp_path / "b").mkdir()
    for p in (tmp_path / "a" / "cells").rglob("*.json"):
        target = tmp_path / "b" / "cells" / p.relative_to(tmp_path / "a" / "cells")
        target.parent.mkdir(parents=True, exist_ok=True)
        saved = json.loads(p.read_text())
        saved["result"]["timing"]["seconds"] += 1.0
        target.write_text(json.dumps(saved))
    assert main(["bench", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert "2 cells agree" in capsys.readouterr().out
    saved["result"]["errors"][0][-1] += 1e-9
    target.write_text(json.dumps(saved))
    assert main(["bench", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 1
    assert "errors[0][3]" in capsys.readouterr().out
    assert main(["bench", "compare", str(tmp_path / "a"), str(tmp_path / "b"), "--tolerance", "1e-6"]) == 0
    target.unlink()
    assert main(["bench", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 1
    assert "only in A" in capsys.readouterr().out
    assert main(["bench", "compare", str(tmp_path / "a"), str(tmp_path / "b"), "--common-only"]) == 0
    assert differences({"x": float("nan")}, {"x": 1.0}) == ["x: nan != 1.0"]


def test_compare_refuses_a_folder_without_cells(tmp_path, capsys):
    """A protocol (b) output (``closed_loop.json`` and ``runs/``, no ``cells/``) holds no cell: compare
    says so in one line naming the folder instead of reading the report as a cell."""
    for run in ("a", "b"):
        (tmp_path / run / "runs" / "lightdark10d" / "sir").mkdir(parents=True)
        (tmp_path / run / "closed_loop.json").write_text(json.dumps({"protocol": "b", "rows": [{"method": "sir"}]}))
        (tmp_path / run / "runs" / "lightdark10d" / "sir" / "train.json").write_text(json.dumps({"iterations": 1}))
    assert main(["bench", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(tmp_path / "a") in err and "holds no benchmark cells" in err
    with pytest.raises(ValueError, match="^A: .* holds no benchmark cells"):
        compare_runs(tmp_path / "a", tmp_path / "b")
    cell = {"spec": {"method": "sir"}, "result": {"errors": [1.0], "timing": {"seconds": 1.0}}}
    for run in ("a", "b"):  # a cell beside the reports is compared; the reports are left out
        (tmp_path / run / "sir-0123456789.json").write_text(json.dumps(cell))
    assert compare_runs(tmp_path / "a", tmp_path / "b") == (1, [])


@pytest.mark.parametrize("flags, named", [
    (["--backend", "ray", "--workers", "2"], "--workers"),
    (["--backend", "inprocess", "--workers", "2"], "--workers"),
    (["--ray-address", "auto"], "--ray-address"),
    (["--seeds-per-cell", "0"], "--seeds-per-cell"),
])
def test_runner_flags_are_checked_with_one_line(tmp_path, capsys, flags, named):
    assert main(["bench", "domains", "--quick", "--output", str(tmp_path), *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and named in err


def test_ray_missing_is_one_line(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray":
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    cell = dom.FilterCell(domain="lightdark10d", method="sir", particles=5, steps=1, seeds=(0,))
    with pytest.raises(ValueError,
                       match=r"--backend ray: ray is not installed; install with pip install escort-rl\[ray\]"):
        run_cells([cell], make_backend("ray"))


def test_synthetic_cells_are_saved_and_a_rerun_reuses_them(tmp_path, monkeypatch):
    from escort_rl.bench import synthetic as syn

    spec = syn.SyntheticSpec(targets=["gmm1d"], methods=["oracle", "sir"], seeds=3, particles=20, num_steps=2,
                             seeds_per_cell=2, output=tmp_path)
    first = syn.run_synthetic(spec)
    assert len(list((tmp_path / "cells").rglob("*.json"))) == 2 * 2  # methods x seed blocks
    assert [len(r["per_seed"]["mmd2"]) for r in first["rows"]] == [3, 3]

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished cell ran again")

    monkeypatch.setattr(syn, "fit_particles", must_not_run)
    again = syn.run_synthetic(spec)
    assert differences([r["per_seed"] for r in again["rows"]], [r["per_seed"] for r in first["rows"]]) == []
