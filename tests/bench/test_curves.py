"""`escort-rl bench curves`: learning curves of runs side by side."""

from __future__ import annotations

import json

from escort_rl.cli import main
from escort_rl.config import compose
from escort_rl.trainers.training import train


def test_curves_of_a_dvrl_and_a_deepsets_run(tmp_path, capsys):
    small = ["trainer.iterations=2", "trainer.num_envs=2", "env.max_steps=8", "num_particles=10",
             "dvrl.module.num_particles=8"]
    train(compose([*small, "filter=sir", "trainer.warm_start_filter=null", f"output_dir={tmp_path / 'sir'}"]),
          progress=False)
    train(compose([*small, "trainer=dvrl_a2c", f"output_dir={tmp_path / 'dvrl'}"]), progress=False)
    out = tmp_path / "curves"
    assert main(["bench", "curves", str(tmp_path / "sir"), str(tmp_path / "dvrl"), "--output", str(out)]) == 0
    runs = json.loads((out / "learning_curves.json").read_text())["rows"]
    assert [r["label"] for r in runs] == ["sir + DeepSets (ppo)", "dvrl (learned belief)"]
    assert [len(r["history"]) for r in runs] == [2, 2] and "elbo" in runs[1]["history"][0]
    md = (out / "learning_curves.md").read_text()
    assert "| sir + DeepSets (ppo) |" in md and "| dvrl (learned belief) |" in md
    assert (out / "learning_curves.png").stat().st_size > 0
    capsys.readouterr()
    assert main(["bench", "curves", str(tmp_path / "nowhere"), "--output", str(out)]) == 2
    assert "nowhere" in capsys.readouterr().err


def test_legend_names_the_directory_only_where_labels_repeat():
    from escort_rl.bench.curves import legend_labels

    runs = [{"label": "dvrl", "run": "a/dvrl"}, {"label": "sir + DeepSets (ppo)", "run": "a/p1"},
            {"label": "sir + DeepSets (ppo)", "run": "b/p2"}]
    assert legend_labels(runs) == ["dvrl", "sir + DeepSets (ppo) (p1)", "sir + DeepSets (ppo) (p2)"]
