"""rumba-cnc daemon package."""

import os

# The identification problems are small (a few thousand rows × a few dozen columns): OpenBLAS
# threads only add contention there (3x slower on a loaded 2-core machine). Must run before
# numpy is first imported; an explicit setting in the environment wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
