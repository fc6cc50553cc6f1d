"""Test-suite set-up: validation runs in float64 (analytic comparisons need it).

JAX's persistent compilation cache is switched off for the suite: with it, a
worker that loaded the calibration demo's gradient program compiled by another
process (the notebook kernel or the other worker) aborted inside XLA's
``deserialize_executable`` (twice in a row, with and without the cache's file
lock), killing the worker.  Each process compiles its own programs instead.
"""
import os

os.environ.setdefault("JDEM_SMALL", "1")  # notebooks and studies run their small configuration
os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)     # inherited by kernels and subprocesses
os.environ["JAX_ENABLE_COMPILATION_CACHE"] = "false"

import jax

jax.config.update("jax_enable_x64", True)
