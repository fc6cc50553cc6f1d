"""Test-suite set-up: validation runs in float64 (analytic comparisons need it)."""
import os

os.environ.setdefault("JDEM_SMALL", "1")  # notebooks and studies run their small configuration

import jax

jax.config.update("jax_enable_x64", True)
