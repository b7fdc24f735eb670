"""Ctrl-C during ``escort-rl train``: one line naming the iteration and the resume command, exit status
130, no traceback, and the run resumes from its last checkpoint."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

from conftest import tiny_overrides
from escort_rl.trainers.scaffold import TrainingInterrupted, caused_by_interrupt, interrupt_message


def test_sigint_during_training_prints_one_line_and_exits_130(tmp_path):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "escort_rl.cli", "train", "--quiet",
           *tiny_overrides("trainer.iterations=100000", f"output_dir={run}")]
    # a shell starts a command with SIGINT at its default; an earlier test or library of this pytest process
    # may have left it ignored, which a child inherits, and Python then installs no KeyboardInterrupt
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 300
        while not list((run / "checkpoints").glob("checkpoint-*")) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith("interrupted at iteration "), last
    assert last.endswith(f"; resume with: escort-rl train resume={run}"), last

    from escort_rl.cli import main
    from escort_rl.trainers.checkpointing import load_checkpoint

    done = load_checkpoint(run)["trainer_state"]["iteration"]
    assert main(["train", "--quiet", f"resume={run}", f"trainer.iterations={done + 1}"]) == 0
    assert load_checkpoint(run)["trainer_state"]["iteration"] == done + 1


def test_an_interrupt_wrapped_by_another_error_is_recognised():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise RuntimeError("TensorDictModule failed with operation") from inner
    except RuntimeError as err:
        assert caused_by_interrupt(err)
    assert not caused_by_interrupt(RuntimeError("plain"))
    assert issubclass(TrainingInterrupted, KeyboardInterrupt)
    assert interrupt_message(3, None, "r").startswith("interrupted at iteration 3, before the first checkpoint")
