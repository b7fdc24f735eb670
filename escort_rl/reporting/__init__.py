"""Reporting shared by trainers and benchmarks: figures (below both layers)."""
