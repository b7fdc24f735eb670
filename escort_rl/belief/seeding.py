"""Seeded priors of several beliefs stacked in one batch, and what makes them reproducible: one
random stream per kind and seed (:func:`derived_seed`), so a seed's draws do not depend on which
other seeds share its batch, and a hash of tensors' bytes (:func:`tensor_hash`) that proves it."""

from __future__ import annotations

import hashlib

import torch

from escort_rl.belief.particle_belief import ParticleBelief

__all__ = ["derived_seed", "tensor_hash", "initial_beliefs"]


def derived_seed(kind: str, base_seed: int, seed: int) -> int:
    """A 63-bit seed for ``kind`` (``trajectory``, ``belief``, ``filter``) of one seed: the streams
    never overlap, so no prior particle copies the true start state."""
    digest = hashlib.sha256(f"escort-rl/domains/{kind}/{base_seed}/{seed}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def tensor_hash(*tensors: torch.Tensor) -> str:
    """SHA-256 (first 16 hex digits) of the tensors' bytes, shapes and dtypes."""
    h = hashlib.sha256()
    for t in tensors:
        t = t.detach().cpu().contiguous()
        h.update(f"{tuple(t.shape)}{t.dtype}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()[:16]


def initial_beliefs(filt, model, seeds: list[int], n: int, base_seed: int = 0, kind: str = "belief"):
    """The prior of each seed, drawn by ``filt.init`` with the seed's own generator (the stream
    ``kind``), stacked into one ``ParticleBelief`` with particles ``[B, n, d]``; and the per-seed
    hashes of the particles."""
    parts = []
    for s in seeds:
        g = torch.Generator().manual_seed(derived_seed(kind, base_seed, s))
        b = filt.init(model, (), n, g)
        parts.append((b.particles, b.log_weights))
    particles = torch.stack([p for p, _ in parts])
    log_w = torch.stack([w for _, w in parts])
    return ParticleBelief(particles, log_w), [tensor_hash(p) for p, _ in parts]

