"""Fuzz campaign targets for ``benchmarks/bench_fuzz.py`` (one module per target)."""
