"""Reporting shared by trainers and benchmarks, below both layers: mean ± s.e. (:mod:`.stats`),
Markdown tables (:mod:`.tables`), report paths and the results writer (:mod:`.paths`) and figures
(:mod:`.plots`)."""
