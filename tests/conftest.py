"""Test-suite set-up: validation runs in float64 (analytic comparisons need it).

JAX's persistent compilation cache is switched off for the suite: with it, a
worker that loaded the calibration demo's gradient program compiled by another
process (the notebook kernel or the other worker) aborted inside XLA's
``deserialize_executable`` (twice in a row, with and without the cache's file
lock), killing the worker.  Each process compiles its own programs instead.

Compiled programs are released after every test file (``jax.clear_caches``): a
worker that kept every program of the files it ran grew past 5.8 GB, and late
in the suite workers died inside XLA's compiler (SIGSEGV, SIGABRT) on a 24 GiB
machine with no swap while the other worker and a notebook kernel held theirs.
"""
import os

os.environ.setdefault("JDEM_SMALL", "1")  # notebooks and studies run their small configuration
os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)     # inherited by kernels and subprocesses
os.environ["JAX_ENABLE_COMPILATION_CACHE"] = "false"

import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Free the compiled programs of a test file once it is done."""
    yield
    jax.clear_caches()
    gc.collect()
