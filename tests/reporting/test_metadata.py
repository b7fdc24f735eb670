"""Every result records what it was measured with: the commit, the library versions, the hardware."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import torch
import torchrl

import escort_rl
from escort_rl.reporting.metadata import run_metadata, with_metadata
from escort_rl.reporting.paths import write_results

ROOT = Path(escort_rl.__file__).resolve().parent.parent


def test_the_metadata_names_the_commit_versions_and_hardware():
    meta = run_metadata()
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:  # a git checkout (CI runs on a clone)
        assert meta["commit"] == head.stdout.strip() and isinstance(meta["dirty"], bool)
    assert meta["versions"]["torch"] in (torch.__version__, torch.__version__.split("+")[0])
    assert meta["versions"]["torchrl"] == torchrl.__version__
    assert meta["versions"]["escort-rl"] == escort_rl.__version__
    assert meta["cpu"] and meta["cpu_count"] >= 1
    assert (meta["gpu"] is None) == (not torch.cuda.is_available())
    json.dumps(meta)  # plain JSON values


def test_every_written_result_carries_it(tmp_path, capsys):
    write_results(tmp_path, "demo", {"rows": [1, 2]}, "# demo\n")
    saved = json.loads((tmp_path / "demo.json").read_text())
    assert saved["rows"] == [1, 2] and saved["run"]["versions"]["torch"]
    assert with_metadata([3])["rows"] == [3]
