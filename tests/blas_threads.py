"""OpenBLAS on one thread in a pytest-xdist worker's own process (``tests/conftest.py`` imports this
first, before anything imports numpy): two workers on two cores, each with OpenBLAS's threads
spinning for work, made numpy-heavy tests up to ten times slower (a PPCA pass 11 s instead of 1).
The processes the tests start get the environment as it was: a daemon or a command in a subprocess
runs with OpenBLAS as it does in a serial run."""

from __future__ import annotations

import os
import sys

if os.environ.get("PYTEST_XDIST_WORKER") and "OPENBLAS_NUM_THREADS" not in os.environ:
    if "numpy" in sys.modules:
        raise AssertionError("numpy was imported before tests/blas_threads.py could set its threads")
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    try:
        import numpy  # noqa: F401  (OpenBLAS reads its thread count when numpy loads it)
    finally:
        del os.environ["OPENBLAS_NUM_THREADS"]
