"""Fixtures the benchmarks and the tests share: the thesis set-up on the shipped config, the
simulated CNC behind its real front-ends, daemon configurations, journals of a run."""
