"""Test-suite set-up: validation runs in float64 (analytic comparisons need it).

JAX's persistent compilation cache is pointed at a fresh folder for the session
(also inherited by the notebook kernels and CLI subprocesses through the
environment): several tests compile the same programs (the demo problem's curve
and gradient in test_calibrate, test_cli and the calibration notebook), and the
cache compiles each once.  The pytest-xdist workers (``-n 2`` in pyproject's
addopts) inherit the folder from the controlling process, which removes it.
Set ``JAX_COMPILATION_CACHE_DIR`` yourself to keep a cache between runs.
"""
import atexit
import os
import shutil
import tempfile

os.environ.setdefault("JDEM_SMALL", "1")  # notebooks and studies run their small configuration
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="jdem-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)

import jax

jax.config.update("jax_enable_x64", True)
