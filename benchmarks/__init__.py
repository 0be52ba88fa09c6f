"""Speed / memory benchmarks, run by hand: `python -m benchmarks` (or `make bench`)."""

import daemon  # noqa: F401  (first: the same single-threaded BLAS set-up as the `rumba` command)
