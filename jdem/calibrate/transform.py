"""The bounded transform of the fitted parameters: an unbounded internal
coordinate u per parameter, value = lo (hi/lo)^sigmoid(u) (log-uniform) for
lo > 0, lo + (hi - lo) sigmoid(u) otherwise, and the default bounds."""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jdem.validate import InputError

#: default bounds, absolute; other parameters get start / 5 .. start x 5 (log space)
DEFAULT_BOUNDS = {"nu": (0.0, 0.45), "phi": (0.0, np.deg2rad(60.0))}
DEFAULT_FACTOR = 5.0
def bounds_for(name, start, bounds):
    """(lo, hi) of parameter ``name``: from ``bounds``, else ``DEFAULT_BOUNDS``,
    else start / 5 .. start x 5; checked to be finite and to hold ``start``."""
    if bounds and name in bounds:
        lo, hi = (float(b) for b in bounds[name])
    elif name in DEFAULT_BOUNDS:
        lo, hi = DEFAULT_BOUNDS[name]
    else:
        lo, hi = start / DEFAULT_FACTOR, start * DEFAULT_FACTOR
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise InputError(f"bounds of {name!r} must be finite with lo < hi, got ({lo!r}, {hi!r})")
    if not lo < start < hi:
        raise InputError(f"start value of {name!r} = {start!r} is outside its bounds "
                         f"({lo!r}, {hi!r})")
    return lo, hi


def to_value(u, lo, hi):
    """Internal (unbounded) -> value: log-uniform between lo > 0 and hi, linear if lo <= 0."""
    s = jax.nn.sigmoid(u)
    if lo > 0:
        return jnp.exp(math.log(lo) + s * (math.log(hi) - math.log(lo)))
    return lo + s * (hi - lo)


def to_internal(v, lo, hi):
    """Value -> internal coordinate, the inverse of :func:`to_value`."""
    s = (math.log(v / lo) / math.log(hi / lo)) if lo > 0 else (v - lo) / (hi - lo)
    return math.log(s / (1.0 - s))


def log_space(lo):
    """Whether bounds with this lower end are log-uniform (lo > 0)."""
    return lo > 0


def dscale_du(u, lo, hi):
    """d(ln value)/du for log-space bounds, d(value)/du for linear ones."""
    s = 1.0 / (1.0 + math.exp(-u))
    return (math.log(hi / lo) if lo > 0 else hi - lo) * s * (1.0 - s)
