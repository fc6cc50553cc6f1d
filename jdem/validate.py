"""Input checks that turn bad input into errors naming the field and the value.

These run on the host (NumPy), before anything is traced, so they never slow a
jitted step.  Inside traced code use ``jnp.where`` instead.
"""
from __future__ import annotations

import numpy as np


class InputError(ValueError):
    """Bad user input; the message names the field and the offending value."""


def _first_bad(a, bad):
    idx = np.argwhere(bad)
    first = tuple(int(k) for k in idx[0]) if idx.size else ()
    value = a[first] if first else a
    return first, float(value)


def require_finite(name, value):
    a = np.asarray(value, dtype=np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        where, v = _first_bad(a, bad)
        at = f"[{', '.join(map(str, where))}]" if where else ""
        raise InputError(f"{name}{at} must be finite, got {v}")
    return a


def require_positive(name, value, allow_zero=False):
    a = require_finite(name, value)
    bad = a < 0 if allow_zero else a <= 0
    if bad.any():
        where, v = _first_bad(a, bad)
        at = f"[{', '.join(map(str, where))}]" if where else ""
        cmp = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name}{at} must be {cmp}, got {v}")
    return a


def require_range(name, value, lo, hi):
    a = require_finite(name, value)
    bad = (a < lo) | (a > hi)
    if bad.any():
        where, v = _first_bad(a, bad)
        at = f"[{', '.join(map(str, where))}]" if where else ""
        raise InputError(f"{name}{at} must lie in [{lo}, {hi}], got {v}")
    return a


def check_particle_input(pos, radius, density):
    pos = np.asarray(pos)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3):
        raise InputError(f"pos must have shape (n, 2) or (n, 3), got {pos.shape}")
    radius = np.asarray(radius)
    if radius.shape != (pos.shape[0],):
        raise InputError(f"radius must have shape ({pos.shape[0]},), got {radius.shape}")
    require_finite("pos", pos)
    require_positive("radius", radius)
    require_positive("density", density)


def check_params(params, dim=None):
    """Check every field of a :class:`jdem.state.Params` (host values only)."""
    import jax

    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(params)):
        return  # traced (inside jit / grad): checked where the values were made
    for name, value in params._asdict().items():
        require_finite(f"params.{name}", value)
    require_positive("params.dt", params.dt)
    for name in ("kn", "ks", "youngs", "bond_youngs"):
        require_positive(f"params.{name}", getattr(params, name))
    for name in ("friction", "contact_damping", "viscous_damping", "bond_tensile",
                 "bond_cohesion", "bond_tensile_strain", "bond_shear_strain",
                 "bond_damping"):
        require_positive(f"params.{name}", getattr(params, name), allow_zero=True)
    require_range("params.local_damping", params.local_damping, 0.0, 1.0)
    require_range("params.poisson", params.poisson, -1.0, 0.5)
    require_range("params.bond_poisson", params.bond_poisson, -1.0, 0.5)
    require_range("params.bond_friction_angle", params.bond_friction_angle, 0.0, np.pi / 2)
    if dim is not None and np.shape(params.gravity) != (dim,):
        raise InputError(f"params.gravity must have shape ({dim},), got {np.shape(params.gravity)}")
