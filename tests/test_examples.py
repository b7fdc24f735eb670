"""The examples run as a user would run them, at their tiny default budget."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def test_the_custom_model_example_trains_evaluates_and_loads_its_policy(tmp_path):
    out = subprocess.run([sys.executable, str(EXAMPLES / "custom_model.py"), "--output", str(tmp_path / "heater")],
                         capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    trained = next(line for line in lines if line.startswith("trained: return "))
    assert trained.endswith("success None")  # the heater has no goal: the return alone
    assert any(line.startswith("policy reads ['particles', 'particle_log_weights']") for line in lines)
    assert (tmp_path / "heater" / "model.pt").is_file()


def test_the_fit_example_recovers_the_noise_within_ten_percent_of_kalmans_mle(tmp_path):
    """examples/fit_model.py: gradient ascent on the differentiable SIR filter's log-evidence from 50 logged
    trajectories lands within 10% of the Kalman maximum-likelihood estimate (the script exits non-zero if not)."""
    out = subprocess.run([sys.executable, str(EXAMPLES / "fit_model.py")], capture_output=True, text=True,
                         cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stdout[-1000:] + out.stderr[-2000:]
    last = out.stdout.splitlines()[-1]
    assert last.startswith("largest relative difference from Kalman's MLE: ")
    assert float(last.split(": ")[1].rstrip("%")) <= 10.0
