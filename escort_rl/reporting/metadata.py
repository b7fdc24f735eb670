"""What a result was measured with: the commit, the library versions and the hardware, recorded in
every benchmark's and evaluation's JSON (under ``"run"``)."""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

LIBRARIES = ("escort-rl", "torch", "torchrl", "tensordict", "numpy", "gymnasium", "hydra-core")


def git_commit(where: Path | None = None) -> dict:
    """``{"commit": sha or None, "dirty": bool or None}`` of the checkout the package runs from
    (``None`` outside a git checkout, e.g. an installed wheel)."""
    root = Path(where or Path(__file__).resolve().parents[2])

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    sha = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if sha else None
    return {"commit": sha, "dirty": None if status is None else bool(status)}


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_metadata() -> dict:
    """The commit, library versions, Python, CPU (name and cores), GPU (``None`` without CUDA),
    torch's thread count and the UTC time, as plain JSON values.

    Examples:
        >>> meta = run_metadata()
        >>> sorted(meta)
        ['commit', 'cpu', 'cpu_count', 'dirty', 'gpu', 'python', 'threads', 'time', 'versions']
    """
    import torch

    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {**git_commit(), "versions": versions, "python": platform.python_version(), "cpu": cpu_name(),
            "cpu_count": os.cpu_count(), "gpu": gpu, "threads": torch.get_num_threads(),
            "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def with_metadata(result) -> dict:
    """``result`` with the run's metadata under ``"run"``: a mapping gains the key, a list becomes
    ``{"rows": result, "run": ...}``."""
    meta = run_metadata()
    return {**result, "run": meta} if isinstance(result, dict) else {"rows": result, "run": meta}
